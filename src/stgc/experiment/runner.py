"""Run a plan: one independent `stgc train` subprocess per run, each run a task (in parallel on Ray, or in order),
resumable, then results.csv and the report.

Layout of an experiment folder OUT:

    OUT/<run name>/            a normal run directory (config.json, point_cloud/, eval.json, ...)
    OUT/<run name>/experiment.json   the run's plan entry (family, label, overrides) for the report; a run shared
                               by several plans has each plan's name, family and label under "plans" (by plan name),
                               the top-level ones staying the first plan's
    OUT/logs/<run name>.log    stdout + stderr of that run's subprocesses
    OUT/results-<plan>.csv     one row per run (and per codec rate point), rewritten atomically after every run
    OUT/report-<plan>/         report.md, report_rd.png/.svg, report.json

Runs are named by their settings, and the per-plan outputs carry the plan's name, so several plans (table2 and
table3) can share one folder and train their common runs once.

A run counts as finished when RUN/eval.json exists and RUN/train_summary.json says finished; finished runs are
skipped, an interrupted run with a checkpoint is continued with `--resume`, a failed run is reported and the
others still run. A run already in OUT that was made with other options, preset or data fails instead of being
reused (`reuse_mismatch`). A codec point's RUN/model_q<Q>.stgc is reused only when it is what compressing the run
now would write (that quality, the run's final model, the runner's codec options); any other is written again.
"""

from __future__ import annotations

import csv
import ctypes
import logging
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from stgc.codec import CodecConfig
from stgc.codec.files import custom_codec_options, written_without_window_depths
from stgc.codec.format import decode_metadata, read_capped, read_header
from stgc.codec.video import is_video_stgc, read_video_index
from stgc.compaction.config import idle_compaction_options
from stgc.model.config import idle_model_options
from stgc.config import (
    EXECUTION_OPTIONS,
    ConfigError,
    apply_overrides,
    iter_fields,
    same_option_value,
    same_place,
)
from stgc.distributed import Task, check_reachable, cpus_for_threads, run_tasks
from stgc.data.readers import detect_format
from stgc.errors import StgcError
from stgc.eval.evaluate import foreign_model
from stgc.eval.report import (
    CODEC_SUFFIX,
    Report,
    ReportRow,
    scored_earlier_model,
    make_report,
    rate_points,
    record_fields,
    remove_report,
)
from stgc.experiment.plans import Plan, RunSpec, check_codec_baseline, load_plan
from stgc.experiment.spread import EntrySpread, baseline_entry, seed_spread, spread_markdown, write_spread_csv
from stgc.fileio import atomic_open, read_json_object, write_json
from stgc.options import (
    configs_from_run,
    default_configs,
    idle_feature_options,
    refuse_unused_compaction_options,
    refuse_unused_model_options,
    section_classes,
    resolve_configs,
)
from stgc.official import FAMILY_OPTIONS
from stgc.run import Run
from stgc.train.behaviour import missing_behaviour
from stgc.train.config import DensifyConfig, idle_window_options, refuse_unused_window_options
from stgc.train.continuation import check_window_fits, continuation_configs

_log = logging.getLogger(__name__)

RESULT_COLUMNS = ("plan", "name", "family", "label", "seed", "status", "rate_point", "num_gaussians", "size_mb", "mbps",
                  "psnr", "psnr_yuv", "ssim", "lpips", "fps", "train_seconds", "overrides", "run_dir")
CLI_MODULE = "stgc.cli"
_PR_SET_PDEATHSIG = 1  # linux/prctl.h


# ------------------------------------------------------------------------------------------ commands
# The only places that know the CLI's verbs and flags: adapt here if they change.


def build_train_command(
    data_path: str | Path,
    run_dir: str | Path,
    preset: str | None,
    overrides: Mapping[str, str],
    *,
    resume: bool = False,
    python: str = sys.executable,
) -> list[str]:
    """`python -m stgc.cli train DATA --out RUN [--preset P] --set key=value ...`, or for `resume`
    `... train DATA --out RUN --resume`: a resumed run keeps the config saved in RUN, and the CLI refuses
    overrides next to --resume (they could silently differ from what the run started with)."""
    cmd = [python, "-m", CLI_MODULE, "train", str(data_path), "--out", str(run_dir)]
    if resume:
        return cmd + ["--resume"]
    # Not resumable (no checkpoint): whatever partial run is there is this run's own false start.
    cmd.append("--overwrite")
    if preset:
        cmd += ["--preset", preset]
    for key, value in overrides.items():
        cmd += ["--set", f"{key}={value}"]
    return cmd


def build_finetune_command(source_dir: str | Path, run_dir: str | Path, iterations: int,
                           overrides: Mapping[str, str], *, python: str = sys.executable) -> list[str]:
    """`python -m stgc.cli finetune SOURCE --out RUN --iterations N --overwrite --set key=value ...` (a fine-tuning
    run resumes with build_train_command(..., resume=True) like any other)."""
    cmd = [python, "-m", CLI_MODULE, "finetune", str(source_dir), "--out", str(run_dir), "--iterations",
           str(iterations), "--overwrite"]
    for key, value in overrides.items():
        cmd += ["--set", f"{key}={value}"]
    return cmd


def finetune_overrides(spec: RunSpec, extra: Mapping[str, str]) -> dict[str, str]:
    """The options `stgc finetune` gets for a fine-tuning run: its plan entry's, and --set's train.* ones over them
    (--set wins over the plan in every run; the other sections and the length come from the source)."""
    return {**spec.overrides, **{k: v for k, v in extra.items() if k.startswith("train.") and k != "train.iterations"}}


def run_overrides(plan: Plan, spec: RunSpec, extra: Mapping[str, str], out_dir: Path) -> dict[str, str]:
    """The options that make `spec`'s run: its plan entry's with --set's over them, except --set's options that
    would act on nothing there (`idle_options`: `stgc train` and `finetune` refuse them); a fine-tuning run's
    are its source's with `finetune_overrides` over them. A run with a loss reference gets
    compaction.loss_reference = that run's folder under `out_dir`."""
    if spec.source is None:
        reference = {} if spec.reference is None else {"compaction.loss_reference": str(out_dir / spec.reference)}
        merged = {**spec.overrides, **extra, **reference}
    else:
        source = next(s for s in plan.runs if s.name == spec.source)
        merged = {**run_overrides(plan, source, extra, out_dir), **finetune_overrides(spec, extra)}
    idle = idle_options(merged) - set(spec.overrides)
    return {k: v for k, v in merged.items() if k not in idle}


