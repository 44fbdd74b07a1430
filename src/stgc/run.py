"""A run directory: what belongs to a run, and starting a new one without mixing it with an old one.

A run directory holds the files of ONE training: its config, logs, checkpoint, saved iterations and evaluation
records. Starting a new run where an old one lies would leave the old `point_cloud/iteration_*` beside the new
config, and every later verb would read the stale model under the new run's name. So a new run refuses a
directory that already holds a run, unless the caller resumes it or asks to overwrite it (which removes the old
run's files, and only those: other files in the folder, such as an experiment's notes or logs, stay).
"""

from __future__ import annotations

import ast
import fcntl
import gc
import json
import logging
import os
import re
import shutil
import socket
from pathlib import Path
from typing import IO, Any, TypeGuard

from stgc.errors import DataError, FormatError, OutputError, StgcError
from stgc.fileio import file_sha256, read_json_object, write_json

log = logging.getLogger(__name__)

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
    "seams.png",
    "video.json",
    "continued_from.json",
    "restored_from.json",
)
RUN_FOLDERS = ("point_cloud", "tensorboard")
# A whole-video run (`stgc train --segment-frames N`) holds one complete run per segment in RUN/segment_<k>/.
SEGMENT_PREFIX = "segment_"
# What later verbs derive from the run's model and keep beside it: bitstreams and their evaluations, evaluations on
# other data, and the experiment runner's record of the plan entry the run was trained for. They describe the old
# model, so replacing the run removes them too.
DERIVED_PATTERNS = ("*.stgc", "eval_*.json", "eval_*_per_view.csv", "seams_*.png", "experiment.json")


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


