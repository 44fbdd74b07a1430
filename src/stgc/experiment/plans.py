"""Plans of runs: the paper's Table 2 and Table 3, or any list of runs in a PLAN.toml.

A run is a name (its directory under the experiment folder), the dotted config overrides that distinguish it
(`data.preprocess=stg-isolated`, `compaction.method=st-knn`, `compaction.case=2`, `compaction.criterion=scale`),
and for the report the RD-curve family it belongs to and the label of its point. Runs with identical overrides
carry identical names across plans, so Table 2 and Table 3 in one folder share their common runs.

PLAN.toml:

    name = "ablation"          # optional, default: the file name
    baseline = "STG"           # family the BD deltas are computed against (default: the first run's)
    [[runs]]
    name = "stg"
    family = "STG"             # optional, default: the name
    label = "no preprocessing" # optional, default: the name
    overrides = { "data.preprocess" = "none", "compaction.method" = "none" }
    # or: overrides = ["data.preprocess=none", "compaction.method=none"]
    [[runs]]
    name = "stg-rate-1e-3"
    from = "stg"               # fine-tune that (earlier) run's finished model instead of training from scratch
    iterations = 1000          # ... for this many more iterations (stgc finetune); overrides: train.* only
    overrides = { "train.quantization_aware.iterations" = 1000, "train.quantization_aware.rate_weight" = 1e-3 }
    codec_qualities = [2]      # this run's .stgc rate points (default: the experiment's --codec-quality)
    [[runs]]
    name = "st-knn-budget"
    loss_reference = "stg"     # an earlier run with compaction.method=reference: this run's damage budget holds
                               # its probe loss against that one's (sets compaction.loss_reference; trains after it)

A plan may also say `seeds = [0, 1, 2]` (or `stgc experiment --seeds 0 1 2` for any plan): every run is then trained
once per seed (train.seed), seed 0 under the run's name and seed s under `<name>-seed<s>`, so that a plan's earlier
runs (trained with the default seed 0) count as its seed 0. A run's `from` and `loss_reference` name the same
seed's run. Two runs of one configuration differ by a few tenths of a dB on a real capture (0.34-0.41 dB between
seeds of panoptic_basketball's `cpu` preset), so a difference at that line needs several seeds; the report then
gives each run's mean over its seeds and the spread, and its change against the baseline seed by seed.
"""

from __future__ import annotations

import difflib
import re
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from stgc.compaction.config import PAPER_RULE
from stgc.codec.format import QUALITY_LEVELS
from stgc.config import ConfigError
from stgc.errors import DataError, FormatError
from stgc.eval.report import CODEC_SUFFIX

PAPER_PREPROCESS = "stg-isolated"
CASES = (1, 2, 3, 4)
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
# Every key a PLAN.toml may hold: a misspelt one would otherwise be dropped and change the experiment silently.
PLAN_KEYS = ("name", "baseline", "title", "runs", "seeds")
RUN_KEYS = ("name", "family", "label", "overrides", "from", "iterations", "codec_qualities", "loss_reference")


@dataclass(frozen=True)
class RunSpec:
    name: str
    overrides: dict[str, str]
    family: str
    label: str
    source: str | None = None  # a run of the same plan whose finished model this one fine-tunes (stgc finetune)
    iterations: int = 0  # with `source`: the iterations trained beyond it
    codec_qualities: tuple[int, ...] | None = None  # this run's .stgc rate points (default: the experiment's)
    # A run of the same plan trained with compaction.method=reference: this run's damage budget holds its probe
    # loss against that one's (compaction.loss_reference = its folder); it trains after it.
    reference: str | None = None
    # In a plan with seeds: the train.seed of this run, and the name of the plan entry it is that seed of.
    seed: int | None = None
    entry: str | None = None

    @property
    def entry_name(self) -> str:
        """The plan entry this run trains: its own name, or in a plan with seeds the entry it is one seed of."""
        return self.entry or self.name


@dataclass(frozen=True)
class Plan:
    name: str
    runs: tuple[RunSpec, ...]
    baseline: str | None = None
    title: str = ""
    notes: tuple[str, ...] = field(default_factory=tuple)
    seeds: tuple[int, ...] = ()  # every entry trained once per seed (`with_seeds`); () = once, as configured


def seed_run_name(entry: str, seed: int) -> str:
    """The folder of seed `seed` of plan entry `entry`: seed 0 (train.seed's default) keeps the entry's name."""
    return entry if seed == 0 else f"{entry}-seed{seed}"