def idle_options(options: Mapping[str, str]) -> set[str]:
    """The keys of `options` that act on nothing in the run they make: compaction options where nothing is pruned
    (a plan's `stg` baseline), rate-aware options `idle_window_options` names, a lite model's decoder options.
    --set applies to every run of a plan, so its such options are left out of those runs (and out of what their
    reuse compares)."""
    configs = default_configs()  # what a plan's run starts from (no compaction)
    for section in list(configs):
        values = {k.partition(".")[2]: v for k, v in options.items() if k.partition(".")[0] == section}
        try:
            configs[section] = apply_overrides(configs[section], values, section)
        except ConfigError:  # a bad value: check_plan_options names it
            pass
    return set(options) & _idle_in(configs)


def check_plan_options(plan: Plan, preset: str | None, extra: Mapping[str, str], out_dir: Path) -> None:
    """Resolve and validate every run's options before the first training starts: a typo in the plan's last run
    must not surface hours later. Raises ConfigError naming the run."""
    for key in extra:
        values = {str(spec.overrides[key]) for spec in plan.runs if key in spec.overrides}
        if len(values) > 1:  # --set wins in every run: the runs would train alike under the names of their values
            raise ConfigError(f"--set {key}: plan {plan.name!r} varies it between its runs "
                              f"({', '.join(sorted(values))}); run the plan without it, or write a plan of your own")
    defaults = default_configs(preset or "cpu")
    for key, value in extra.items():  # each --set value's name and type, whether or not it acts in a run (values
        section, _, name = key.partition(".")  # that only a run's other options make valid are checked per run)
        try:
            if section not in defaults:
                raise ConfigError(f"{key}: unknown section {section!r} (one of {', '.join(defaults)})")
            apply_overrides(defaults[section], {name: value}, section)
        except ValueError as exc:
            raise ConfigError(f"--set {key}={value}: {exc}") from None
    by_run = {spec.name: run_overrides(plan, spec, extra, out_dir) for spec in plan.runs}
    unused = sorted(k for k in extra if not any(k in overrides for overrides in by_run.values()))
    if unused:
        raise ConfigError(f"--set {', '.join(unused)}: acts on nothing in any run of plan {plan.name!r} (e.g. "
                          "compaction options where nothing is pruned, rate-aware options without a window); drop it")
    methods = {}
    for spec in plan.runs:
        try:
            overrides = by_run[spec.name]
            configs = resolve_configs(preset or "cpu", {}, {}, overrides)
            # A fine-tuning run trains without compaction (stgc finetune switches it off), whatever its source did.
            methods[spec.name] = "none" if spec.source is not None else configs["compaction"].method
            if spec.reference is not None and methods.get(spec.reference) != "reference":
                raise ConfigError(f"its loss_reference {spec.reference!r} trains with compaction.method="
                                  f"{methods.get(spec.reference)}: a loss reference is a run trained with "
                                  "compaction.method=reference")
            refuse_unused_window_options(configs["train"], overrides)  # the entry's own: --set's idle ones are out
            refuse_unused_model_options(configs["model"], overrides)
            if spec.source is None:
                refuse_unused_compaction_options(configs["compaction"], overrides)
            else:
                check_window_fits(configs["train"].quantization_aware.iterations, spec.iterations)
        except ValueError as exc:  # ConfigError, and a section's own validation
            raise ConfigError(f"plan {plan.name!r}, run {spec.name!r}: {exc}") from None


def reuse_mismatch(run_dir: Path, data_path: str | Path, preset: str | None, overrides: Mapping[str, str],
                   spec: RunSpec | None = None, extra: Mapping[str, str] | None = None, *,
                   check_config: bool = True) -> str | None:
    """Why the run already in `run_dir` is not the one the plan asks for now, or None when it is, or when nothing is
    there yet. A finished run is skipped and an interrupted one resumed with its own saved config, so a mismatch
    would put one run's numbers under another's options in the results.

    Checked: the plan entry this runner recorded (experiment.json: options, preset, data), a fine-tuning run's
    source and length (continued_from.json against `source`, the plan entry's `from` and `iterations`), and the
    whole saved config.json against the config the plan resolves to today, execution options left out. The last
    catches what the recorded options cannot: a preset whose defaults moved, a run copied in by hand, a
    fine-tuning run whose source's options changed. `spec` is the run's plan entry and `extra` the --set options
    (needed for a fine-tuning run); `check_config` off (a stand-in trainer with options of its own, in tests)
    compares only the options the plan sets, and only for a run copied in by hand."""
    run = Run(run_dir)
    if not run.has_config() and not run.experiment_path.is_file():
        return None
    differences = []
    recorded = read_json_object(run.experiment_path, strict=False)
    wanted = {k: str(v) for k, v in overrides.items() if k not in EXECUTION_OPTIONS}
    if recorded is not None:
        before = {str(k): str(v) for k, v in (recorded.get("overrides") or {}).items() if k not in EXECUTION_OPTIONS}
        # --set's options that act on nothing in this run are no longer passed to it (run_overrides), and never
        # acted in it; an earlier runner recorded them.
        idle = idle_options({**before, **wanted}) - set(wanted)
        before = {k: v for k, v in before.items() if k not in idle}
        for key in sorted(set(before) | set(wanted)):
            if _same_plan_option(key, before.get(key), wanted.get(key), run_dir.parent):
                continue
            if _saved_as_planned(run_dir, key, preset, wanted, data_path):
                continue  # spelt otherwise then ("1e-1", "0.1"), or named then and the default now, or the reverse
            differences.append(f"{key}: {before.get(key, 'unset')} then, {wanted.get(key, 'unset')} now")
        if recorded.get("preset") not in (None, preset or "cpu"):
            differences.append(f"preset: {recorded['preset']} then, {preset or 'cpu'} now")
        if recorded.get("data") is not None and not same_place(recorded["data"], data_path):
            differences.append(f"data: {recorded['data']} then, {Path(data_path).resolve()} now")
    finetune = spec if spec is not None and spec.source is not None else None
    if finetune is not None:
        differences += _continuation_mismatch(run, finetune)
    if run.has_config() and (check_config or recorded is None) and not differences:  # each difference said once
        differences += _config_mismatch(run_dir, data_path, preset, wanted,
                                        None if finetune is None else (finetune, dict(extra or {})), check_config)
    return "; ".join(differences) or None


