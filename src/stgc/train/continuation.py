"""Fine-tuning a finished run into a new run: `stgc finetune RUN --out NEW --iterations N` (issue #17).

Rate-aware fine-tuning, and every RD point of a lambda sweep, starts from one trained model rather than from
scratch: NEW begins as RUN's last checkpoint (model, optimizer, colour correction, random streams) with RUN's
configuration, its schedule extended by N iterations, and only `train.*` options changed (the data, the model and
the finished compaction are what RUN was trained with; changing them would not describe what NEW holds). ST-KNN
compaction is not re-opened: a compacted RUN stays as pruned as it is. The xyz learning rate decays over the new
total, as if the run had been planned that long. NEW keeps RUN's metrics and compaction logs, so its curves show
the whole history, and `continued_from.json` names RUN and the iteration NEW started at. NEW resumes like any run
(`stgc train --out NEW --resume`).
"""

from __future__ import annotations

import dataclasses
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from stgc.config import ConfigError, apply_overrides, split_sections, validate_config
from stgc.errors import StgcError
from stgc.fileio import atomic_path, write_json
from stgc.run import Run, RunLock, prepare_new_run
from stgc.train.checkpoint import copy_checkpoint
from stgc.train.config import (
    QuantizationAwareConfig,
    TrainConfig,
    refuse_preset_option,
    refuse_unused_window_options,
    resolve_schedule,
)
from stgc.train.loop import (
    check_same_data,
    check_trainable,
    options_fingerprint,
    resolved_options,
    run_config,
    run_options,
)


def check_continuable(source: str | Path) -> None:
    """Raise StgcError unless `source` is a finished single-segment run with a checkpoint."""
    source = Path(source)
    run = Run(source)
    if run.is_video():
        raise StgcError(f"{source}: a whole video; fine-tune its segments one by one (RUN/segment_<k>)")
    if not run.has_config() or not run.checkpoint_path.is_file():
        raise StgcError(f"{source}: not a run with config.json and checkpoint.pt to continue from")
    if not run.training_finished():
        raise StgcError(f"{source}: its training is not finished; finish it first (stgc train --out {source} --resume)")


def check_window_fits(window: int, iterations: int) -> None:
    """A continuation's rate-aware window must lie inside it: a longer one would start inside the source's finished
    training, and config.json would record steps that never ran."""
    if window > iterations:
        raise ConfigError(f"train.quantization_aware.iterations {window}: longer than the continuation's {iterations} "
                          f"iterations (set it to at most {iterations}, or 0 for none)")


def continuation_configs(saved: Mapping[str, Any], source: str | Path, iterations: int,
                         overrides: Mapping[str, str] | None = None) -> dict[str, Any]:
    """The configs (data, model, train, compaction, data_path) a continuation of `source` by `iterations` trains
    with, from `saved` (`stgc.options.configs_from_run(source)`): train.iterations extended, `overrides`
    ({"train.x": value}) applied and validated, the compaction switched off. Raises ConfigError naming the
    problem."""
    if iterations < 1:
        raise ConfigError(f"iterations {iterations}: a continuation trains at least 1 more iteration")
    sections = split_sections(dict(overrides or {}), {"data", "model", "train", "compaction"})
    others = sorted(f"{section}.{key}" for section, values in sections.items() if section != "train" for key in values)
    if others:
        raise ConfigError(f"{', '.join(others)}: a continuation changes train.* options only (it keeps the data, the "
                          f"model and the compaction {source} was trained with)")
    refuse_preset_option(f"train.{key}" for key in sections.get("train", {}))  # the source's schedule's name
    configs = dict(saved)
    base = saved["train"].iterations
    start = dataclasses.replace(saved["train"], iterations=base + iterations)
    if start.quantization_aware.iterations == 0:
        # The source had no window, so its window options acted on nothing (an older config reads them as they were
        # then): a window opened here takes today's defaults for what it is not given.
        start = dataclasses.replace(start, quantization_aware=QuantizationAwareConfig())
    train_cfg = apply_overrides(start, sections.get("train", {}), "train")
    if train_cfg.iterations != base + iterations:
        raise ConfigError("train.iterations: give the continuation's length as its iterations, not as an override")
    check_window_fits(train_cfg.quantization_aware.iterations, iterations)
    refuse_unused_window_options(train_cfg, (f"train.{key}" for key in sections.get("train", {})))
    configs["train"] = validate_config(train_cfg, "train")
    configs["compaction"] = dataclasses.replace(saved["compaction"], method="none")
    return configs


