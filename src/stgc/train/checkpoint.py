"""The resumable training checkpoint RUN/checkpoint.pt.

It holds everything that the next iteration depends on: the model's parameters and decoder, Adam's state, the
iteration, the densification accumulators, the compaction controller and EMS state, the python/numpy/torch RNG
states, and the fingerprint of the options it was trained with (the trainer resumes it under those options only).
The trainer draws its random numbers from per-iteration streams seeded by (seed, iteration), so a resumed
run replays exactly the draws an uninterrupted one would have made.
"""

from __future__ import annotations

import random
from pathlib import Path
from typing import Any

import numpy as np
import torch

from stgc.errors import FormatError
from stgc.fileio import atomic_open
from stgc.run import Run

CHECKPOINT_FORMAT = "stgc-train-checkpoint"
CHECKPOINT_VERSION = 1
# The sha256 of the options that decide what the run trains (`stgc.train.loop.run_options`), and those options by
# dotted name (to name what differs when a resume is refused). A checkpoint written before they were kept has none.
OPTIONS_FINGERPRINT = "options_fingerprint"
OPTIONS = "options"


def rng_states() -> dict[str, Any]:
    return {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state()}


def restore_rng_states(states: dict[str, Any]) -> None:
    random.setstate(states["python"])
    np.random.set_state(states["numpy"])
    torch.set_rng_state(states["torch"])


def save_checkpoint(run_dir: str | Path, payload: dict[str, Any]) -> Path:
    """Write RUN/checkpoint.pt atomically (a kill during the write leaves the previous checkpoint intact)."""
    path = Run(run_dir).checkpoint_path
    _write(path, {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "rng": rng_states(), **payload})
    return path


def _write(path: Path, data: dict[str, Any]) -> None:
    with atomic_open(path, "wb") as f:  # a Python file: a failed write raises OSError with its cause
        torch.save(data, f)


def copy_checkpoint(source_dir: str | Path, out_dir: str | Path, fingerprint: str, options: dict[str, Any]) -> Path:
    """Write RUN `source_dir`'s checkpoint as OUT `out_dir`'s, atomically, marked as trained with `options` (whose
    fingerprint is `fingerprint`): a fine-tuning starts from its source's state under its own options. Returns the
    path written."""
    data = load_checkpoint(source_dir)
    data.update({OPTIONS_FINGERPRINT: fingerprint, OPTIONS: options})
    path = Run(out_dir).checkpoint_path
    _write(path, data)
    return path


def load_checkpoint(run_dir: str | Path) -> dict[str, Any]:
    """Read RUN/checkpoint.pt; raises FormatError when it is missing, unreadable or not ours."""
    path = Run(run_dir).checkpoint_path
    if not path.is_file():
        raise FormatError(path, "no checkpoint to resume from (was the run started with checkpointing?)")
    try:
        # Our own file: it contains python RNG state (tuples) and numpy arrays, so full unpickling is needed.
        data = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # torch raises many types for corrupt files
        raise FormatError(path, f"cannot read checkpoint ({type(exc).__name__}: {exc})") from None
    if not isinstance(data, dict) or data.get("format") != CHECKPOINT_FORMAT:
        raise FormatError(path, "not an stgc training checkpoint")
    if data.get("version") != CHECKPOINT_VERSION:
        raise FormatError(path, f"checkpoint version {data.get('version')} (this stgc reads {CHECKPOINT_VERSION})")
    return data