def _saved_as_planned(run_dir: Path, key: str, preset: str | None, wanted: Mapping[str, str],
                      data_path: str | Path) -> bool:
    """Whether the run's config.json (read as it trained: SAVED_BEFORE for keys it lacks) holds the value the plan's
    options (`wanted`) give the option `key` (dotted, with its section) now: the one they name, else its default,
    where the default is left to the data the value training resolves it to on `data_path` (_resolved_by_data)."""
    section, _, name = key.partition(".")
    try:
        saved = configs_from_run(run_dir)[section]
        asked = resolve_configs(preset or "cpu", {}, {}, dict(wanted))
    except (ConfigError, StgcError, KeyError):
        return False
    then = {f.dotted: f.default for f in iter_fields(saved)}
    now = {f.dotted: f.default for f in iter_fields(asked[section])}
    value = now.get(name)
    if value is None and key in RESOLVED_AT_TRAINING:
        value = _resolved_by_data(asked, data_path).get(key)
    return name in now and value is not None and then.get(name) == value


def _continuation_mismatch(run: Run, spec: RunSpec) -> list[str]:
    """A fine-tuning run's recorded source and length against its plan entry (`spec`, with its `source`)."""
    continued = read_json_object(run.path / Run.CONTINUED_FROM, strict=False)
    if continued is None:
        return []
    differences = []
    # By name in the experiment folder: the folder itself may have moved since.
    if continued.get("run") is not None and Path(str(continued["run"])).name != spec.source:
        differences.append(f"fine-tuned from {Path(str(continued['run'])).name} then, from {spec.source} now")
    if continued.get("iterations") is not None and int(continued["iterations"]) != spec.iterations:
        differences.append(f"{continued['iterations']} fine-tuning iterations then, {spec.iterations} now")
    return differences


def _config_mismatch(run_dir: Path, data_path: str | Path, preset: str | None, wanted: Mapping[str, str],
                     finetune: tuple[RunSpec, dict[str, str]] | None, every_option: bool = True) -> list[str]:
    """Every option of RUN/config.json (or only those in `wanted`) against the config the plan resolves to now (a
    fine-tuning run, given as its plan entry and the --set options: its source's saved config continued as the
    plan says). Not compared: options the training resolves from the data and saves resolved (RESOLVED_AT_TRAINING,
    None in the plan), and options a config.json does not hold and no SAVED_BEFORE gives."""
    try:
        saved = configs_from_run(run_dir)
        if finetune is None:
            asked = resolve_configs(preset or "cpu", {}, {}, dict(wanted))
        else:
            spec, extra = finetune
            source_dir = run_dir.parent / str(spec.source)
            if not Run(source_dir).has_config():
                return []
            asked = continuation_configs(configs_from_run(source_dir), source_dir, spec.iterations,
                                         finetune_overrides(spec, extra))
    except (ConfigError, StgcError) as exc:
        if not every_option:  # options only a stand-in trainer knows (tests), or a config it wrote
            return []
        # Nothing compared would reuse any run (another version's options, a damaged file): refuse it instead.
        return [f"its config.json cannot be compared with the plan's ({exc})"]
    recorded = Run(run_dir).read_config() or {}
    differences = []
    by_data = _resolved_by_data(asked, data_path)
    idle = _idle_in(saved) & _idle_in(asked)  # acted in neither run
    for section in ("data", "model", "train", "compaction"):
        held = _dotted_keys(recorded.get(section))
        # A key an older config.json's section lacks was trained as SAVED_BEFORE says (configs_from_run read it so).
        before = set(getattr(section_classes()[section], "SAVED_BEFORE", {})) - held if held else set()
        theirs = {f.dotted: f.default for f in iter_fields(saved[section])}
        for f in iter_fields(asked[section]):
            key, then, now = f"{section}.{f.dotted}", theirs.get(f.dotted), f.default
            if (f.dotted not in held | before or key in EXECUTION_OPTIONS or not (every_option or key in wanted)
                    or (f.dotted in before and now == "auto")  # 'auto' resolves by the data: unknown here
                    or key in idle):
                continue
            if key in RESOLVED_AT_TRAINING and now is None:
                # A run whose config.json holds None left it to the data too (a whole video's shared options).
                if then is None or key not in by_data:
                    continue
                now = by_data[key]  # what training resolves it to on the plan's data
            if key == "data.format" and "auto" in (then, now):
                then, now = (_detected_format(data_path) if v == "auto" else v for v in (then, now))
            if not _same_plan_option(key, then, now, run_dir.parent):
                differences.append(f"{key}: {then} in its config.json, {now} in the plan")
    differences += [f"{change.name}: {change.what}; it acts on this run, trained before it"
                    for change in missing_behaviour(recorded, saved)]
    saved_data = saved.get("data_path")
    if saved_data is not None and not same_place(saved_data, data_path):
        differences.append(f"data: {saved_data} in its config.json, {Path(data_path).resolve()} in the plan")
    return differences


def _idle_in(configs: Mapping[str, Any]) -> set[str]:
    """The options that act on nothing in a run with these configs (the same rules `idle_options` applies to
    --set's options: rate-aware options without a window, compaction options a method does not use, a lite
    model's decoder options, options of a part of training that is switched off)."""
    idle = idle_window_options(configs["train"]) | idle_model_options(configs["model"]) | idle_feature_options(configs)
    return idle | (idle_compaction_options(configs["compaction"]) if configs.get("compaction") is not None else set())


# Options left None in a plan that training resolves from the data and saves resolved (the frame window, the near
# plane, the densification schedule of the initial cloud's kind, the official config family's model options and
# learning rates): their saved values are not the plan's None.
RESOLVED_AT_TRAINING = frozenset({"data.start", "data.duration", "data.near_plane",
                                  *(f"train.densify.{name}" for name in DensifyConfig.OFFICIAL)}) | FAMILY_OPTIONS