class Run:
    """One run directory and its layout: the one place that names a run's files. Every verb reaches a run's
    config, summary, checkpoint, saved models and evaluation records through it.

        RUN/config.json                      the configs the run was started with (resolved values)
        RUN/metrics.jsonl, compaction.jsonl  training logs
        RUN/checkpoint.pt                    the latest training checkpoint (resume)
        RUN/train_summary.json               iterations, wall seconds, finished
        RUN/continued_from.json              the run a fine-tuning started from (stgc finetune)
        RUN/point_cloud/iteration_<N>/       saved models (official layout); the largest N is the run's model
        RUN/eval.json, eval_per_view.csv     the evaluation on the run's own test views
        RUN/eval_on_<data>.json              an evaluation on other data (never replaces the run's own)
        RUN/<name>.stgc, eval_<name>.json    bitstreams of the model and their evaluations
    A whole video trained as segments (`stgc train --segment-frames N`) is a run whose `video.json` lists its
    segments, each a complete run of its own in RUN/segment_<k>/; its eval.json is the whole video's.
    """

    CONFIG = "config.json"
    METRICS = "metrics.jsonl"
    COMPACTION_LOG = "compaction.jsonl"
    CHECKPOINT = "checkpoint.pt"
    SUMMARY = "train_summary.json"
    EXPERIMENT = "experiment.json"
    VIDEO = "video.json"
    TASK_LOG = "task.log"
    CONTINUED_FROM = "continued_from.json"
    RESTORED_FROM = "restored_from.json"  # `stgc decompress`: the model is a bitstream's, not a training's

    def __init__(self, path: str | Path):
        self.path = Path(path)

    def __repr__(self) -> str:
        return f"Run({str(self.path)!r})"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Run) and self.path == other.path

    def __hash__(self) -> int:
        return hash(self.path)

    @classmethod
    def create(cls, path: str | Path, *, overwrite: bool = False, keep: Path | None = None,
               derived: bool = True) -> Run:
        """A new run at `path` (see `prepare_new_run`: an existing run there is refused unless `overwrite`)."""
        return cls(prepare_new_run(path, overwrite=overwrite, keep=keep, derived=derived))

    @classmethod
    def of(cls, path: str | Path) -> Run | None:
        """The run holding `path` (the run itself, RUN/point_cloud/iteration_<N>, its PLY, or a file in RUN): the
        nearest of path and its three parents that has a config.json, or a restored_from.json (a run `stgc
        decompress` restored from a file without its run's config: a run of its own, though it has no config.json,
        never the run whose folder it was restored into); None if there is none."""
        path = Path(path).resolve()  # "." or a bare file name has no parents to climb
        found = next((p for p in [path, *path.parents][:4]
                      if (p / cls.CONFIG).is_file() or (p / cls.RESTORED_FROM).is_file()), None)
        return None if found is None else cls(found)

    # ------------------------------------------------------------------ files
    @property
    def config_path(self) -> Path:
        return self.path / self.CONFIG

    @property
    def summary_path(self) -> Path:
        return self.path / self.SUMMARY

    @property
    def task_log_path(self) -> Path:
        """Where a segment trained as a task (stgc.distributed) appends its messages: a Ray worker's are not shown."""
        return self.path / self.TASK_LOG

    @property
    def checkpoint_path(self) -> Path:
        return self.path / self.CHECKPOINT

    @property
    def experiment_path(self) -> Path:
        return self.path / self.EXPERIMENT

    def iteration_dir(self, iteration: int) -> Path:
        return self.path / "point_cloud" / f"iteration_{int(iteration)}"

    def eval_paths(self, other_data: str | None = None, bitstream: str | Path | None = None) -> tuple[Path, Path]:
        """(record .json, per-view .csv) of an evaluation: of the run's model, or of `bitstream` (RUN/<stem>.stgc:
        eval_<stem>.json); evaluated on a dataset other than the run's own (`other_data`, its folder name),
        `_on_<name>` is added, so the run's own record (what `stgc report` shows) is never replaced."""
        suffix = f"_on_{other_data}" if other_data else ""
        if bitstream is not None:
            bitstream = Path(bitstream)
            # Not with_suffix: a stem with a dot (model.q5) would lose what follows it, and two files share a record.
            base = f"eval_{bitstream.stem}{suffix}"
            return bitstream.parent / f"{base}.json", bitstream.parent / f"{base}_per_view.csv"
        return self.path / f"eval{suffix}.json", self.path / f"eval{suffix}_per_view.csv"

    @staticmethod
    def scored_this_bitstream(record: dict[str, Any], bitstream: str | Path) -> bool:
        """Whether an evaluation record of `bitstream` scored the file as it is now: the SHA-256 the record kept
        equals the file's (records written before it was kept: the file still has the record's size). A file
        written again after its evaluation (`stgc compress` to the same name) makes the record stale."""
        bitstream = Path(bitstream)
        if not bitstream.is_file():
            return False
        if record.get("bitstream_sha256"):
            return bool(record["bitstream_sha256"] == file_sha256(bitstream))
        return bool(record.get("size_bytes") == bitstream.stat().st_size)

    # ------------------------------------------------------------------ contents
    def has_config(self) -> bool:
        return self.config_path.is_file()

    def read_config(self, *, strict: bool = True) -> dict[str, Any] | None:
        """RUN/config.json as saved, or None without one (a damaged file: FormatError, or None if not strict)."""
        return read_json_object(self.config_path, strict=strict)

    def write_config(self, config: dict[str, Any]) -> None:
        write_json(self.config_path, config)

    def read_summary(self, *, strict: bool = True) -> dict[str, Any] | None:
        """RUN/train_summary.json (iterations, wall seconds, it/s, final #Gaussians, finished), or None."""
        return read_json_object(self.summary_path, strict=strict)

    def write_summary(self, summary: dict[str, Any]) -> None:
        write_json(self.summary_path, summary)

    def training_finished(self) -> bool:
        """The summary says finished (a damaged summary reads as not finished: the run is redone, not trusted)."""
        summary = self.read_summary(strict=False)
        return bool(summary and summary.get("finished"))

    def read_eval(self, other_data: str | None = None, *, strict: bool = True) -> dict[str, Any] | None:
        return read_json_object(self.eval_paths(other_data)[0], strict=strict)

    def holds_final_model(self) -> bool:
        """Whether the run's latest saved model is the one it ends with: its training finished, or it was restored
        from a bitstream (which holds a finished model: `stgc compress` refuses a half-trained video and says when a
        run is half-trained)."""
        return self.training_finished() or (self.path / self.RESTORED_FROM).is_file()

    def final_iteration(self) -> int | None:
        """The iteration of the model the run ends with: its finished training's, or the bitstream's a restored run
        came from; None while it trains (or when the files do not say)."""
        summary = self.read_summary(strict=False)
        if summary and summary.get("finished"):
            return _int_or_none(summary.get("iterations"))
        restored = read_json_object(self.path / self.RESTORED_FROM, strict=False)
        return None if restored is None else _int_or_none(restored.get("iteration"))

    def evaluated_finished_model(self) -> bool:
        """Whether the run's own evaluation record (eval.json) scored the model its finished training left: the
        record's iterations are the summary's. A record made while the run still trained (`stgc eval` of a
        half-trained run) names none, and the run may have finished without scoring itself (train.eval_at_end
        off): that record is stale."""
        summary = self.read_summary(strict=False)
        record = self.read_eval(strict=False)
        return bool(summary and summary.get("finished") and record is not None
                    and record.get("iterations") == summary.get("iterations"))

    def progress(self) -> tuple[int, int]:
        """(iterations done, iterations in all) as the files say while the run trains elsewhere: the last row of
        the metrics log against config.json's train.iterations; (0, 0) before either exists."""
        config = self.read_config(strict=False) or {}
        train = config.get("train")
        total = int(train.get("iterations") or 0) if isinstance(train, dict) else 0
        if self.training_finished():
            return total, total
        path = self.path / self.METRICS
        if not path.is_file():
            return 0, total
        with path.open("rb") as f:  # the tail only: a long run's log is long
            f.seek(max(0, path.stat().st_size - 4096))
            lines = f.read().splitlines()
        for line in reversed(lines):
            try:
                return int(json.loads(line)["iteration"]), total
            except (ValueError, KeyError, TypeError):  # a partial line being written
                continue
        return 0, total

    # ------------------------------------------------------------------ segments of a whole video
    @property
    def video_path(self) -> Path:
        return self.path / self.VIDEO

    def is_video(self) -> bool:
        return self.video_path.is_file()

    def read_video(self) -> dict[str, Any]:
        """RUN/video.json: {"segment_frames": N, "data_path": ..., "segments": [{"name", "start", "duration"}]}.

        Every verb trains, evaluates or packs segment k on the frames this file gives it, so a file that does not
        describe the consecutive segments a training writes is a DataError naming it: a start of 2.5 or "2" was
        truncated or failed deep inside a verb, and a gap or an overlap silently dropped frames from the video."""
        video = read_json_object(self.video_path)
        segments = None if video is None else video.get("segments")
        frames = None if video is None else video.get("segment_frames")
        if video is None or not isinstance(segments, list) or not all(
                isinstance(s, dict) and {"name", "start", "duration"} <= set(s) for s in segments) or not (
                _is_int(frames) and frames >= 1):
            raise DataError(self.video_path, "not a whole-video description (segment_frames >= 1, segments with "
                                             "name, start, duration)")
        if not segments:
            raise DataError(self.video_path, "lists no segments (a whole video has at least one)")
        for k, segment in enumerate(segments):
            name, start, duration = segment["name"], segment["start"], segment["duration"]
            if name != f"{SEGMENT_PREFIX}{k:03d}":  # the folder every verb opens for segment k
                raise DataError(self.video_path, f"segment {k} is named {_shown(name)}, not "
                                                 f"{SEGMENT_PREFIX}{k:03d} (segments are named in time order)")
            where = f"segment {k} ({name})"
            if not (_is_int(start) and start >= 0):
                raise DataError(self.video_path, f"{where}: start {_shown(start)} is not a frame number (an integer "
                                                 ">= 0)")
            if not (_is_int(duration) and duration >= 1):
                raise DataError(self.video_path, f"{where}: duration {_shown(duration)} is not a number of frames "
                                                 "(an integer >= 1)")
            if k > 0:
                before = segments[k - 1]
                follows = before["start"] + before["duration"]
                if start != follows:
                    raise DataError(self.video_path, f"{where}: starts at frame {start}, but the segment before it "
                                                     f"ends at frame {follows - 1} (segments are consecutive: it "
                                                     f"starts at {follows})")
        return video

    def check_segment_frames(self, segments: list[dict[str, Any]]) -> None:
        """Refuse (DataError naming the segment's file) a video.json entry whose frames are not those its segment
        recorded for itself: its config.json's data.start/data.duration, or, restored from a bitstream without its
        run config, its restored_from.json's start/duration. An edited video.json would resume or pack a segment on
        frames its model was never trained on (its own frames silently gone from the video)."""
        for segment in segments:
            folder = Run(self.path / str(segment["name"]))
            given = (segment["start"], segment["duration"])
            source, saved = folder.config_path, folder.read_config()
            if saved is not None:
                data = saved.get("data")
                if not isinstance(data, dict):  # no data options: it does not say its frames
                    continue
            else:
                source = folder.path / self.RESTORED_FROM
                data = read_json_object(source)
                if data is None or "start" not in data or "duration" not in data:
                    continue
            own = (data.get("start"), data.get("duration"))
            if own != given or not all(_is_int(v) for v in own):
                field = "data." if source.name == self.CONFIG else ""
                raise DataError(source, f"the segment's frames are {field}start={_shown(own[0])}, "
                                        f"{field}duration={_shown(own[1])}, but {self.video_path} gives it start="
                                        f"{given[0]}, duration={given[1]}; the segment's model is of its own frames: "
                                        f"restore {self.VIDEO} (or train the video again into a new --out)")

    def write_video(self, video: dict[str, Any]) -> None:
        write_json(self.video_path, video)

    def segment(self, index: int) -> Run:
        return Run(self.path / f"{SEGMENT_PREFIX}{index:03d}")

    def segments(self) -> list[Run]:
        """The segment runs of a whole-video run, in time order ([] for a single-segment run)."""
        if not self.is_video():
            return []
        return [Run(self.path / str(s["name"])) for s in self.read_video()["segments"]]

    def saved_iterations(self) -> dict[int, Path]:
        return saved_iterations(self.path)

    def latest_model_dir(self) -> Path | None:
        return latest_iteration_dir(self.path)