def start_continuation(source: str | Path, out: str | Path, iterations: int, configs: Mapping[str, Any],
                       overrides: Mapping[str, str] | None = None, *, overwrite: bool = False,
                       data_path: str | None = None, evaluate: bool = True) -> str:
    """Write NEW (`out`) as `source` continued by `iterations` with `configs` (continuation_configs): its
    config.json, continued_from.json, source's logs and source's checkpoint (marked as trained with NEW's options),
    once the trainer's own checks pass (`check_trainable`; `evaluate`: whether it will score the test views), holding
    NEW's lock (RunLock) while it writes. Returns the data path to train it on (`train(..., resume=True)`)."""
    source, out = Path(source), Path(out)
    check_continuable(source)
    if out.resolve() == source.resolve():
        raise StgcError(f"{out}: the continuation must go to a new run directory, not into {source}")
    data_path = data_path or configs["data_path"]
    if data_path is None:
        raise StgcError(f"{source}: the run has no saved data path; give DATA")
    dataset = configs["data"].open(data_path)
    check_same_data(Run(source).read_config(strict=False), dataset, source)
    check_trainable(dataset, configs["train"], evaluate=evaluate)
    started = int((Run(source).read_summary() or {}).get("iterations") or configs["train"].iterations - iterations)
    # The options as the trainer resolves them: what it records in config.json and checks the checkpoint against.
    train_cfg, model_cfg = resolved_options(dataset, configs["data"], configs["model"], configs["train"])
    config = run_config(dataset, {"data": configs["data"], "model": model_cfg, "train": train_cfg,
                                  "compaction": configs["compaction"]}, resolve_schedule(train_cfg))
    continued_from = {"run": str(source.resolve()), "iteration": started, "iterations": iterations,
                      "overrides": dict(overrides or {})}
    lock = RunLock(out)
    if out.is_dir():
        lock.acquire()  # before an earlier run's files there are removed (overwrite)
    try:
        prepare_new_run(out, overwrite=overwrite)
        lock.acquire()  # a new folder, once made
        _write_continuation(source, out, config, continued_from)
    finally:
        lock.release()
    return str(data_path)


def _write_continuation(source: Path, out: Path, config: dict[str, Any], continued_from: dict[str, Any]) -> None:
    """Write NEW's files, the checkpoint last and each atomically: a start killed on the way leaves no checkpoint
    without the config.json it belongs to (`stgc train --resume` of such a folder trained the source's checkpoint
    under the command line's defaults, thousands of iterations of another training). One stopped by an exception or
    an interrupt removes what it wrote, so that the same command runs again."""
    new = Run(out)
    try:
        new.write_config(config)
        write_json(out / Run.CONTINUED_FROM, continued_from)
        for name in (Run.METRICS, Run.COMPACTION_LOG):
            if (source / name).is_file():
                with atomic_path(out / name) as copy:
                    shutil.copy2(source / name, copy)
        options = run_options(config)
        copy_checkpoint(source, out, options_fingerprint(options), options)
    except BaseException:
        # The checkpoint first: at no moment is there one without its config.json.
        for name in (Run.CHECKPOINT, Run.METRICS, Run.COMPACTION_LOG, Run.CONTINUED_FROM, Run.CONFIG):
            (out / name).unlink(missing_ok=True)
        raise