def _resolved_by_data(asked: Mapping[str, Any], data_path: str | Path) -> dict[str, Any]:
    """What training resolves the options the plan leaves to the data (RESOLVED_AT_TRAINING, None) to on
    `data_path`, dotted with their section; {} when there are none or the data cannot be opened here."""
    data, model, train = asked["data"], asked["model"], asked["train"]
    unset = {f"data.{f.dotted}" for f in iter_fields(data) if f.default is None} | {
        f"model.{f.dotted}" for f in iter_fields(model) if f.default is None} | {
        f"train.{f.dotted}" for f in iter_fields(train) if f.default is None}
    if not unset & RESOLVED_AT_TRAINING:
        return {}
    try:
        dataset = data.open(data_path)
    except (StgcError, OSError):
        return {}
    family = dataset.official_config
    resolved = {"data.start": int(dataset.start), "data.duration": int(dataset.duration),
                "data.near_plane": float(dataset.near_plane)}
    sections = {"model": model.resolved(family),
                "train": train.resolved(not data.points_ship_with(dataset), family)}
    for section, cfg in sections.items():
        resolved.update({f"{section}.{f.dotted}": f.default for f in iter_fields(cfg)})
    return {key: value for key, value in resolved.items() if key in RESOLVED_AT_TRAINING}


def _detected_format(data_path: str | Path) -> str:
    try:
        return detect_format(Path(data_path))
    except StgcError:
        return "auto"


def _same_plan_option(key: str, before: Any, now: Any, out_dir: Path) -> bool:
    """`same_option_value`, except that a loss reference the plan puts in its own experiment folder is that folder's
    run by name: the folder may have moved since (the runner records absolute paths)."""
    if key == "compaction.loss_reference" and before and now and Path(str(now)).resolve().parent == out_dir.resolve():
        return Path(str(before)).name == Path(str(now)).name
    return same_option_value(key, before, now)


def _dotted_keys(section: Any, prefix: str = "") -> set[str]:
    """The dotted option names a saved config section holds (a config.json of an older stgc lacks newer options:
    those are not compared)."""
    if not isinstance(section, Mapping):
        return set()
    keys: set[str] = set()
    for name, value in section.items():
        keys |= _dotted_keys(value, f"{prefix}{name}.") if isinstance(value, Mapping) else {f"{prefix}{name}"}
    return keys


def _failed(outcomes: Sequence[RunOutcome]) -> bool:
    """Whether a run's training or evaluation failed (its first outcome; codec points come after it)."""
    return bool(outcomes) and outcomes[0].status == "failed"


def _waves(plan: Plan) -> list[list[int]]:
    """The plan's run indices in waves: runs trained from scratch first, then each fine-tuning run in the wave
    after its source's, and each run with a loss reference in the wave after the reference's (both are always
    listed before the runs that need them). The runs start in this order, each as soon as what it needs has
    finished."""
    depth: dict[str, int] = {}
    for spec in plan.runs:
        needs = [name for name in (spec.source, spec.reference) if name is not None]
        depth[spec.name] = max((depth[name] + 1 for name in needs), default=0)
    waves: list[list[int]] = [[] for _ in range(max(depth.values(), default=0) + 1)]
    for index, spec in enumerate(plan.runs):
        waves[depth[spec.name]].append(index)
    return waves


def build_eval_command(target: str | Path, *, python: str = sys.executable) -> list[str]:
    return [python, "-m", CLI_MODULE, "eval", str(target), "--json"]


def build_compress_command(run_dir: str | Path, out: str | Path, config: CodecConfig, *,
                           python: str = sys.executable) -> list[str]:
    """`stgc compress` with `config`'s options (those that differ from the defaults named)."""
    named = [f"codec.{f.dotted}={f.default}" for f in iter_fields(config)
             if f.dotted != "quality" and f.default != getattr(CodecConfig(), f.dotted)]
    return [python, "-m", CLI_MODULE, "compress", str(run_dir), "--out", str(out), "--quality", str(config.quality),
            *[arg for option in named for arg in ("--set", option)]]


# ------------------------------------------------------------------------------------------- state


def _read_json(path: Path) -> dict[str, Any] | None:
    # A damaged marker file means "not done": the run is redone rather than the plan stopped.
    return read_json_object(path, strict=False)


def run_is_finished(run_dir: str | Path) -> bool:
    """Finished = its training summary says finished and its evaluation record scored that finished model."""
    return Run(run_dir).evaluated_finished_model()


def parse_overrides(items: Sequence[str] | Mapping[str, Any] | None) -> dict[str, str]:
    """["key=value", ...] or {key: value} -> {key: "value"}."""
    if not items:
        return {}
    if isinstance(items, Mapping):
        return {str(k): str(v) for k, v in items.items()}
    out = {}
    for item in items:
        if "=" not in item:
            raise ValueError(f"override {item!r} is not key=value")
        k, v = item.split("=", 1)
        out[k.strip()] = v.strip()
    return out


@dataclass
class RunOutcome:
    name: str
    family: str
    label: str
    status: str  # finished | skipped | failed | dry-run
    run_dir: Path
    overrides: dict[str, str]
    record: dict[str, Any] | None = None
    seconds: float = 0.0
    message: str = ""
    bitstream: str | None = None
    # Failed because its folder holds a run made with other settings (reuse refused; nothing was trained).
    stale: bool = False


@dataclass
class PlanResult:
    plan: Plan
    out_dir: Path
    outcomes: list[RunOutcome] = field(default_factory=list)
    results_csv: Path | None = None
    report: Report | None = None

    @property
    def failed(self) -> list[RunOutcome]:
        return [o for o in self.outcomes if o.status == "failed"]

    def __str__(self) -> str:
        lines = [f"plan {self.plan.name}: {len(self.outcomes)} rows in {self.out_dir}"]
        for o in self.outcomes:
            r = o.record or {}
            psnr = f"{r['psnr']:.2f} dB" if isinstance(r.get("psnr"), (int, float)) else "-"
            rate = f"{r['mbps']:.3f} Mbps" if isinstance(r.get("mbps"), (int, float)) else "-"
            msg = f"  ({o.message})" if o.message else ""
            lines.append(f"  {o.status:<9} {o.name:<32} {psnr:>10} {rate:>14}{msg}")
        if self.results_csv:
            lines.append(f"results: {self.results_csv}")
        if self.report:
            lines.append(str(self.report))
        return "\n".join(lines)


