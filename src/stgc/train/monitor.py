"""Run logs: JSON-lines files (metrics, compaction events), a progress bar, optional TensorBoard."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from tqdm import tqdm

from stgc.fileio import atomic_open, output_error


class JsonLines:
    """Append-only JSON-lines log. On resume, entries past the checkpoint's iteration are dropped, because the
    resumed run writes them again (a killed run may have logged beyond its last checkpoint)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)

    def truncate_after(self, iteration: int) -> None:
        if not self.path.exists():
            return
        kept = []
        for line in self.path.read_text().splitlines():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                continue  # a line cut short by the kill
            if int(row.get("iteration", 0)) <= iteration:
                kept.append(line)
        with atomic_open(self.path) as f:
            f.write("".join(k + "\n" for k in kept))

    def clear(self) -> None:
        if self.path.exists():
            self.path.unlink()

    def append(self, row: dict[str, Any]) -> None:
        # One write of a whole line per call: a kill leaves at most one partial last line, which readers skip.
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with open(self.path, "a") as f:
                f.write(json.dumps(row) + "\n")
                f.flush()
                os.fsync(f.fileno())
        except OSError as exc:
            raise output_error(self.path, exc) from None

    def read(self) -> list[dict[str, Any]]:
        if not self.path.exists():
            return []
        rows = []
        for line in self.path.read_text().splitlines():
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError:
                continue
        return rows


class Progress:
    """tqdm progress bar (or nothing) with the running loss, PSNR and number of Gaussians."""

    def __init__(self, total: int, initial: int, enabled: bool):
        self.bar = None
        if enabled:

            self.bar = tqdm(total=total, initial=initial, unit="it", dynamic_ncols=True, smoothing=0.05)

    def update(self, loss: float, psnr: float, num_gaussians: int) -> None:
        if self.bar is not None:
            self.bar.update(1)
            if self.bar.n % 10 == 0:
                self.bar.set_postfix(loss=f"{loss:.4f}", psnr=f"{psnr:.2f}", G=num_gaussians, refresh=False)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


class TensorBoard:
    """TensorBoard scalars when `torch.utils.tensorboard` (the tensorboard package) is importable; else a no-op.
    `first_step`: the first iteration this writer logs; events a killed run left at or after it are purged, as
    metrics.jsonl is truncated on resume (else its curves would hold both runs' points)."""

    def __init__(self, log_dir: str | Path, enabled: bool, first_step: int = 1):
        self.writer = None
        if enabled:
            try:
                from torch.utils.tensorboard import SummaryWriter
            except Exception:  # tensorboard is optional
                return
            self.writer = SummaryWriter(log_dir=str(log_dir), purge_step=first_step)

    def scalars(self, iteration: int, values: dict[str, float]) -> None:
        if self.writer is not None:
            for key, value in values.items():
                if isinstance(value, (int, float)):
                    self.writer.add_scalar(key, value, iteration)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