def run_config_problems(saved: Any) -> list[str]:
    """Why `saved` (a config.json as read) is not shaped as one a stgc training wrote; empty when it is: data,
    model and train sections that are objects (a model section may be null, as the Python API saved it until
    2026-11-27), a train section that holds its iterations (or its resolved schedule's), and a compaction section
    that is null, absent or an object naming its method. Anything else would be read as defaults made up for it (a
    30,000-iteration custom schedule, ST-KNN compaction) and trained on as if the run had asked for them."""
    if not isinstance(saved, dict):
        return [f"it is {_shown(saved)}, not an object"]
    problems = []
    for name in ("data", "model", "train"):
        if name not in saved:
            problems.append(f"no {name!r} section")
        elif not (isinstance(saved[name], dict) or (name == "model" and saved[name] is None)):
            problems.append(f"its {name!r} section is {_shown(saved[name])}, not an object")
    train = saved.get("train")
    if isinstance(train, dict):
        resolved = train.get("resolved_schedule")
        if "iterations" not in train and not (isinstance(resolved, dict) and "iterations" in resolved):
            problems.append("its 'train' section has no iterations")
    compaction = saved.get("compaction")
    if compaction is not None and not (isinstance(compaction, dict) and "method" in compaction):
        # Every training saved the whole section (or null, without compaction): its method is always there.
        problems.append(f"its 'compaction' section is {_shown(compaction)}, not null or an object with a method")
    return problems