Runner = Callable[[list[str], Path], int]


def subprocess_runner(cmd: list[str], log_path: Path) -> int:
    """Run `cmd` with stdout and stderr appended to `log_path`; return its exit status."""
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "a") as log:
        log.write(f"\n$ {' '.join(cmd)}\n")
        log.flush()
        return subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, env=os.environ.copy(),
                              preexec_fn=_die_with_parent).returncode


def _die_with_parent() -> None:
    """In the child, before exec: Linux kills it when the runner dies. A Ray worker killed mid-run must not leave
    its `stgc train` behind, training on beside the retry that resumes the same run."""
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)


def _result_row(plan: Plan, o: RunOutcome, out_dir: Path, seed: int | None) -> dict[str, Any]:
    row = record_fields(_reportable_record(o) or {})
    try:
        rel = o.run_dir.relative_to(out_dir)
    except ValueError:
        rel = o.run_dir
    return {"plan": plan.name, "name": o.name, "family": o.family, "label": o.label, "seed": seed,
            "status": o.status, **row,
            "overrides": " ".join(f"{k}={v}" for k, v in o.overrides.items()),
            "run_dir": str(rel) + (f"/{o.bitstream}" if o.bitstream else "")}


def write_results(path: Path, plan: Plan, outcomes: Sequence[RunOutcome], out_dir: Path) -> None:
    reported = _reported(outcomes)
    # Each seed's runs are curves of their own: two seeds of one entry are not two rate points of one curve.
    seed_of = {spec.name: spec.seed for spec in plan.runs}
    points: dict[int, str] = {}
    for seed in {seed_of.get(o.run_dir.name) for o in outcomes}:
        points |= rate_points([reported[id(o)] for o in outcomes
                              if id(o) in reported and seed_of.get(o.run_dir.name) == seed])
    with atomic_open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=RESULT_COLUMNS)
        writer.writeheader()
        for o in outcomes:
            row = _result_row(plan, o, out_dir, seed_of.get(o.run_dir.name))
            row["rate_point"] = points.get(id(reported[id(o)])) if id(o) in reported else None
            writer.writerow({k: ("" if row.get(k) is None else row[k]) for k in RESULT_COLUMNS})


def _reported(outcomes: Sequence[RunOutcome]) -> dict[int, ReportRow]:
    """{id(outcome): its report row} of the outcomes that have a result to report."""
    records = {id(o): _reportable_record(o) for o in outcomes}
    return {id(o): ReportRow.from_mapping({**record_fields(record), "name": o.label, "family": o.family,
                                           "run": o.name})
            for o in outcomes if (record := records[id(o)]) is not None}


def _reportable_record(o: RunOutcome) -> dict[str, Any] | None:
    """The outcome's evaluation record where it is the outcome's result: not for a failed or dry-run outcome, nor
    for a record of a model the finished run does not end with (the check `stgc report` applies to the same
    records, so that results-<plan>.csv, the plan's report and `stgc report OUT/*` agree)."""
    if o.record is None or o.status in ("failed", "dry-run"):
        return None
    if scored_earlier_model(o.record, Run(o.run_dir).read_summary(strict=False)):
        return None
    return o.record


def _write_report(plan: Plan, outcomes: Sequence[RunOutcome], report_dir: Path, bd_method: str) -> Report | None:
    """The plan's report (None, and an earlier one's files removed, where no run has a result). A plan over seeds
    reports each entry's mean over its seeds, with the spread and the change against the baseline seed by seed
    (spread.py) as a table of the report and report_dir/seeds.csv."""
    (report_dir / "seeds.csv").unlink(missing_ok=True)  # an earlier report's, with other seeds or none
    reported = _reported(outcomes)
    if not reported:
        remove_report(report_dir)
        return None
    rows = list(reported.values())
    notes: tuple[str, ...] = ()
    spreads: list[EntrySpread] = []
    if plan.seeds:
        spreads = seed_spread(plan, {(o.run_dir.name, o.bitstream): reported[id(o)]
                                     for o in outcomes if id(o) in reported})
        rows = [spread.mean_row() for spread in spreads]
        notes = (spread_markdown(spreads, baseline_entry(plan)),)
        uneven = sorted(spread.entry for spread in spreads if sorted(spread.rows) != sorted(plan.seeds))
        if uneven:  # a failed seed: those rows' means are over fewer seeds than the others'
            notes = (f"**Averaged over fewer seeds than the plan's {list(plan.seeds)}** (a run failed): "
                     f"{', '.join(uneven)}; compare their rows with the others' with care (the seeds table says "
                     "which seeds each has).", *notes)
    report = make_report(rows, report_dir, plan.baseline, title=plan.title or f"Plan {plan.name}",
                         bd_method=bd_method,  # type: ignore[arg-type]
                         notes=notes, baseline_may_be_missing=True)  # the plan's: its runs may have failed
    if spreads:  # beside a report that was written, never left from a failed one
        write_spread_csv(report_dir / "seeds.csv", spreads)
    return report


