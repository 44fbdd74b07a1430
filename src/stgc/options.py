"""A run's options: the config sections, presets, and how command-line layers and a saved config.json become
config objects. Shared by the command line and the experiment runner (which checks every run's options before its
first training)."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

from stgc.compaction import CompactionConfig
from stgc.compaction.config import idle_compaction_options, settling_after_reset, why_idle
from stgc.compaction.config import resolve_schedule as resolve_pruning_schedule
from stgc.config import ConfigError, apply_overrides, from_saved, split_sections, validate_config
from stgc.data import DataConfig
from stgc.data.config import data_config_from_saved
from stgc.errors import FormatError, StgcError
from stgc.model import ModelConfig
from stgc.model.config import idle_model_options
from stgc.run import Run, check_run_config
from stgc.train.config import TrainConfig, opacity_reset_iterations, refuse_preset_option, train_preset


def section_classes() -> dict[str, type]:
    """The config dataclass of each section."""
    return {"data": DataConfig, "model": ModelConfig, "train": TrainConfig, "compaction": CompactionConfig}


# What a preset sets outside the training schedule. The cpu preset bounds the initial cloud (points from every
# 3rd frame, at most 3,000 per frame: 30k for a 30-frame segment, 51k for a 50-frame one), because dense
# per-frame clouds (e.g. 14k points x 30 frames) would start a 2-core run with hundreds of thousands of Gaussians.
PRESET_DATA_OVERRIDES: dict[str, dict[str, str]] = {
    "cpu": {"init_frames_every": "3", "max_points_per_frame": "3000"},
    "paper": {},
}


def default_configs(preset: str = "cpu") -> dict[str, Any]:
    """Config objects of a `stgc train` run before any option: the preset, and no compaction."""
    classes = section_classes()
    configs = {name: cls() for name, cls in classes.items()}
    configs["train"] = train_preset(preset)
    configs["data"] = apply_overrides(configs["data"], PRESET_DATA_OVERRIDES.get(preset, {}), "data")
    configs["compaction"] = replace(configs["compaction"], method="none")
    return configs


def resolve_configs(
    preset: str,
    shortcuts: dict[str, dict[str, Any]],
    options: dict[str, dict[str, str]],
    sets: dict[str, str],
) -> dict[str, Any]:
    """preset < shortcut flags < --section.field options < --set overrides. A shortcut flag and an option naming
    one option with two values is refused (which should win is a guess), and so are train.preset (the preset's
    name: --preset gives it) and options of a part of training the others switch off (`idle_feature_options`)."""
    layers = (shortcuts, options, split_sections(sets, set(section_classes())))
    refuse_conflicting_flags(shortcuts, layers[1:])
    given = [f"{section}.{key}" for layer in layers for section, values in layer.items() for key in values]
    refuse_preset_option(given)
    configs = default_configs(preset)
    for layer in layers:
        for section, overrides in layer.items():
            configs[section] = apply_overrides(configs[section], overrides, section)
    for section, cfg in configs.items():
        validate_config(cfg, section)
    refuse_training_signal_with_budget(configs["compaction"])
    refuse_unused_feature_options(configs, given)
    return configs


def refuse_conflicting_flags(shortcuts: dict[str, dict[str, Any]], layers: Iterable[dict[str, dict[str, Any]]]) -> None:
    """Raise ConfigError where a shortcut flag (--variant, --quality, ...) and an option (--section.key, --set) give
    one option two values."""
    for layer in layers:
        for section, values in shortcuts.items():
            for key, value in values.items():
                given = (layer.get(section) or {}).get(key)
                if given is not None and str(given).strip() != str(value).strip():
                    raise ConfigError(f"{section}.{key}: given twice, as {value} (its shortcut flag) and as {given}; "
                                      "give it once")


def configs_from_run(run_dir: Path) -> dict[str, Any]:
    """The configs a run was started with (RUN/config.json), but for `train.stop_after` (below). A config.json that
    is not a run's (`check_run_config`) or whose options this version cannot read is a FormatError naming it."""
    run = Run(run_dir)
    path = run.config_path
    saved = run.read_config()
    if saved is None:
        raise StgcError(f"{path}: not found; is {run_dir} a stgc run directory?")
    if "train" not in saved and (run.path / Run.RESTORED_FROM).is_file():
        # `stgc decompress` keeps the data and model options a decoded model is evaluated with, not a training's.
        raise StgcError(f"{run_dir}: holds a model restored from a bitstream (stgc decompress), not a training: its "
                        f"{Run.CONFIG} has no training options, so there is nothing to resume or fine-tune")
    check_run_config(saved, path)

    out: dict[str, Any] = {}
    for name, cls in section_classes().items():
        if name == "compaction" and saved.get(name) is None:
            # `train(..., compaction_cfg=None)` trains without compaction and saves the section as null: it prunes
            # nothing when it trains on (nor does a config without the section).
            out[name] = CompactionConfig(method="none")
            continue
        if name == "data":
            out[name], _ = data_config_from_saved(saved[name], path)
            continue
        # A null model section: `train(..., model_cfg=None)` saved the model options so until 2026-11-27, and trained
        # with the default ones.
        section = dict(saved[name] or {})
        section.pop("path", None)
        resolved = section.pop("resolved_schedule", None)
        if name == "train" and isinstance(resolved, dict) and "iterations" in resolved:
            # Runs saved before `iterations` meant real iterations stored it in schedule units; the resolved
            # schedule always held the real number.
            section["iterations"] = resolved["iterations"]
        try:
            out[name] = validate_config(from_saved(cls, section, name), name)
        except (ValueError, TypeError, AttributeError) as exc:  # ConfigError included: an option named, or not
            message = str(exc)
            named = message.startswith(f"{name}.") or f" {name}." in message
            raise FormatError(path, f"run config: {message if named else f'{name} section: {message}'}") from None
    # stop_after is the option of the command that gave it, not of the run: a run read back (to resume it, fine-tune
    # it or compare it) trains to its end unless a command asks to stop again.
    out["train"] = replace(out["train"], stop_after=None)
    out["data_path"] = saved["data"].get("path")
    return out


