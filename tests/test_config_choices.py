"""Fixed-choice options (typed `Literal[...]`) are checked against their values by `validate_config`, not only by the
command line's and config.json's parsers: a config built in Python with a typo (stats_views="Last") trained as the
other choice (the code tests `== "last"`), then its config.json could not be read back, so resume and eval failed
only after the training time was spent."""

from __future__ import annotations

import dataclasses
import importlib
import json
import pkgutil
import types
import typing
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import stgc
from stgc.codec.files import CodecConfig
from stgc.config import ConfigError, from_saved, to_dict, validate_config
from stgc.options import section_classes
from stgc.compaction import CompactionConfig
from stgc.data import DataConfig
from stgc.train import DensifyConfig, Trainer, TrainConfig, train

TYPOS = [  # values a type checker lets through when they come from user input or a sweep, not from literals
    (TrainConfig(densify=DensifyConfig(stats_views="Last")),
     "train.densify.stats_views: 'Last' is not one of last, all"),
    (TrainConfig(densify=DensifyConfig(stats_count="in-frustum")),
     "train.densify.stats_count: 'in-frustum' is not one of rendered, in_frustum"),
    (TrainConfig(colour_correction="yes"),
     "train.colour_correction: 'yes' is not one of auto, on, off"),
]


@pytest.mark.parametrize("config, message", TYPOS)
def test_a_typo_in_a_fixed_choice_option_is_refused(config, message):
    with pytest.raises(ConfigError) as caught:
        validate_config(config, "train")
    assert str(caught.value) == message


@pytest.mark.parametrize("config, message", TYPOS)
def test_the_refusal_reads_as_the_parsers(config, message):
    """The same value given on the command line or in config.json is refused with the same words."""
    with pytest.raises(ConfigError) as caught:
        from_saved(TrainConfig, json.loads(json.dumps(to_dict(config))), "train")
    assert str(caught.value) == message


@pytest.mark.parametrize("config", [
    TrainConfig(densify=DensifyConfig(stats_views="last", stats_count="in_frustum"), colour_correction="on"),
    TrainConfig(densify=DensifyConfig(stats_views="all", stats_count="rendered"), colour_correction="off"),
    TrainConfig(),
])
def test_valid_choices_pass_and_read_back(config):
    assert validate_config(config, "train") is config
    assert from_saved(TrainConfig, json.loads(json.dumps(to_dict(config))), "train") == config


def test_a_value_must_be_the_choice_itself_not_one_equal_to_it():
    """config.json records the value as it is: True for 1, or a choice's look-alike of another type, would not read
    back as what the run compared."""
    with pytest.raises(ConfigError, match="train.colour_correction: True is not one of auto, on, off"):
        validate_config(TrainConfig(colour_correction=True), "train")


@pytest.fixture()
def tiny_data(tmp_path: Path):
    from scenes import write_n3dv_scene

    from stgc.data import open_dataset

    return open_dataset(write_n3dv_scene(tmp_path / "data"))


@pytest.mark.parametrize("entry", ["Trainer", "train"])
@pytest.mark.parametrize("config, message", TYPOS)
def test_the_trainer_refuses_a_typo_before_the_run_folder_is_written(tiny_data, tmp_path, entry, config, message):
    out = tmp_path / "run"
    with pytest.raises(ConfigError) as caught:
        if entry == "Trainer":
            Trainer(tiny_data, None, None, config, None, out)
        else:
            train(tiny_data, None, None, config, None, out)
    assert str(caught.value) == message
    assert not out.exists()


def literal_choices(tp: Any) -> tuple[tuple[Any, ...], bool] | None:
    """(the values, whether None is allowed too) of `Literal[...]`, `Optional[Literal[...]]` or `Literal[...] | None`;
    None for any other type (found here, not by stgc.config's own helper, so that a fault there cannot hide a
    field)."""
    args = typing.get_args(tp) if typing.get_origin(tp) in (typing.Union, types.UnionType) else (tp,)
    choices = [a for a in args if a is not type(None)]
    if len(choices) == 1 and typing.get_origin(choices[0]) is typing.Literal:
        return typing.get_args(choices[0]), len(args) == 2
    return None


# Every config section a command validates: the sections of a run, and the codec's options (stgc compress).
ROOTS: dict[str, type] = {**section_classes(), "codec": CodecConfig}


def _config_classes() -> set[type]:
    """Every config dataclass of stgc: a dataclass whose fields carry the `help` the command line shows."""
    found: set[type] = set()
    for module in pkgutil.walk_packages(stgc.__path__, "stgc."):
        for value in vars(importlib.import_module(module.name)).values():
            if (isinstance(value, type) and dataclasses.is_dataclass(value) and value.__module__.startswith("stgc.")
                    and any("help" in f.metadata for f in dataclasses.fields(value))):
                found.add(value)
    return found


def _sections(cls: type) -> Iterator[tuple[tuple[str, ...], type]]:
    """(path of field names, class) of `cls` and of every config dataclass nested in it."""
    yield (), cls
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        inner = [a for a in (typing.get_args(hints[f.name]) or (hints[f.name],)) if a is not type(None)]
        if len(inner) == 1 and isinstance(inner[0], type) and dataclasses.is_dataclass(inner[0]):
            for path, nested in _sections(inner[0]):
                yield (f.name, *path), nested