def run_plan(
    data_path: str | Path,
    plan: str | Path | Plan,
    out_dir: str | Path,
    preset: str | None = "cpu",
    extra_overrides: Sequence[str] | Mapping[str, Any] | None = None,
    codec_qualities: Sequence[int] = (),
    *,
    runner: Runner = subprocess_runner,
    command_builder: Callable[..., list[str]] = build_train_command,
    python: str = sys.executable,
    make_report_files: bool = True,
    preprocess: str | None = None,
    bd_method: str = "pchip",
    dry_run: bool = False,
    log: Callable[[str], None] | None = None,
    check_options: bool = True,
    use_ray: bool = False,
    ray_address: str | None = None,
    seeds: Sequence[int] = (),
) -> PlanResult:
    """Train, evaluate (and optionally compress + evaluate at each codec quality) every run of `plan` under
    OUT, skipping what is already done; write OUT/results-<plan>.csv and the report in OUT/report-<plan>.

    `extra_overrides` apply to every run and win over the plan's own. Each run (training, evaluation, its codec
    points) is a task (`stgc.distributed.run_tasks`): with use_ray on a local Ray or the cluster at
    `ray_address`, else one after another here. `runner(cmd, log_path) -> exit status` and `command_builder` are
    injectable (tests use a fake trainer). `seeds`: train every run once per seed (plans.with_seeds); the report
    then gives each run's mean over its seeds and the spread (spread.py)."""
    if use_ray and ray_address is not None:
        check_reachable(ray_address)  # refused in seconds, before anything is written
    plan = load_plan(plan, preprocess, seeds)
    # Absolute: a worker on another node reads relative paths against its own working directory.
    data_path, out_dir = Path(data_path).resolve(), Path(out_dir).resolve()
    extra = parse_overrides(extra_overrides)
    if plan.seeds and "train.seed" in extra:
        raise ConfigError(f"--set train.seed: plan {plan.name} trains seeds {list(plan.seeds)}, one per run; give "
                          "the seeds there (--seeds), not as an option of every run")
    say = log or _log.info  # stgc's one channel for messages: stderr, silenced by -q
    results_csv = out_dir / f"results-{plan.name}.csv"
    result = PlanResult(plan, out_dir, results_csv=results_csv)
    qualities = [int(q) for q in codec_qualities]
    check_codec_baseline(plan, qualities)
    if check_options:  # off only for a stand-in trainer with options of its own (tests)
        check_plan_options(plan, preset, extra, out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)  # after the checks: a refused plan leaves no folder

    per_spec: list[list[RunOutcome]] = [[] for _ in plan.runs]
    index_of = {spec.name: index for index, spec in enumerate(plan.runs)}
    # Runs trained from scratch first, then the runs that need another (a fine-tuning run its source, a budgeted
    # run its loss reference): each starts as soon as what it needs has finished, not when a whole batch has.
    order = [index for wave in _waves(plan) for index in wave]
    tasks: list[Task] = []
    indices: list[int] = []
    task_of: dict[str, int] = {}
    for index in order:
        spec = plan.runs[index]
        run_dir = out_dir / spec.name
        overrides = run_overrides(plan, spec, extra, out_dir)
        if dry_run:
            outcome = RunOutcome(spec.name, spec.family, spec.label, "skipped", run_dir, overrides)
            if not run_is_finished(run_dir):
                outcome.status = "dry-run"
                outcome.message = " ".join(
                    build_eval_command(run_dir, python=python) if Run(run_dir).training_finished()  # scored again
                    else command_builder(data_path, run_dir, preset, overrides, python=python) if spec.source is None
                    else build_finetune_command(out_dir / spec.source, run_dir, spec.iterations,
                                                finetune_overrides(spec, extra), python=python))
            per_spec[index] = [outcome]
            continue
        task_of[spec.name] = len(tasks)
        tasks.append(Task(name=spec.name, function=run_spec,
                          args=(spec, run_dir, data_path, preset, overrides,
                                qualities if spec.codec_qualities is None else list(spec.codec_qualities),
                                runner, command_builder,
                                python, out_dir / "logs" / f"{spec.name}.log", say, extra, check_options,
                                plan.name),
                          num_cpus=_run_cpus(preset, overrides), progress=Run(run_dir).progress,
                          log_file=Run(run_dir).task_log_path,
                          after=tuple(task_of[name] for name in (spec.source, spec.reference) if name is not None)))
        indices.append(index)

    def record(index: int, outcomes: list[RunOutcome]) -> None:
        per_spec[index] = outcomes
        result.outcomes = [o for group in per_spec for o in group]
        write_results(results_csv, plan, result.outcomes, out_dir)  # after every run: a kill keeps what is done

    def start_if(task_index: int) -> bool:
        index = indices[task_index]
        spec = plan.runs[index]
        needed = [(what, name) for what, name in (("source", spec.source), ("loss reference", spec.reference))
                  if name is not None and _failed(per_spec[index_of[name]])]
        if not needed:
            return True
        what, name = needed[0]
        record(index, [RunOutcome(spec.name, spec.family, spec.label, "failed", out_dir / spec.name,
                                  run_overrides(plan, spec, extra, out_dir),
                                  message=f"its {what} run {name!r} failed")])
        return False

    if tasks:
        run_tasks(tasks, use_ray=use_ray, address=ray_address, start_if=start_if,
                  on_done=lambda task_index, outcomes: record(indices[task_index], outcomes))
    result.outcomes = [o for group in per_spec for o in group]
    write_results(results_csv, plan, result.outcomes, out_dir)

    if make_report_files and not dry_run:
        result.report = _write_report(plan, result.outcomes, out_dir / f"report-{plan.name}", bd_method)
    return result


def run_spec(spec: RunSpec, run_dir: Path, data_path: str | Path, preset: str | None, overrides: dict[str, str],
             qualities: Sequence[int], runner: Runner, command_builder: Callable[..., list[str]], python: str,
             log_path: Path, say: Callable[[str], None], extra: Mapping[str, str] | None = None,
             check_config: bool = True, plan_name: str | None = None) -> list[RunOutcome]:
    """One run of a plan, as a task: train (or resume, or skip when finished), evaluate, and each codec point. A
    problem found on the way (a damaged record, a bitstream that cannot be read) fails this run's row and lets
    the runs that need it be marked failed, instead of ending the plan without their rows. `plan_name`: the plan
    whose entry (family, label) RUN/experiment.json gets (none without it)."""
    try:
        return _run_spec(spec, run_dir, data_path, preset, overrides, qualities, runner, command_builder, python,
                         log_path, say, extra, check_config, plan_name)
    except StgcError as error:
        say(f"[{spec.name}] FAILED: {error}")
        return [RunOutcome(spec.name, spec.family, spec.label, "failed", run_dir, overrides, message=str(error))]