def check_run_config(saved: Any, path: Path) -> None:
    """Raise FormatError naming `path` unless `saved` is shaped as a training's config.json (`run_config_problems`)."""
    problems = run_config_problems(saved)
    if problems:
        raise FormatError(path, f"not a stgc run config ({'; '.join(problems)})")


def _shown(value: Any, limit: int = 40) -> str:
    """`value` as a message shows it: its repr, cut at `limit` characters."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit]}..."


class RunExistsError(StgcError):
    """The output directory already holds a run and neither resume nor overwrite was asked for."""


def run_contents(path: Path) -> list[Path]:
    """The run files and folders present in `path` (empty when it holds no run)."""
    return [path / name for name in (*RUN_FILES, *RUN_FOLDERS) if (path / name).exists()]


def prepare_new_run(path: str | Path, *, overwrite: bool = False, keep: Path | None = None,
                    derived: bool = True) -> Path:
    """Make `path` ready for a new run: create it, or refuse (RunExistsError) when it already holds one, unless
    `overwrite` (then the old run's files, and with `derived` the bitstreams and evaluations derived from it, are
    removed first; `keep` is spared: the input being restored there). Clear errors when `path` cannot be a
    directory."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise StgcError(f"{path}: exists and is not a directory")
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise StgcError(f"{path}: its parent {parent} is a file, not a directory")
            break
    existing = run_contents(path) if path.is_dir() else []
    if path.is_dir():
        # A segment that failed before saving anything holds only its task log: the old video's all the same.
        existing += sorted(p for p in path.glob(f"{SEGMENT_PREFIX}*")
                           if p.is_dir() and (run_contents(p) or (p / Run.TASK_LOG).is_file()))
    if existing and not overwrite:
        names = ", ".join(p.name for p in existing[:4]) + (", ..." if len(existing) > 4 else "")
        raise RunExistsError(f"{path}: already holds a run ({names}); use --resume to continue it or --overwrite to "
                             "replace it")
    if overwrite and derived and path.is_dir():
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


