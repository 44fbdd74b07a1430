"""A run directory: what belongs to a run, and starting a new one without mixing it with an old one.

A run directory holds the files of ONE training: its config, logs, checkpoint, saved iterations and evaluation
records. Starting a new run where an old one lies would leave the old `point_cloud/iteration_*` beside the new
config, and every later verb would read the stale model under the new run's name. So a new run refuses a
directory that already holds a run, unless the caller resumes it or asks to overwrite it (which removes the old
run's files, and only those: other files in the folder, such as an experiment's notes or logs, stay).
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path

from stgc.errors import StgcError

# Everything a training writes into its run directory (docs/training.md lists them): their presence means the
# folder holds a run.
RUN_FILES = (
    "config.json",
    "metrics.jsonl",
    "compaction.jsonl",
    "checkpoint.pt",
    "train_summary.json",
    "eval.json",
    "eval_per_view.csv",
    "compaction.png",
)
RUN_FOLDERS = ("point_cloud", "tensorboard")
# What later verbs derive from the run's model and keep beside it: bitstreams and their evaluations, evaluations on
# other data. They describe the old model, so replacing the run removes them too.
DERIVED_PATTERNS = ("*.stgc", "eval_*.json", "eval_*_per_view.csv")


# RUN/point_cloud/iteration_<N>/point_cloud.ply: one saved model per N (official layout).
_ITERATION_DIR = re.compile(r"^iteration_(\d+)$")
SAVED_MODEL = "point_cloud.ply"


def saved_iterations(run_dir: str | Path) -> dict[int, Path]:
    """{N: RUN/point_cloud/iteration_<N>} for every iteration whose PLY is there."""
    root = Path(run_dir) / "point_cloud"
    found: dict[int, Path] = {}
    if root.is_dir():
        for child in root.iterdir():
            match = _ITERATION_DIR.match(child.name)
            if match and (child / SAVED_MODEL).is_file():
                found[int(match.group(1))] = child
    return found


def latest_iteration_dir(run_dir: str | Path) -> Path | None:
    """The saved iteration with the largest N (the one rule every verb uses for "the run's model"), or None."""
    found = saved_iterations(run_dir)
    return found[max(found)] if found else None


def iteration_of(path: str | Path) -> int | None:
    """The training iteration a model path refers to: an iteration dir (or a file in it), or a run dir's latest."""
    path = Path(path)
    for candidate in (path, path.parent):
        match = _ITERATION_DIR.match(candidate.name)
        if match:
            return int(match.group(1))
    found = saved_iterations(path)
    return max(found) if found else None


class RunExistsError(StgcError):
    """The output directory already holds a run and neither resume nor overwrite was asked for."""


def run_contents(path: Path) -> list[Path]:
    """The run files and folders present in `path` (empty when it holds no run)."""
    return [path / name for name in (*RUN_FILES, *RUN_FOLDERS) if (path / name).exists()]


def prepare_new_run(path: str | Path, *, overwrite: bool = False, keep: Path | None = None) -> Path:
    """Make `path` ready for a new run: create it, or refuse (RunExistsError) when it already holds one, unless
    `overwrite` (then the old run's files, and the bitstreams and evaluations derived from it, are removed first;
    `keep` is spared: the input being restored there). Clear errors when `path` cannot be a directory."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise StgcError(f"{path}: exists and is not a directory")
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise StgcError(f"{path}: its parent {parent} is a file, not a directory")
            break
    existing = run_contents(path) if path.is_dir() else []
    if existing and not overwrite:
        names = ", ".join(p.name for p in existing[:4]) + (", ..." if len(existing) > 4 else "")
        raise RunExistsError(f"{path}: already holds a run ({names}); use --resume to continue it or --overwrite to "
                             "replace it")
    if overwrite and path.is_dir():
        spared = keep.resolve() if keep is not None else None
        existing += [p for pattern in DERIVED_PATTERNS for p in path.glob(pattern) if p.resolve() != spared]
    for item in existing:
        if item.is_dir():
            shutil.rmtree(item)
        else:
            item.unlink()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StgcError(f"{path}: cannot create the run directory ({exc.strerror or exc})") from None
    return path
