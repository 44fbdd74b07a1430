"""Plot of a run's compaction log: pruning ratio, smoothed loss and Gaussian count over iterations."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from stgc.errors import DataError
from stgc.fileio import atomic_path

LOG_NAME = "compaction.jsonl"


def read_compaction_log(run_dir_or_jsonl: str | Path) -> list[dict[str, Any]]:
    """The pruning-step records of RUN/compaction.jsonl (or of the given .jsonl file), in file order."""
    path = Path(run_dir_or_jsonl)
    if path.is_dir():
        path = path / LOG_NAME
    if not path.is_file():
        raise DataError(path, "no compaction log (was the run trained with compaction.method st-knn or reference?)")
    records = []
    with open(path, encoding="utf-8") as f:
        lines = f.readlines()
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except json.JSONDecodeError as err:
            if number == len(lines) and not line.endswith("\n"):
                break  # the last line of a run killed mid-write (the trainer rewrites it on resume)
            raise DataError(path, f"line {number} is not JSON ({err.msg})") from None
        if not isinstance(record, dict) or "iteration" not in record:
            raise DataError(path, f"line {number} is not a pruning-step record (no 'iteration')")
        iteration = record["iteration"]
        if isinstance(iteration, bool) or not isinstance(iteration, int) or iteration < 0:
            raise DataError(path, f"line {number}: iteration {iteration!r} is not a non-negative integer")
        for key in ("ratio", "smoothed_loss", "gaussians_left", "removed"):
            value = record.get(key)
            if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))):
                raise DataError(path, f"line {number}: {key} {value!r} is not a number")
        records.append(record)
    if not records:
        raise DataError(path, "no pruning steps logged")
    return records


# What the ratio controller compared between steps, by the records' `loss_signal` (older logs have none: training).
_LOSS_LABELS = {"training": "smoothed training loss", "probe": "probe loss\n(fixed training views and times)",
                "probe_psnr": "probe MSE\n(geometric mean over the views)",
                "prune_damage": "PSNR the prunes cost\nthe probe views so far (dB)"}


def loss_label(records: list[dict[str, Any]]) -> str:
    """The y label of the loss panel: the signal the run's controller compared."""
    signals = {str(r.get("loss_signal", "training")) for r in records}
    if len(signals) == 1 and (signal := signals.pop()) in _LOSS_LABELS:
        return _LOSS_LABELS[signal]
    return "controller's loss (" + ", ".join(sorted(signals)) + ")"


def plot_compaction(run_dir_or_jsonl: str | Path, out_png: str | Path) -> Path:
    """Write a PNG of ratio, smoothed loss and #Gaussians against iteration (with a loss reference, also the loss
    above the reference's against the budget); returns its path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    records = read_compaction_log(run_dir_or_jsonl)
    iterations = [r["iteration"] for r in records]

    def series(key: str) -> list[float]:
        return [float("nan") if r.get(key) is None else float(r[key]) for r in records]

    referenced = any(r.get("reference_loss") is not None for r in records)
    rows = 4 if referenced else 3
    fig, axes = plt.subplots(rows, 1, figsize=(7, 2.5 * rows), sharex=True)
    axes[0].step(iterations, series("ratio"), where="post", color="tab:blue")
    axes[0].set_ylabel("pruning ratio\n(of matched pairs)")
    axes[1].plot(iterations, series("smoothed_loss"), marker=".", color="tab:red", label="this run")
    if referenced:
        axes[1].plot(iterations, series("reference_loss"), color="black", linestyle="--",
                     label="the unpruned reference run")
        axes[1].legend(loc="upper right", fontsize="small")
        axes[1].set_yscale("log")
        # What the budget holds: the loss above the unpruned run's at the same iteration, as a fraction.
        damage = [float("nan") if r.get("reference_loss") in (None, 0) or r.get("smoothed_loss") is None
                  else float(r["smoothed_loss"]) / float(r["reference_loss"]) - 1.0 for r in records]
        axes[2].plot(iterations, damage, marker=".", color="tab:purple")
        budgets = {float(r["loss_budget"]) for r in records if r.get("loss_budget")}
        for budget in budgets:
            axes[2].axhline(budget, color="black", linestyle=":", label=f"budget {budget:.3f}")
        if budgets:
            axes[2].legend(loc="upper left", fontsize="small")
        axes[2].set_ylabel("loss / reference - 1")
    if any(r.get("damage_allowed_db") is not None for r in records):
        axes[1].plot(iterations, series("damage_allowed_db"), color="black", linestyle=":",
                     label="allowed by now (the budget spread over the steps)")
        axes[1].legend(loc="upper left", fontsize="small")
    axes[1].set_ylabel(loss_label(records))
    axes[-1].plot(iterations, series("gaussians_left"), marker=".", color="tab:green")
    axes[-1].set_ylabel("Gaussians")
    axes[-1].set_xlabel("iteration")
    for ax in axes:
        ax.grid(True, alpha=0.3)
    source = Path(run_dir_or_jsonl)
    removed = sum(int(r.get("removed", 0)) for r in records)
    axes[0].set_title(f"ST-KNN compaction: {source.name}\n{len(records)} steps, {removed} removed", fontsize="medium")
    fig.tight_layout()
    out_png = Path(out_png)
    try:
        with atomic_path(out_png) as tmp:
            fig.savefig(tmp, format="png", dpi=110)
    finally:
        plt.close(fig)
    return out_png