# An official STG run keeps its options as the repr of its argparse Namespace in RUN/cfg_args.
OFFICIAL_ARGS = "cfg_args"


def official_run_args(path: str | Path) -> dict[str, Any] | None:
    """The options an official STG run saved (RUN/cfg_args, `Namespace(key=value, ...)`), found from the run, an
    iteration dir or its PLY; None where there is none. Read as Python literals, never executed; FormatError when
    the file is not such a Namespace."""
    path = Path(path).resolve()  # the parents of a relative path ('.', 'point_cloud.ply') stop at the working dir
    found = next((p / OFFICIAL_ARGS for p in [path, *path.parents][:4] if (p / OFFICIAL_ARGS).is_file()), None)
    if found is None:
        return None
    try:
        call = ast.parse(found.read_text(errors="replace").strip(), mode="eval").body
        if not (isinstance(call, ast.Call) and isinstance(call.func, ast.Name) and call.func.id == "Namespace"):
            raise ValueError("not a Namespace(...)")
        args = {}
        for keyword in call.keywords:
            if keyword.arg is None:
                raise ValueError("a **-argument")
            try:
                args[keyword.arg] = ast.literal_eval(keyword.value)
            except ValueError:
                args[keyword.arg] = None  # a value that is no literal (an object's repr): not one stgc reads
        return args
    except (SyntaxError, ValueError) as exc:
        raise FormatError(found, f"not an official STG cfg_args file ({exc})") from None


def _is_int(value: Any) -> TypeGuard[int]:
    """An integer as JSON holds one: not a bool (True is an int in Python), a float or a string of digits."""
    return isinstance(value, int) and not isinstance(value, bool)


def _int_or_none(value: Any) -> int | None:
    try:
        return None if value is None else int(value)
    except (TypeError, ValueError):
        return None


# RUN/.lock: not one of the run's files (stgc.run.RUN_FILES), so a folder holding only a stale one holds no run.
LOCK_NAME = ".lock"
# Tries at locking a lock file that its releasing holders keep removing (each try follows a release).
_LOCK_TRIES = 20


class RunInUseError(OutputError):
    """Another trainer holds the run folder (RunLock): it trains the run, or a fine-tuning is being started in it."""