def refuse_unused_model_options(model: ModelConfig, given: Iterable[str]) -> None:
    """Raise ConfigError when model options (`given`: dotted names) are set where they act on nothing
    (`idle_model_options`: the decoder's options of a lite model)."""
    unused = sorted(set(given) & idle_model_options(model))
    if unused:
        raise ConfigError(f"{', '.join(unused)}: the lite model has no decoder; choose the full model "
                          "(--variant full) or drop them")


def refuse_training_signal_with_budget(compaction: CompactionConfig) -> None:
    """Raise ConfigError for a new run that asks for the training-loss signal under a damage budget. The budget's
    default (0.3 dB) is the probe signals', and `loss_signal=training` asked alone means the paper's step-to-step
    rule. The pair was allowed until session 39: runs saved with it still read and resume (this is not part of
    `validate`, which a saved config passes through), while a plan row asking for it is refused like a new run."""
    if compaction.method == "st-knn" and compaction.loss_signal == "training" and compaction.loss_budget_db > 0:
        raise ConfigError("compaction.loss_signal training compares the smoothed training loss step to step (the "
                          "paper's rule, with compaction.loss_budget_db=0); the damage budget "
                          f"(compaction.loss_budget_db {compaction.loss_budget_db}, default 0.3) needs a probe signal "
                          "that measures the model, not the sample: set compaction.loss_budget_db=0, or "
                          "loss_signal probe, probe_psnr or prune_damage")


def refuse_unused_compaction_options(compaction: CompactionConfig, given: Iterable[str]) -> None:
    """Raise ConfigError when compaction options (`given`: dotted names such as "compaction.case") are set where
    they act on nothing (`idle_compaction_options`: a run whose compaction.method is none; a custom window with a
    case's own window; ...): they would be recorded in its config.json and silently ignored."""
    unused = sorted(set(given) & idle_compaction_options(compaction))
    if not unused:
        return
    if compaction.method == "none":
        raise ConfigError(f"{', '.join(unused)}: given for a run whose compaction.method is none, where nothing "
                          "is pruned; choose a method (--compaction st-knn) or drop them")
    raise ConfigError("; ".join(why_idle(compaction, key) for key in unused))