def with_seeds(plan: Plan, seeds: Sequence[int]) -> Plan:
    """`plan` with each run trained once per seed (train.seed = s, named `seed_run_name`), its `from` and
    loss_reference the same seed's runs. Raises ConfigError for seeds that are not distinct integers >= 0, a run
    that sets train.seed itself, or a plan already expanded with other seeds."""
    seeds = tuple(seeds)
    if not seeds:
        return plan
    if not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in seeds) or len(set(seeds)) != len(
            seeds):
        raise ConfigError(f"plan {plan.name}: seeds {list(seeds)}: distinct integers >= 0")
    if plan.seeds:
        if plan.seeds != seeds:
            raise ConfigError(f"plan {plan.name} trains seeds {list(plan.seeds)}; --seeds {' '.join(map(str, seeds))} "
                              "asks for others: give them in one place")
        return plan
    runs = []
    for spec in plan.runs:
        if "train.seed" in spec.overrides:
            raise ConfigError(f"plan {plan.name}, run {spec.name!r}: sets train.seed, which the plan's seeds set "
                              "for every run")
        for seed in seeds:
            runs.append(replace(spec, name=seed_run_name(spec.name, seed),
                                overrides={**spec.overrides, "train.seed": str(seed)},
                                source=None if spec.source is None else seed_run_name(spec.source, seed),
                                reference=None if spec.reference is None else seed_run_name(spec.reference, seed),
                                seed=seed, entry=spec.name))
    names = [r.name for r in runs]
    clash = sorted({n for n in names if names.count(n) > 1})
    if clash:
        raise ConfigError(f"plan {plan.name}: with seeds, {', '.join(clash)} would name two runs; rename the entry")
    return replace(plan, runs=tuple(runs), seeds=seeds)


def _spec(name: str, family: str, label: str, **overrides: Any) -> RunSpec:
    return RunSpec(name, {k.replace("__", "."): str(v) for k, v in overrides.items()}, family, label)


def _uncompacted(preprocess: str) -> RunSpec:
    if preprocess == "none":
        return _spec("stg", "STG", "Trained model", data__preprocess="none", compaction__method="none")
    name = "stg-preprocessed" if preprocess == PAPER_PREPROCESS else f"stg-{preprocess}"
    return _spec(name, "STG", "with preprocessing", data__preprocess=preprocess,
                 compaction__method="none")


def _stknn(case: int, criterion: str, preprocess: str, family: str) -> RunSpec:
    # The paper's tables: its rule as written, whatever stgc's defaults.
    paper = {f"compaction__{key}": value for key, value in PAPER_RULE.items()}
    return _spec(f"st-knn-{criterion}-case{case}" + ("" if preprocess == PAPER_PREPROCESS else f"-{preprocess}"),
                 family, f"Case {case}", data__preprocess=preprocess, compaction__method="st-knn",
                 compaction__case=case, compaction__criterion=criterion, **paper)


def table2_plan(preprocess: str = PAPER_PREPROCESS) -> Plan:
    """Paper Table 2: the trained model without and with preprocessing, and the proposed method (timestamp
    criterion, on the preprocessed model) for Cases 1-4. BD deltas: the proposed curve vs the two STG points."""
    runs = [_uncompacted("none"), _uncompacted(preprocess)]
    runs += [_stknn(c, "timestamp", preprocess, "ST-KNN (proposed)") for c in CASES]
    return Plan("table2", tuple(runs), baseline="STG",
                title="Table 2: STG with/without preprocessing and the proposed ST-KNN compaction")


def table3_plan(preprocess: str = PAPER_PREPROCESS) -> Plan:
    """Paper Table 3: the preprocessed model uncompacted, and Cases 1-4 with the removal criterion `scale`
    (the smaller Gaussian of a pair goes) vs `timestamp` (the later one goes). BD: timestamp vs scale."""
    runs = [_uncompacted(preprocess)]
    runs += [_stknn(c, "scale", preprocess, "ST-KNN (scale)") for c in CASES]
    runs += [_stknn(c, "timestamp", preprocess, "ST-KNN (timestamp)") for c in CASES]
    return Plan("table3", tuple(runs), baseline="ST-KNN (scale)",
                title="Table 3: removal criterion scale vs prominently displayed timestamp")


BUILTIN_PLANS = {"table2": table2_plan, "table3": table3_plan}


