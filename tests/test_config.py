from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from typing import Literal

import pytest

from stgc.config import (
    ConfigError,
    add_config_arguments,
    apply_overrides,
    collect_overrides,
    from_dict,
    iter_fields,
    parse_set_arguments,
    same_option_value,
    to_dict,
)


@dataclass(frozen=True)
class Inner:
    threshold: float = field(default=2e-4, metadata={"help": "gradient threshold"})
    rounds: int = field(default=6, metadata={"help": "rounds"})


@dataclass(frozen=True)
class Outer:
    iterations: int = field(default=30000, metadata={"help": "total iterations"})
    criterion: Literal["timestamp", "scale"] = field(default="timestamp", metadata={"help": "which to drop"})
    enabled: bool = field(default=True, metadata={"help": "on/off"})
    limit: int | None = field(default=None, metadata={"help": "optional"})
    times: tuple[float, ...] = field(default=(0.5,), metadata={"help": "sample times"})
    inner: Inner = field(default_factory=Inner)


def test_fields_are_flattened_with_dotted_names():
    names = [s.dotted for s in iter_fields(Outer)]
    assert names == ["iterations", "criterion", "enabled", "limit", "times", "inner.threshold", "inner.rounds"]


def test_overrides_are_coerced_to_the_field_type():
    cfg = apply_overrides(
        Outer(),
        {"iterations": "5000", "criterion": "scale", "enabled": "false", "limit": "none",
         "times": "0.1,0.9", "inner.threshold": "1e-3"},
    )
    assert cfg.iterations == 5000 and cfg.criterion == "scale" and cfg.enabled is False
    assert cfg.limit is None and cfg.times == (0.1, 0.9) and cfg.inner.threshold == pytest.approx(1e-3)
    assert cfg.inner.rounds == 6
    assert apply_overrides(Outer(), {"iterations": "3e4"}).iterations == 30000  # an integer written as a float


@pytest.mark.parametrize(
    "key,value,message",
    [("iterations", "abc", "cannot read"), ("criterion", "size", "not one of"), ("enabled", "maybe", "boolean"),
     ("inner.thresold", "1", "did you mean inner.threshold"), ("nope", "1", "unknown option"),
     ("iterations", "1e-4", "not an integer"), ("iterations", "2.5e0", "not an integer")],
)
def test_bad_overrides_name_the_field(key, value, message):
    with pytest.raises(ConfigError, match=message):
        apply_overrides(Outer(), {key: value})


def test_json_round_trip():
    cfg = apply_overrides(Outer(), {"inner.rounds": "3", "times": "[0.25, 0.75]"})
    assert from_dict(Outer, to_dict(cfg)) == cfg


def test_argparse_options_are_generated_with_defaults_in_help():
    parser = argparse.ArgumentParser()
    add_config_arguments(parser, "train", Outer, "training")
    help_text = parser.format_help()
    assert "--train.inner.threshold" in help_text and "(default: 0.0002)" in help_text
    ns = parser.parse_args(["--train.iterations", "10", "--train.inner.rounds", "2"])
    assert collect_overrides(ns) == {"train": {"iterations": "10", "inner.rounds": "2"}}
    assert parse_set_arguments(["a.b=1", "c=x=y"]) == {"a.b": "1", "c": "x=y"}


def test_path_options_agree_when_they_name_one_place_however_spelled(tmp_path, monkeypatch):
    run = tmp_path / "reference"
    run.mkdir()
    (run / "compaction_log.jsonl").write_text("")
    other = tmp_path / "other"
    other.mkdir()
    monkeypatch.chdir(tmp_path)
    assert same_option_value("compaction.loss_reference", "reference", str(run))
    assert same_option_value("compaction.loss_reference", str(run / "compaction_log.jsonl"), "reference")
    assert same_option_value("data.path", "./reference/../reference", str(run))
    assert not same_option_value("compaction.loss_reference", "reference", str(other))
    assert not same_option_value("compaction.loss_reference", "", str(run))
    # Two files are two places, even in one folder (DATA naming one MIV sequence JSON of several).
    (tmp_path / "A01.json").write_text("{}")
    (tmp_path / "B02.json").write_text("{}")
    assert not same_option_value("data.path", "A01.json", "B02.json")
    assert same_option_value("data.path", "A01.json", str(tmp_path))
    # Other options compare as values: a string that happens to name a folder is not a place.
    assert not same_option_value("train.backend", "reference", str(run))
    assert same_option_value("train.iterations", 9000, 9000)


def test_an_optional_option_whose_value_is_named_none_keeps_it():
    """model.decoder_activation 'none' (the official immersive configs' sandwichnoactss) is a value, and unset
    (the data's family decides) is another: 'none' became unset, then sigmoid, on the command line and read back."""
    from stgc.config import from_saved
    from stgc.model import ModelConfig

    assert apply_overrides(ModelConfig(), {"decoder_activation": "none"}, "model").decoder_activation == "none"
    assert apply_overrides(ModelConfig(), {"decoder_activation": "null"}, "model").decoder_activation is None
    assert from_saved(ModelConfig, {"decoder_activation": "none"}).decoder_activation == "none"
    assert from_saved(ModelConfig, {"decoder_activation": None}).decoder_activation is None
    assert apply_overrides(ModelConfig(), {"trbf_scale_init": "none"}, "model").trbf_scale_init is None  # no clash