def _literal_fields() -> Iterator[tuple[str, tuple[str, ...], str, tuple[Any, ...], bool]]:
    """(section, path to the nested config, field, choices, optional) of every fixed-choice option."""
    for section, root in ROOTS.items():
        for path, cls in _sections(root):
            hints = typing.get_type_hints(cls)
            for f in dataclasses.fields(cls):
                kind = literal_choices(hints[f.name])
                if kind is not None:
                    yield section, path, f.name, *kind


LITERAL_FIELDS = list(_literal_fields())


def test_every_config_class_is_a_validated_section():
    """A config class outside these sections would hold options no `validate_config` call reaches."""
    reachable = {cls for root in ROOTS.values() for _, cls in _sections(root)}
    assert _config_classes() <= reachable


def test_the_fixed_choice_options_are_found():
    names = {".".join((section, *path, name)) for section, path, name, _, _ in LITERAL_FIELDS}
    assert {"train.densify.stats_views", "train.densify.stats_count", "train.colour_correction",
            "train.quantization_aware.allocation", "model.decoder_activation", "codec.allocation"} <= names
    # A choice inside another type (a tuple of choices, a choice or a number) is not checked: such a field needs
    # validate_config taught first.
    for section, root in ROOTS.items():
        for path, cls in _sections(root):
            hints = typing.get_type_hints(cls)
            for f in dataclasses.fields(cls):
                if "Literal" in repr(hints[f.name]):
                    assert literal_choices(hints[f.name]) is not None, (section, *path, f.name, hints[f.name])


def _with_value(section: str, path: tuple[str, ...], name: str, value: Any) -> Any:
    """The default config of `section` with the option set to `value`, past any check its constructor makes
    (ModelConfig.__post_init__), as a config loaded by other code or changed in place would hold it."""
    config = ROOTS[section]()
    target = config
    for step in path:
        target = getattr(target, step)  # a default_factory's own instance: config holds the only reference
    object.__setattr__(target, name, value)
    return config


@pytest.mark.parametrize("section, path, name, choices, optional", LITERAL_FIELDS,
                         ids=[".".join((s, *p, n)) for s, p, n, _, _ in LITERAL_FIELDS])
def test_every_fixed_choice_option_is_checked(section, path, name, choices, optional):
    dotted = ".".join((section, *path, name))
    for bad in ("Bogus", str(choices[0]).upper(), f" {choices[0]}", 7, *(() if optional else (None,))):
        with pytest.raises(ConfigError) as caught:
            validate_config(_with_value(section, path, name, bad), section)
        assert str(caught.value) == f"{dotted}: {bad!r} is not one of {', '.join(map(str, choices))}"
    # Each choice (and None where the option may be unset) passes this check; other checks may still refuse
    # a combination, but never for this option's value.
    for good in (*choices, *((None,) if optional else ())):
        try:
            validate_config(_with_value(section, path, name, good), section)
        except (ConfigError, ValueError) as exc:
            assert not str(exc).startswith(f"{dotted}: {good!r} is not one of"), exc


def test_the_choices_alone_can_be_checked_where_a_section_s_other_checks_do_not_apply():
    """`check_choices` checks the fixed choices only, of nested configs too, and lets None pass (the trainer checks
    the sections whose other checks run where they are used); a continuation's carried compaction section (method
    none, its source's loss reference kept) passes both."""
    from stgc.compaction.config import CompactionConfig
    from stgc.config import check_choices
    from stgc.data import DataConfig

    check_choices(None, "compaction")
    carried = CompactionConfig(method="none", loss_reference="/elsewhere/run")
    check_choices(carried, "compaction")
    validate_config(carried, "compaction")
    with pytest.raises(ValueError, match="loss_reference"):
        validate_config(dataclasses.replace(carried, method="st-knn"), "compaction")
    with pytest.raises(ConfigError, match="^data.yuv_range: 'Full' is not one of limited, full$"):
        check_choices(DataConfig(yuv_range="Full"), "data")
    with pytest.raises(ConfigError, match="^train.densify.stats_views: 'Last' is not one of last, all$"):
        check_choices(TYPOS[0][0], "train")


@pytest.mark.parametrize("section, options, message", [
    ("data", lambda: dataclasses.replace(DataConfig(), yuv_range="Full"),
     "data.yuv_range: 'Full' is not one of limited, full"),
    ("compaction", lambda: dataclasses.replace(CompactionConfig(), loss_signal="psnr"),
     "compaction.loss_signal: 'psnr' is not one of training, probe, probe_psnr, prune_damage"),
])
def test_the_trainer_refuses_a_typo_in_any_section_before_the_run_folder_is_written(tiny_data, tmp_path, section,
                                                                                     options, message):
    out = tmp_path / "run"
    configs: dict[str, Any] = {"data": None, "compaction": None, section: options()}
    with pytest.raises(ConfigError) as caught:
        Trainer(tiny_data, configs["data"], None, TrainConfig(), configs["compaction"], out)
    assert str(caught.value) == message
    assert not out.exists()