def _overrides(value: Any, where: Path, run: str) -> dict[str, str]:
    if value is None:
        return {}
    if isinstance(value, Mapping):
        return {str(k): _toml_scalar(v) for k, v in value.items()}
    if isinstance(value, Sequence) and not isinstance(value, str):
        out = {}
        for item in value:
            if not isinstance(item, str) or "=" not in item:
                raise FormatError(where, f"run {run!r}: override {item!r} is not 'key=value'")
            k, v = item.split("=", 1)
            out[k.strip()] = v.strip()
        return out
    raise FormatError(where, f"run {run!r}: overrides must be a table or a list of 'key=value' strings")


def _toml_scalar(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, Mapping):
        raise TypeError("nested table")
    return str(v)


def load_plan_toml(path: str | Path) -> Plan:
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except OSError as exc:
        raise DataError(path, f"cannot read plan: {exc.strerror or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise FormatError(path, f"invalid TOML: {exc}") from None
    _refuse_unknown_keys(data, PLAN_KEYS, path, "the plan")
    for key in ("name", "baseline", "title"):
        if key in data and not isinstance(data[key], str):
            raise FormatError(path, f"{key} = {data[key]!r}: a string")
    runs_data = data.get("runs")
    if not isinstance(runs_data, list) or not runs_data:
        raise FormatError(path, "a plan needs a non-empty [[runs]] list")
    runs, seen = [], set()
    for i, r in enumerate(runs_data):
        if not isinstance(r, dict) or not isinstance(r.get("name"), str):
            raise FormatError(path, f"runs[{i}] needs a string 'name'")
        name = r["name"]
        _refuse_unknown_keys(r, RUN_KEYS, path, f"run {name!r}")
        for key in ("family", "label", "from", "loss_reference"):
            if key in r and not isinstance(r[key], str):
                raise FormatError(path, f"run {name!r}: {key} = {r[key]!r}: a string")
        if not _NAME.match(name):
            raise FormatError(path, f"run name {name!r}: use letters, digits, '.', '_' or '-' (it is a folder name)")
        if name in seen:
            raise FormatError(path, f"run name {name!r} appears twice")
        seen.add(name)
        try:
            overrides = _overrides(r.get("overrides"), path, name)
        except TypeError:
            raise FormatError(path, f"run {name!r}: override values must be scalars") from None
        source, iterations = r.get("from"), r.get("iterations")
        if source is not None:
            if source not in seen - {name}:
                raise FormatError(path, f"run {name!r}: from = {source!r} must name a run listed before it")
            if not isinstance(iterations, int) or isinstance(iterations, bool) or iterations < 1:
                raise FormatError(path, f"run {name!r}: a run with 'from' needs iterations = N >= 1 (how many more)")
            if "train.iterations" in overrides:
                raise FormatError(path, f"run {name!r}: give the fine-tuning's length as iterations = N, not as the "
                                        "train.iterations override")
            others = sorted(k for k in overrides if not k.startswith("train."))
            if others:
                raise FormatError(path, f"run {name!r}: {', '.join(others)}: a fine-tuning run changes train.* "
                                        f"options only (it keeps {source!r}'s data, model and compaction)")
        elif iterations is not None:
            raise FormatError(path, f"run {name!r}: 'iterations' counts the fine-tuning of a 'from' run; set the "
                                    "training length of a run of its own with train.iterations")
        reference = r.get("loss_reference")
        if reference is not None:
            if reference not in seen - {name}:
                raise FormatError(path, f"run {name!r}: loss_reference = {reference!r} must name a run listed before it")
            if source is not None:
                raise FormatError(path, f"run {name!r}: a fine-tuning run ('from') keeps its source's compaction; "
                                        "loss_reference belongs to a run trained from scratch")
            if "compaction.loss_reference" in overrides:
                raise FormatError(path, f"run {name!r}: set the reference run with loss_reference = NAME, not with "
                                        "the compaction.loss_reference override")
        qualities = r.get("codec_qualities")
        if qualities is not None and (not isinstance(qualities, list) or not all(
                isinstance(q, int) and not isinstance(q, bool) and q in QUALITY_LEVELS for q in qualities)
                or len(set(qualities)) != len(qualities)):
            raise FormatError(path, f"run {name!r}: codec_qualities must be a list of distinct codec qualities "
                                    f"({', '.join(map(str, QUALITY_LEVELS))})")
        runs.append(RunSpec(name, overrides, str(r.get("family", name)), str(r.get("label", name)),
                            None if source is None else str(source), int(iterations or 0),
                            None if qualities is None else tuple(qualities),
                            None if reference is None else str(reference)))
    baseline = data.get("baseline")
    if baseline is not None:
        _check_baseline(baseline, runs, path)
    plan_name = str(data.get("name", path.stem))
    if not _NAME.match(plan_name):  # it names OUT/results-<plan>.csv and OUT/report-<plan>/
        raise FormatError(path, f"plan name {plan_name!r}: use letters, digits, '.', '_' or '-' (it names files)")
    plan = Plan(plan_name, tuple(runs), None if baseline is None else str(baseline), str(data.get("title", "")))
    seeds = data.get("seeds")
    if seeds is None:
        return plan
    if not isinstance(seeds, list) or not seeds:
        raise FormatError(path, f"seeds = {seeds!r}: a non-empty list of distinct integers >= 0")
    try:
        return with_seeds(plan, seeds)
    except ConfigError as exc:
        raise FormatError(path, str(exc)) from None


def _refuse_unknown_keys(table: Mapping[str, Any], known: Sequence[str], path: Path, where: str) -> None:
    unknown = sorted(set(table) - set(known))
    if unknown:
        hints = [f"{k!r}" + (f" (did you mean {close[0]!r}?)" if (close := difflib.get_close_matches(k, known, 1))
                             else "") for k in unknown]
        raise FormatError(path, f"{where}: unknown key(s) {', '.join(hints)}; expected {', '.join(known)}")


def _check_baseline(baseline: str, runs: Sequence[RunSpec], path: Path) -> None:
    """The baseline names a family of the plan, a run of it, or a family's codec points (its name + CODEC_SUFFIX),
    which exist only for runs with codec rate points: the plan's own codec_qualities, or the experiment's
    --codec-quality (checked when the experiment starts, `check_codec_baseline`)."""
    names = {r.family for r in runs} | {r.name for r in runs}
    family = baseline[: -len(CODEC_SUFFIX)] if baseline.endswith(CODEC_SUFFIX) else None
    if baseline not in names and family not in {r.family for r in runs}:
        raise FormatError(path, f"baseline = {baseline!r}: neither a family of its runs "
                                f"({', '.join(sorted({r.family for r in runs}))}), a run name, nor a family's codec "
                                f"points ('<family>{CODEC_SUFFIX}')")


def check_codec_baseline(plan: Plan, codec_qualities: Sequence[int]) -> None:
    """Refuse, before anything trains, a plan whose baseline is a family's codec points when none of that family's
    runs will have any (no codec_qualities in the plan and no --codec-quality)."""
    if plan.baseline is None or not plan.baseline.endswith(CODEC_SUFFIX) or codec_qualities:
        return
    family = plan.baseline[: -len(CODEC_SUFFIX)]
    if not any(r.codec_qualities for r in plan.runs if r.family == family):
        raise ConfigError(f"plan {plan.name}: its baseline {plan.baseline!r} is the codec points of {family}, which "
                          "has no codec rate points: give --codec-quality Q")


def load_plan(plan: str | Path | Plan, preprocess: str | None = None, seeds: Sequence[int] = ()) -> Plan:
    """A Plan from a built-in name ("table2", "table3"; `preprocess` picks their preprocessing rule), a
    PLAN.toml path, or a Plan; with `seeds`, each run trained once per seed (`with_seeds`)."""
    return with_seeds(_load_plan(plan, preprocess), seeds)


def _load_plan(plan: str | Path | Plan, preprocess: str | None) -> Plan:
    if isinstance(plan, Plan):
        return plan
    key = str(plan)
    if key in BUILTIN_PLANS:
        return BUILTIN_PLANS[key](preprocess or PAPER_PREPROCESS)
    path = Path(key)
    if path.suffix.lower() == ".toml" or path.exists():
        if preprocess is not None:  # a TOML plan names its preprocessing in each run's overrides
            raise ConfigError(f"--preprocess {preprocess}: applies to the built-in plans ({', '.join(BUILTIN_PLANS)}) "
                              f"only; {path} sets data.preprocess in its runs' overrides")
        return load_plan_toml(path)
    raise DataError(path, f"unknown plan: expected one of {', '.join(BUILTIN_PLANS)} or a PLAN.toml file")