def _run_spec(spec: RunSpec, run_dir: Path, data_path: str | Path, preset: str | None, overrides: dict[str, str],
              qualities: Sequence[int], runner: Runner, command_builder: Callable[..., list[str]], python: str,
              log_path: Path, say: Callable[[str], None], extra: Mapping[str, str] | None,
              check_config: bool, plan_name: str | None = None) -> list[RunOutcome]:
    outcome = RunOutcome(spec.name, spec.family, spec.label, "skipped", run_dir, overrides)
    extra = dict(extra or {})
    mismatch = reuse_mismatch(run_dir, data_path, preset, overrides, spec, extra, check_config=check_config)
    if mismatch is not None:
        outcome.status, outcome.stale = "failed", True
        outcome.message = (f"{run_dir} holds a run made with other settings ({mismatch}); give another --out, or "
                           "remove that run to train it again")
        say(f"[{spec.name}] FAILED: {outcome.message}")
        return [outcome]
    start = time.perf_counter()
    if run_is_finished(run_dir):
        say(f"[{spec.name}] finished earlier: skipped")
        # Reused, perhaps by another plan than the one that trained it: `stgc report` finds this plan's family and
        # label there too. What the run was trained with stays as recorded (a run copied in by hand gets this).
        recorded = Run(run_dir).experiment_path.is_file()
        _record_entry(run_dir, spec, plan_name, None if recorded else _run_entry(overrides, preset, data_path))
    else:
        outcome.status = _train_and_eval(spec, run_dir, data_path, preset, overrides, extra, runner,
                                         command_builder, python, log_path, say, outcome, plan_name)
    outcome.seconds = time.perf_counter() - start
    # Only a finished model's evaluation: a failed run's eval.json, if any, is an earlier one's (a record made while
    # it trained, or of the run it was before --overwrite), and its numbers would stand in the failed row.
    outcome.record = Run(run_dir).read_eval(strict=False) if outcome.status in ("finished", "skipped") else None
    outcomes = [outcome]
    if outcome.status != "failed":
        outcomes += [_codec_point(spec, run_dir, q, runner, python, log_path, say, overrides) for q in qualities]
    return outcomes


def _run_cpus(preset: str | None, overrides: Mapping[str, str]) -> int:
    """The CPUs a run's task asks for: its train.threads (0: the whole machine)."""
    try:
        return cpus_for_threads(resolve_configs(preset or "cpu", {}, {}, dict(overrides))["train"].threads)
    except ConfigError:  # a stand-in trainer's own options (tests); check_plan_options reports real ones
        return 1


def _train_and_eval(spec: RunSpec, run_dir: Path, data_path: str | Path, preset: str | None,
                    overrides: dict[str, str], extra: Mapping[str, str], runner: Runner,
                    command_builder: Callable[..., list[str]], python: str, log_path: Path,
                    say: Callable[[str], None], outcome: RunOutcome, plan_name: str | None = None) -> str:
    run_dir.mkdir(parents=True, exist_ok=True)
    entry = _run_entry(overrides, preset, data_path)
    # Recorded now for a run this resumes or finds finished; a new run's --overwrite removes it (it belongs to
    # whatever was there), so it is written again after training, with the other plans' entries kept: a false
    # start of this very run (reuse_mismatch passed) was theirs too.
    before = _record_entry(run_dir, spec, plan_name, entry)
    run = Run(run_dir)
    if not run.training_finished():
        resume = run.checkpoint_path.is_file() and run.has_config()
        if spec.source is not None and not resume:
            # --set's options that act on nothing in this run were left out of `overrides` (run_overrides); the
            # fine-tuning would refuse them after its source trained.
            given = {k: v for k, v in finetune_overrides(spec, extra).items() if k in overrides}
            cmd = build_finetune_command(run_dir.parent / spec.source, run_dir, spec.iterations, given,
                                         python=python)
        else:
            cmd = command_builder(data_path, run_dir, preset, overrides, resume=resume, python=python)
        say(f"[{spec.name}] {'resuming' if resume else 'training'} (log: {log_path})")
        code = runner(cmd, log_path)
        _record_entry(run_dir, spec, plan_name, entry, before)
        if code != 0:
            outcome.message = f"train exited with status {code}; see {log_path}"
            say(f"[{spec.name}] FAILED: {outcome.message}")
            return "failed"
        if not run.training_finished():
            outcome.message = f"train exited 0 but {run.summary_path} does not say finished"
            say(f"[{spec.name}] FAILED: {outcome.message}")
            return "failed"
    if not run.evaluated_finished_model():
        code = runner(build_eval_command(run_dir, python=python), log_path)
        if code != 0 or not run.evaluated_finished_model():
            outcome.message = f"evaluation failed (status {code}); see {log_path}"
            return "failed"
    return "finished"


def _run_entry(overrides: Mapping[str, str], preset: str | None, data_path: str | Path) -> dict[str, Any]:
    """What RUN/experiment.json records of how the run is trained (reuse_mismatch compares it)."""
    return {"overrides": dict(overrides), "preset": preset or "cpu", "data": str(Path(data_path).resolve())}