class RunLock:
    """An exclusive advisory lock on a run folder (flock on RUN/.lock), held while a trainer or the start of a
    fine-tuning writes the folder: two trainers in one folder (two resumes of a run, or a resume while a killed
    driver's Ray worker still trains it) wrote every metrics row twice and interleaved their checkpoints. The kernel
    releases it when its holder dies, so a killed run never leaves its folder locked. The file holds the holder's pid
    and host, for the message that refuses a second trainer."""

    def __init__(self, run_dir: str | Path):
        self.run_dir = Path(run_dir)
        self.path = self.run_dir / LOCK_NAME
        self._file: IO[str] | None = None

    @property
    def held(self) -> bool:
        return self._file is not None

    def acquire(self) -> None:
        """Take the lock (nothing to do while this object holds it); RunInUseError naming the folder and the holder
        when another one holds it. The folder must exist."""
        if self._file is not None:
            return
        collected = False
        for _ in range(_LOCK_TRIES):
            try:
                handle = open(self.path, "a+")
            except OSError:
                return  # a folder that cannot be written: the run's own first write fails, naming its file
            try:
                fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = _lock_holder(handle)
                handle.close()
                if not collected and holder.get("pid") == os.getpid() and holder.get("host") == socket.gethostname():
                    # A trainer this process dropped without running it (a test, a notebook) keeps its lock until the
                    # garbage collector frees it: its strategies refer back to it, so dropping it frees nothing.
                    gc.collect()
                    collected = True
                    continue
                raise RunInUseError(self.run_dir, f"is being trained by {_holder_words(holder)}; two trainers in one "
                                                  "run folder would both write its logs and checkpoints: wait until "
                                                  "it ends, or stop it (a stopped process frees the folder)") from None
            except OSError as exc:
                handle.close()
                log.warning("%s: cannot lock the run folder (%s): training without the guard against a second "
                            "trainer in it", self.run_dir, exc.strerror or exc)
                return
            if not _same_file(handle, self.path):
                handle.close()  # its last holder removed it when it released it: lock the one there now
                continue
            try:
                handle.seek(0)
                handle.truncate()
                handle.write(json.dumps({"pid": os.getpid(), "host": socket.gethostname()}))
                handle.flush()
            except OSError:
                pass  # held all the same; a refused trainer just cannot name the holder
            self._file = handle
            return
        raise RunInUseError(self.run_dir, f"{LOCK_NAME} is replaced as soon as it is locked: other trainers keep "
                                          "starting and ending in this folder")

    def release(self) -> None:
        """Let the lock go (nothing to do when not held) and remove its file."""
        handle, self._file = self._file, None
        if handle is None:
            return
        try:
            # Removed while still locked: a process that opened it meanwhile sees, once it locks it, that it is no
            # longer the folder's lock file, and tries again (acquire).
            if _same_file(handle, self.path):
                self.path.unlink()
        except OSError:
            pass
        handle.close()

    def __enter__(self) -> RunLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def _same_file(handle: IO[str], path: Path) -> bool:
    """Whether the open `handle` is the file at `path` (not one removed from there)."""
    try:
        there, mine = os.stat(path), os.fstat(handle.fileno())
    except OSError:
        return False
    return (there.st_dev, there.st_ino) == (mine.st_dev, mine.st_ino)


def _lock_holder(handle: IO[str]) -> dict[str, Any]:
    """The pid and host a lock file names ({} when it names none: its holder had not written them yet)."""
    try:
        handle.seek(0)
        holder = json.loads(handle.read() or "{}")
    except (OSError, ValueError):
        return {}
    return holder if isinstance(holder, dict) else {}


def _holder_words(holder: dict[str, Any]) -> str:
    pid, host = holder.get("pid"), holder.get("host")
    if not isinstance(pid, int):
        return "another process"
    if isinstance(host, str) and host != socket.gethostname():
        return f"another process (pid {pid} on {host})"
    if pid == os.getpid():
        return f"another trainer of this process (pid {pid}; it holds the folder until its run ends)"
    return f"another process (pid {pid})"
