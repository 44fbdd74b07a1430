"""A run's config.json read back (`stgc.options.configs_from_run`: resume, fine-tune, plan reuse): only a config a
stgc training wrote is a run's, and a damaged or outdated one is an error naming the file and the option, never a
traceback and never defaults made up for what it lacks."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from stgc.cli import main
from stgc.config import to_dict
from stgc.errors import FormatError
from stgc.options import configs_from_run, default_configs


def _trained_config(data: Path) -> dict[str, Any]:
    """config.json as a training writes it (every option of every section, the resolved schedule's iterations)."""
    configs = default_configs("cpu")
    train = {**to_dict(configs["train"]), "resolved_schedule": {"iterations": configs["train"].iterations}}
    return {"data": {**to_dict(configs["data"]), "path": str(data)}, "model": to_dict(configs["model"]),
            "train": train, "compaction": to_dict(configs["compaction"]), "behaviour": []}


def _run_with(tmp_path: Path, config: Any, name: str = "run") -> Path:
    run = tmp_path / name
    run.mkdir()
    (run / "config.json").write_text(json.dumps(config))
    return run


def _edited(tmp_path: Path, edit) -> Path:
    config = _trained_config(tmp_path / "DATA")
    edit(config)
    return _run_with(tmp_path, config)


@pytest.mark.parametrize("edit, problem", [
    (lambda c: c.clear() or c.update({"data": {"init_source": "random"}, "comment": "not a stgc run"}),
     "no 'model' section; no 'train' section"),
    (lambda c: c.pop("train"), "no 'train' section"),
    (lambda c: c.update(train={}), "its 'train' section has no iterations"),
    (lambda c: c.update(train=[]), "its 'train' section is [], not an object"),
    (lambda c: c.pop("model"), "no 'model' section"),
    (lambda c: c.pop("data"), "no 'data' section"),
    (lambda c: c.update(compaction={}), "its 'compaction' section is {}, not null or an object with a method"),
    (lambda c: c.update(compaction=[]), "its 'compaction' section is [], not null or an object with a method"),
    (lambda c: c.update(compaction="st-knn"), "its 'compaction' section is 'st-knn'"),
])
def test_a_json_object_that_is_not_a_run_config_is_refused_not_filled_with_defaults(tmp_path, edit, problem):
    """A missing train section read as TrainConfig() (a 30,000-iteration custom schedule), a missing data section as
    DataConfig(), an empty compaction section as ST-KNN: a folder holding any JSON object trained on as a run."""
    run = _edited(tmp_path, edit)
    with pytest.raises(FormatError) as caught:
        configs_from_run(run)
    assert str(run / "config.json") in str(caught.value) and "not a stgc run config" in str(caught.value)
    assert problem in str(caught.value)


def test_resuming_a_folder_with_a_foreign_config_json_is_refused_before_anything_is_written(tmp_path, capsys):
    run = _run_with(tmp_path, {"data": {"init_source": "random"}, "comment": "not a stgc run"}, "foreign2")
    before = (run / "config.json").read_text()
    assert main(["train", str(tmp_path / "DATA"), "--out", str(run), "--resume", "--set", "train.stop_after=2"]) == 2
    err = capsys.readouterr().err
    assert f"{run / 'config.json'}: not a stgc run config" in err and "Traceback" not in err
    assert [p.name for p in run.iterdir()] == ["config.json"] and (run / "config.json").read_text() == before


def test_a_restored_run_is_said_to_hold_no_training(tmp_path, capsys):
    """`stgc decompress` writes the data and model sections only: a decoded model, nothing to resume."""
    config = _trained_config(tmp_path / "DATA")
    run = _run_with(tmp_path, {key: config[key] for key in ("data", "model")}, "restored")
    (run / "restored_from.json").write_text(json.dumps({"bitstream": str(tmp_path / "m.stgc"), "iteration": 10}))
    assert main(["train", "--out", str(run), "--resume"]) == 2
    assert "restored from a bitstream (stgc decompress), not a training" in capsys.readouterr().err
    assert sorted(p.name for p in run.iterdir()) == ["config.json", "restored_from.json"]


@pytest.mark.parametrize("edit, check", [
    (lambda c: None, lambda out: out["compaction"].method == "none" and out["train"].iterations == 9000),
    (lambda c: c["compaction"].update(method="st-knn"), lambda out: out["compaction"].method == "st-knn"),
    # `train(..., compaction_cfg=None)` saves the section as null: no compaction.
    (lambda c: c.update(compaction=None), lambda out: out["compaction"].method == "none"),
    # A restored run's sections (data and model) and a config without one: no compaction either.
    (lambda c: c.pop("compaction"), lambda out: out["compaction"].method == "none"),
    # `train(..., model_cfg=None)` saved the model section as null until 2026-11-27: the default model options.
    (lambda c: c.update(model=None), lambda out: out["model"].variant == "full"),
    # Runs saved before `iterations` meant real iterations: the resolved schedule holds the real number.
    (lambda c: (c["train"].pop("iterations"), c["train"]["resolved_schedule"].update(iterations=12)),
     lambda out: out["train"].iterations == 12),
    # A config saved before an option existed reads as it trained (SAVED_BEFORE), a nested group's too.
    (lambda c: (c["train"]["densify"].pop("max_growth"), c["train"].pop("colour_correction")),
     lambda out: out["train"].densify.max_growth == 0.0 and out["train"].colour_correction == "off"),
    # train.preset is no option any more, but config.json records it: read as it is.
    (lambda c: c["train"].update(preset="paper"), lambda out: out["train"].preset == "paper"),
])
def test_every_config_json_a_training_wrote_still_reads(tmp_path, edit, check):
    out = configs_from_run(_edited(tmp_path, edit))
    assert check(out) and out["data_path"] == str(tmp_path / "DATA")


@pytest.mark.parametrize("edit, named", [
    (lambda c: c["train"].update(bogus=1), "unknown option train.bogus"),
    (lambda c: c["train"]["densify"].update(bogus=1), "unknown option train.densify.bogus"),
    (lambda c: c.update(model=5), "its 'model' section is 5, not an object"),
    (lambda c: c.update(train="abc"), "its 'train' section is 'abc', not an object"),
    (lambda c: c["train"].update(densify=7), "train.densify: 7 is not an object"),
    (lambda c: c["train"]["densify"].update(enabled={"a": 1}), "train.densify.enabled: {'a': 1} is an object"),
    (lambda c: c["train"].update(batch="many"), "train.batch: cannot read 'many'"),
    (lambda c: c["train"]["lr"].update(opacity=-1), "train.lr.opacity: -1"),
    (lambda c: c["model"].update(variant="mid"), "model.variant"),
    (lambda c: c["compaction"].update(case="x"), "compaction.case"),
    (lambda c: c["data"].update(downscale="x"), "data.downscale: cannot read 'x'"),
])
def test_a_damaged_or_outdated_section_is_an_error_naming_the_file_and_the_option(tmp_path, capsys, edit, named):
    """`unknown option bogus` named neither the file nor the section; a section or group that is not an object was a
    TypeError or AttributeError traceback, or 'dictionary update sequence element #0 ...'."""
    run = _edited(tmp_path, edit)
    assert main(["train", "--out", str(run), "--resume"]) == 2
    err = capsys.readouterr().err
    assert f"{run / 'config.json'}: " in err and named in err and "Traceback" not in err, err
