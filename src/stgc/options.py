"""A run's options: the config sections, presets, and how command-line layers and a saved config.json become
config objects. Shared by the command line and the experiment runner (which checks every run's options before its
first training)."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import replace
from pathlib import Path
from typing import Any

from stgc.compaction import CompactionConfig
from stgc.compaction.config import idle_compaction_options, why_idle
from stgc.config import ConfigError, apply_overrides, from_saved, split_sections, validate_config
from stgc.data import DataConfig
from stgc.data.config import data_config_from_saved
from stgc.errors import StgcError
from stgc.model import ModelConfig
from stgc.model.config import idle_model_options
from stgc.run import Run
from stgc.train.config import TrainConfig, train_preset


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
    one option with two values is refused (which should win is a guess)."""
    refuse_conflicting_flags(shortcuts, [options, split_sections(sets, set(section_classes()))])
    configs = default_configs(preset)
    for layer in (shortcuts, options, split_sections(sets, set(configs))):
        for section, overrides in layer.items():
            configs[section] = apply_overrides(configs[section], overrides, section)
    for section, cfg in configs.items():
        validate_config(cfg, section)
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
    """The configs a run was started with (RUN/config.json), but for `train.stop_after` (below)."""
    run = Run(run_dir)
    path = run.config_path
    saved = run.read_config()
    if saved is None:
        raise StgcError(f"{path}: not found; is {run_dir} a stgc run directory?")

    classes = section_classes()
    out: dict[str, Any] = {}
    for name, cls in classes.items():
        if name == "compaction" and saved.get(name) is None:
            # `train(..., compaction_cfg=None)` trains without compaction and saves the section as null; a restored
            # run (`stgc decompress`) has none: neither prunes when it trains on.
            out[name] = CompactionConfig(method="none")
            continue
        section = dict(saved.get(name) or {})
        if name == "data":
            out[name], _ = data_config_from_saved(section, path)
            continue
        section.pop("path", None)
        resolved = section.pop("resolved_schedule", None)
        if name == "train" and isinstance(resolved, dict) and "iterations" in resolved:
            # Runs saved before `iterations` meant real iterations stored it in schedule units; the resolved
            # schedule always held the real number.
            section["iterations"] = resolved["iterations"]
        out[name] = validate_config(from_saved(cls, section), name)
    # stop_after is the option of the command that gave it, not of the run: a run read back (to resume it, fine-tune
    # it or compare it) trains to its end unless a command asks to stop again.
    out["train"] = replace(out["train"], stop_after=None)
    out["data_path"] = (saved.get("data") or {}).get("path")
    return out


def refuse_unused_model_options(model: ModelConfig, given: Iterable[str]) -> None:
    """Raise ConfigError when model options (`given`: dotted names) are set where they act on nothing
    (`idle_model_options`: the decoder's options of a lite model)."""
    unused = sorted(set(given) & idle_model_options(model))
    if unused:
        raise ConfigError(f"{', '.join(unused)}: the lite model has no decoder; choose the full model "
                          "(--variant full) or drop them")


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