# Clone/split's own options: with train.densify.enabled false there are no rounds, so they act on nothing (the
# statistics are gathered for the rounds only). Not among them: start and interval (the steps pruning, floater
# removal and the opacity resets act at), prune_opacity, prune_until and the opacity reset options.
CLONE_SPLIT_OPTIONS = ("rounds", "grad_threshold", "percent_dense", "split_count", "max_gaussians", "max_growth",
                       "prune_in_rounds", "stats_views", "stats_count")

# The learning rates of parameters the lite model does not have: its colour has no decoder and no time features.
FULL_MODEL_RATES = ("decoder", "features_t")


def _feature_idle_reasons(configs: Mapping[str, Any]) -> dict[str, str]:
    """{option (dotted, with its section): why it acts on nothing} for the options of a part of training that the
    run's other options switch off: point preprocessing (data.preprocess none), error-guided sampling
    (train.ems.enabled false), clone/split (train.densify.enabled false), the full model's parameters (a lite
    model) and compaction's wait after opacity resets (no pruning step within the wait after a reset)."""
    data, model, train = configs.get("data"), configs.get("model"), configs.get("train")
    idle: dict[str, str] = {}
    if data is not None and data.preprocess == "none":
        idle["data.preprocess_fraction"] = ("given for a run whose data.preprocess is none, where no point is removed; "
                                            "choose a preprocessing or drop it")
    if train is not None and not train.ems.enabled:
        idle |= {f"train.ems.{f.name}": "given for a run without error-guided sampling (train.ems.enabled is false), "
                                        "where it acts on nothing; enable it or drop it"
                 for f in fields(train.ems) if f.name != "enabled"}
    if train is not None and not train.densify.enabled:
        idle |= {f"train.densify.{name}": "acts only in clone/split rounds, and train.densify.enabled is false (no "
                                          "round is run); enable densification or drop it"
                 for name in CLONE_SPLIT_OPTIONS}
    compaction = configs.get("compaction")
    # 0 (no wait) is what a run without resets does: a plan that pins it stays valid under --set that drops them.
    if train is not None and compaction is not None and compaction.method == "st-knn" \
            and compaction.reset_settle_steps > 0:
        pruning = resolve_pruning_schedule(compaction, train.iterations)
        resets = opacity_reset_iterations(train)
        settle = compaction.reset_settle_steps * pruning.interval
        if not any(settling_after_reset(step, resets, settle) for step in pruning.iterations()):
            idle["compaction.reset_settle_steps"] = (
                f"waits after an opacity reset, and no pruning step comes within {compaction.reset_settle_steps} "
                f"steps after one (resets at {', '.join(map(str, resets)) or 'none'}); drop it")
    if train is not None and model is not None and model.variant == "lite":
        idle |= {f"train.lr.{name}": "the lite model has no decoder and no time features to learn at this rate; "
                                     "choose the full model (--variant full) or drop it"
                 for name in FULL_MODEL_RATES}
    return idle


def idle_feature_options(configs: Mapping[str, Any]) -> set[str]:
    """The options (dotted, with their section) that act on nothing in a run with `configs` because the part of
    training they belong to is switched off (`_feature_idle_reasons`). Given for such a run they are refused
    (`refuse_unused_feature_options`)."""
    return set(_feature_idle_reasons(configs))


def refuse_unused_feature_options(configs: Mapping[str, Any], given: Iterable[str]) -> None:
    """Raise ConfigError when options (`given`: dotted names) are set where they act on nothing
    (`idle_feature_options`): they would be recorded in config.json and silently ignored, and the run taken for
    one trained with them. Only given options count: a preset's or a default's values are no choice."""
    reasons = _feature_idle_reasons(configs)
    by_reason: dict[str, list[str]] = {}
    for key in sorted(set(given) & set(reasons)):
        by_reason.setdefault(reasons[key], []).append(key)
    if by_reason:
        raise ConfigError("; ".join(f"{', '.join(keys)}: {reason}" for reason, keys in by_reason.items()))
