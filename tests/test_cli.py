"""The command line: every verb has help, config options are generated from the dataclasses, errors are one line."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from stgc.cli import build_parser, main
from stgc.config import ConfigError, iter_fields
from stgc.options import default_configs, resolve_configs

VERBS = ["train", "finetune", "eval", "render", "compress", "decompress", "plot", "experiment", "report", "demo"]


@pytest.mark.parametrize("verb", VERBS)
def test_every_verb_has_help(verb, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([verb, "--help"])
    assert exit_info.value.code == 0
    assert "usage: stgc " + verb in capsys.readouterr().out


def test_train_help_lists_every_config_field_with_its_default():
    train = build_parser()._subparsers._group_actions[0].choices["train"]  # type: ignore[union-attr]
    help_text = " ".join(train.format_help().split())
    for section, cfg in default_configs("cpu").items():
        for spec in iter_fields(cfg):
            assert f"--{section}.{spec.dotted}" in help_text
    assert "(default: 0.2)" in help_text  # the cpu preset's schedule_scale, not the dataclass default


def test_precedence_preset_then_options_then_set():
    configs = resolve_configs(
        "cpu",
        {"compaction": {"method": "st-knn", "case": "4"}},
        {"train": {"iterations": "900"}, "compaction": {"case": "4"}},
        {"train.iterations": "1200", "data.preprocess": "stg-isolated"},
    )
    assert configs["train"].iterations == 1200 and configs["train"].preset == "cpu"
    assert configs["compaction"].method == "st-knn" and configs["compaction"].case == 4
    # A shortcut flag (--case 3) and an option giving the same option another value: which wins would be a guess.
    with pytest.raises(ConfigError, match="compaction.case: given twice, as 3"):
        resolve_configs("cpu", {"compaction": {"case": "3"}}, {"compaction": {"case": "4"}}, {})
    with pytest.raises(ConfigError, match="compaction.case: given twice"):
        resolve_configs("cpu", {"compaction": {"case": "3"}}, {}, {"compaction.case": "4"})
    assert configs["data"].preprocess == "stg-isolated" and configs["data"].max_points_per_frame == 3000
    assert default_configs("cpu")["compaction"].method == "none"


@pytest.mark.parametrize(
    "argv,message",
    [
        (["train", "nowhere", "--out", "RUN", "--set", "train.iterationz=5"], "did you mean train.iterations"),
        (["data", "inspect", "no/such/dir"], "no/such/dir"),
        (["eval", "no/such/run"], "no/such/run"),
    ],
)
def test_bad_input_is_one_clear_line(argv, message, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_resume_refuses_options_that_would_be_ignored(tmp_path, capsys):
    (tmp_path / "config.json").write_text("{}")
    assert main(["train", "--out", str(tmp_path), "--resume", "--set", "train.iterations=5"]) == 2
    assert "keeps its saved config.json; drop train.iterations" in capsys.readouterr().err


def test_experiment_passes_preprocess_and_bd_method_to_run_plan(monkeypatch, tmp_path):
    import stgc.cli

    seen = {}

    def fake_run_plan(data, plan, out, **kwargs):
        seen.update(kwargs, data=data, plan=plan)
        return SimpleNamespace(failed=[], outcomes=["r"])

    monkeypatch.setattr(stgc.cli, "run_plan", fake_run_plan)
    assert main(["experiment", "scene", "--plan", "table2", "--out", str(tmp_path), "--preprocess", "closest-pairs",
                 "--bd-method", "cubic", "--codec-quality", "3"]) == 0
    assert seen["preprocess"] == "closest-pairs" and seen["bd_method"] == "cubic"
    assert seen["codec_qualities"] == [3] and seen["plan"] == "table2"


def test_version_and_verbosity_flags(capsys):
    import logging

    from stgc import __version__
    from stgc.cli import configure_logging

    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0 and __version__ in capsys.readouterr().out
    runner_log = logging.getLogger("stgc.experiment.runner")  # a module that reports progress, as every one does
    try:
        for verbosity, shown in [(0, ["info", "warning"]), (-1, []), (1, ["debug", "info", "warning"])]:
            configure_logging(verbosity)
            for level in ("debug", "info", "warning"):
                getattr(runner_log, level)(level)
            err = capsys.readouterr().err
            assert [line.removeprefix("stgc: ") for line in err.splitlines()] == shown, (verbosity, err)
    finally:
        configure_logging(0)


def test_render_names_gif_among_its_outputs(capsys):
    """`stgc render` writes a .gif as it writes an .mp4, but its --out help and its error named only .png and .mp4."""
    render = build_parser()._subparsers._group_actions[0].choices["render"]  # type: ignore[union-attr]
    assert "FILE.gif" in " ".join(render.format_help().split())
    assert main(["render", "nowhere", "--out", "clip.webm"]) == 2
    err = capsys.readouterr().err
    assert "clip.webm" in err and ".gif" in err and ".mp4" in err


def test_export_to_a_splatv_name_without_format_splatv_is_refused(tmp_path, capsys):
    """`stgc export RUN --out x.splatv` without `--format splatv` silently wrote a folder of PLY files named x.splatv;
    it is refused, before anything is read or written, with the flag it wants."""
    assert main(["export", "nowhere", "--out", str(tmp_path / "x.splatv")]) == 2
    err = capsys.readouterr().err
    assert "x.splatv" in err and "--format splatv" in err and "Traceback" not in err
    assert not (tmp_path / "x.splatv").exists()