def _record_entry(run_dir: Path, spec: RunSpec, plan_name: str | None, run_entry: Mapping[str, Any] | None,
                  before: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Write RUN/experiment.json over `before` (default: the file as it is): `run_entry` (_run_entry; None keeps
    what is recorded) and `plan_name`'s entry {name, family, label} under "plans". A run that two plans share
    (table2 and table3) is labelled by each plan its own way. The top-level name, family and label stay the
    first plan's (an older file's are taken as that), as older readers and the report read them. Returns what
    the file holds."""
    path = Run(run_dir).experiment_path
    if before is None:
        before = read_json_object(path, strict=False) or {}
    mine = {"name": spec.name, "family": spec.family, "label": spec.label}
    entry = {**mine, **before, **(run_entry or {})}
    plans = before.get("plans")
    plans = dict(plans) if isinstance(plans, Mapping) else {}
    if plan_name is not None:
        plans[plan_name] = mine
    if plans:
        entry["plans"] = plans
    if not path.is_file() or entry != read_json_object(path, strict=False):
        write_json(path, entry)
    return entry


def _codec_point(spec: RunSpec, run_dir: Path, quality: int, runner: Runner, python: str, log_path: Path,
                 say: Callable[[str], None], overrides: dict[str, str]) -> RunOutcome:
    stgc = run_dir / f"model_q{quality}.stgc"
    json_path, _ = Run(run_dir).eval_paths(bitstream=stgc)
    outcome = RunOutcome(f"{spec.name}-q{quality}", f"{spec.family}{CODEC_SUFFIX}", f"{spec.label} q{quality}",
                         "skipped", run_dir, overrides, bitstream=stgc.name)
    stale = json_path.is_file() and not Run.scored_this_bitstream(_read_json(json_path) or {}, stgc)
    codec = CodecConfig(quality=quality)  # what the point is written with, and what its file is checked against
    # Any file of that name is taken only when it is what compressing the run now would write: one written by hand
    # (another quality, other codec options) or before the run ended (an earlier model) is not this point.
    unlike = _unlike_codec_point(stgc, Run(run_dir), codec) if stgc.is_file() else None
    if unlike is None and stgc.is_file() and written_without_window_depths(stgc, codec):
        unlike = (f"measured its depths again although the model trained through a rate-aware window at "
                  f"q{quality}")
    if unlike is not None:
        say(f"[{spec.name}] {stgc} {unlike}: compressing it again")
    elif stale:
        say(f"[{spec.name}] {json_path.name} scored an earlier {stgc.name}: evaluating it again")
    if unlike is not None or stale or not json_path.is_file():
        if unlike is not None or not stgc.is_file():
            # Written in place (atomically): a failed compress keeps the old file.
            code = runner(build_compress_command(run_dir, stgc, codec, python=python), log_path)
            if code != 0 or not stgc.is_file():
                outcome.status, outcome.message = "failed", f"compress q{quality} failed (status {code})"
                say(f"[{spec.name}] {outcome.message}")
                return outcome
            # Checked again: a run whose final model is gone compresses its latest, an earlier one, and that
            # file's numbers are not the run's point (and compressing it again on every start would not mend it).
            unlike = _unlike_codec_point(stgc, Run(run_dir), codec)
            if unlike is not None:
                outcome.status, outcome.message = "failed", f"compress q{quality} wrote {stgc}, which {unlike}"
                say(f"[{spec.name}] {outcome.message}")
                return outcome
        code = runner(build_eval_command(stgc, python=python), log_path)
        if code != 0 or not json_path.is_file():
            outcome.status, outcome.message = "failed", f"eval of {stgc.name} failed (status {code})"
            say(f"[{spec.name}] {outcome.message}")
            return outcome
        outcome.status = "finished"
    outcome.record = _read_json(json_path)
    if outcome.record is None:  # this point fails; the run's own row and its other points stand
        outcome.status, outcome.message = "failed", f"{json_path}: cannot read the bitstream evaluation"
        say(f"[{spec.name}] {outcome.message}")
    elif scored_earlier_model(outcome.record, Run(run_dir).read_summary(strict=False)):
        # Left out of the report as `stgc report` leaves it out; the row says why instead of standing empty.
        outcome.status, outcome.message = "failed", (f"{json_path} scored a model the run does not end with "
                                                     f"(iteration {outcome.record.get('iterations')})")
        say(f"[{spec.name}] {outcome.message}")
    return outcome


def _unlike_codec_point(path: Path, run: Run, codec: CodecConfig) -> str | None:
    """Why the .stgc file at `path` is not what `stgc compress` of `run` with `codec` (the runner's command,
    build_compress_command) writes now, or None when it is: the quality its header stores, the model it holds
    (metadata `iteration` against the run's final iteration) and the codec options its metadata records (an
    allocation asked for by name, the run config left out). A whole-video container is checked segment by segment
    against the run's segments. A file written before its metadata recorded codec_options is taken as of the
    defaults."""
    try:
        if is_video_stgc(path):
            segments = run.segments()
            index = read_video_index(path)
            if len(segments) != index.num_segments:
                return f"holds {index.num_segments} segments, the run {len(segments) or 'none'}"
            with open(path, "rb") as f:
                for k, (segment, entry) in enumerate(zip(segments, index.entries)):
                    f.seek(entry.offset)  # one segment's bytes at a time: a whole video can be large
                    why = _unlike_model(f.read(entry.length), f"{path} segment {k}", segment, codec)
                    if why is not None:
                        return f"segment {k} {why}"
            return None
        if run.is_video():
            return "holds one model, the run is a whole video of segments"
        return _unlike_model(read_capped(path), str(path), run, codec)
    except (StgcError, OSError) as exc:  # FormatError, DataError: damaged, truncated, another format's version
        return f"cannot be read ({exc})"


def _unlike_model(data: bytes, source: str, run: Run, codec: CodecConfig) -> str | None:
    """`_unlike_codec_point` for one model's bitstream `data` (named `source` in errors) of `run`."""
    quality = read_header(data, source).quality
    if quality != codec.quality:
        return f"stores quality {quality}, not {codec.quality}"
    metadata = decode_metadata(data, source)
    final, iteration = run.final_iteration(), metadata.get("iteration")
    if final is not None and iteration != final:
        held = "a model of no recorded iteration" if iteration is None else f"the model of iteration {iteration}"
        return f"holds {held}, not the one the run ended with (iteration {final})"
    asked = None if codec.allocation == "auto" else codec.allocation  # what compress records (its metadata)
    if metadata.get("allocation_option") != asked:
        return (f"was written with codec.allocation={metadata.get('allocation_option', 'auto')}, not "
                f"{codec.allocation}")
    recorded, asked_for = metadata.get("codec_options") or {}, custom_codec_options(codec)
    if recorded != asked_for:  # files written before 2026-11-28 record none: taken as the defaults'
        differing = sorted(set(recorded) | set(asked_for), key=str)
        shown = ", ".join(f"codec.{name}={recorded.get(name, 'default')}" for name in differing
                          if recorded.get(name) != asked_for.get(name))
        return f"was written with {shown}, not the runner's options"
    if codec.embed_run_config and run.has_config() and "run_config" not in metadata:
        return "was written without the run's config (codec.embed_run_config=false)"
    if not codec.embed_run_config and "run_config" in metadata:
        return "embeds the run's config (codec.embed_run_config=true)"
    foreign = foreign_model(run, metadata)
    if foreign is not None:  # `stgc eval` records it as `foreign` and every report leaves it out
        return f"holds another run's model ({foreign})"
    return None
