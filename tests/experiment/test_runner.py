"""The plan runner with a fake `stgc.cli` (no training): commands, resumability, failures, codec points, report."""

from __future__ import annotations

import csv
import json
import os
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from stgc.compaction import PAPER_RULE
from stgc.config import to_dict
from stgc.errors import FormatError
from stgc.experiment import (
    build_train_command,
    load_plan,
    load_plan_toml,
    run_is_finished,
    run_plan,
    table2_plan,
    table3_plan,
)
from stgc.experiment.runner import subprocess_runner
from stgc.train.behaviour import recorded_behaviour
from stgc.train.config import PRESETS, train_preset

FAKE_CLI = Path(__file__).with_name("fake_stgc_cli.py")
# The train section a training of each preset writes in config.json, for the fake's (it imports no stgc: a
# subprocess per run): the runner reads a run's config.json as a training's and compares it with the plan.
os.environ["STGC_FAKE_TRAIN"] = json.dumps({name: to_dict(train_preset(name)) for name in PRESETS})
# And the behaviour changes a training of today records (a run without them was trained before them all).
os.environ["STGC_FAKE_BEHAVIOUR"] = json.dumps(recorded_behaviour())


def fake_runner(cmd: list[str], log_path: Path) -> int:
    """Run the real command line with `-m stgc.cli` swapped for the fake script."""
    assert cmd[1:3] == ["-m", "stgc.cli"], cmd
    return subprocess_runner([cmd[0], str(FAKE_CLI), *cmd[3:]], log_path)


def _invocations(out: Path) -> list[str]:
    path = out / "invocations.txt"
    return path.read_text().splitlines() if path.exists() else []


def _results(out: Path, plan: str = "mini") -> list[dict[str, str]]:
    with open(out / f"results-{plan}.csv") as f:
        return list(csv.DictReader(f))


PLAN_TOML = """
name = "mini"
baseline = "STG"
[[runs]]
name = "stg"
family = "STG"
label = "uncompacted"
overrides = { "compaction.method" = "none", "data.preprocess" = "none" }
[[runs]]
name = "pre"
family = "STG"
overrides = ["compaction.method=none", "data.preprocess=stg-isolated"]
[[runs]]
name = "c1"
family = "ST-KNN"
label = "Case 1"
overrides = { "compaction.method" = "st-knn", "compaction.case" = 1 }
[[runs]]
name = "c3"
family = "ST-KNN"
label = "Case 3"
overrides = { "compaction.method" = "st-knn", "compaction.case" = 3, "fake.no_eval" = "1" }
[[runs]]
name = "broken"
family = "ST-KNN"
overrides = { "compaction.method" = "st-knn", "compaction.case" = 2, "fake.fail" = "1" }
"""


def test_the_fake_cli_writes_today_s_compaction_defaults() -> None:
    from fake_stgc_cli import FAKE_COMPACTION_DEFAULTS

    from stgc.compaction import CompactionConfig

    assert {k: getattr(CompactionConfig(), k) for k in FAKE_COMPACTION_DEFAULTS} == FAKE_COMPACTION_DEFAULTS
    # Every option a config.json without it reads otherwise than today's default: the fake must write it.
    changed = {k for k, v in CompactionConfig.SAVED_BEFORE.items() if getattr(CompactionConfig(), k) != v}
    assert changed <= set(FAKE_COMPACTION_DEFAULTS)


def test_builtin_plans_match_the_paper() -> None:
    t2, t3 = table2_plan(), table3_plan()
    assert [r.label for r in t2.runs] == ["Trained model", "with preprocessing", "Case 1", "Case 2", "Case 3",
                                         "Case 4"]
    assert t2.runs[0].overrides == {"data.preprocess": "none", "compaction.method": "none"}
    # The paper's rule as written, whatever stgc's defaults (they hold a damage budget since session 37).
    assert t2.runs[5].overrides == {"data.preprocess": "stg-isolated", "compaction.method": "st-knn",
                                    "compaction.case": "4", "compaction.criterion": "timestamp",
                                    "compaction.pair_order": "distance", "compaction.loss_signal": "training",
                                    "compaction.loss_budget_db": "0.0", "compaction.ratio_max": "0.02",
                                    "compaction.removal_rate_max": "0.0", "compaction.reset_settle_steps": "0"}
    assert {r.overrides.get("compaction.criterion") for r in t3.runs} == {None, "scale", "timestamp"}
    assert t3.baseline == "ST-KNN (scale)" and len(t3.runs) == 9
    # Shared runs have the same name in both tables, so one folder serves both.
    assert {r.name for r in t2.runs} & {r.name for r in t3.runs} >= {"st-knn-timestamp-case1", "stg-preprocessed"}
    assert load_plan("table3", preprocess="closest-pairs").runs[0].overrides["data.preprocess"] == "closest-pairs"


def test_train_command_layout() -> None:
    cmd = build_train_command("DATA", "OUT/r", "cpu", {"compaction.case": "2"}, python="py")
    assert cmd == ["py", "-m", "stgc.cli", "train", "DATA", "--out", "OUT/r", "--overwrite", "--preset", "cpu",
                   "--set", "compaction.case=2"]
    resumed = build_train_command("DATA", "OUT/r", "cpu", {"compaction.case": "2"}, resume=True, python="py")
    assert resumed == ["py", "-m", "stgc.cli", "train", "DATA", "--out", "OUT/r", "--resume"]


def test_the_resume_command_is_accepted_by_the_cli(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The runner's resume command must pass the CLI's own checks (a resumed run refuses overrides)."""
    import stgc.cli
    import stgc.data
    from stgc.cli import main

    run = tmp_path / "r"
    run.mkdir()
    (run / "config.json").write_text('{"data": {}, "model": {}, "train": {"iterations": 10}, '
                                     '"compaction": {"method": "st-knn", "case": "3"}}')
    calls = []
    monkeypatch.setattr(stgc.data.DataConfig, "open", lambda self, path: SimpleNamespace(
        path=path, train=[], verify_images=lambda cameras, progress=False: 0))
    monkeypatch.setattr(stgc.cli, "train", lambda *a, **k: calls.append((a, k)))
    cmd = build_train_command("DATA", run, "cpu", {"compaction.case": "3"}, resume=True, python="py")
    assert main(cmd[3:]) == 0
    (args, kwargs), = calls
    assert kwargs["resume"] is True and args[4].case == 3


@pytest.mark.parametrize("text, problem", [
    ("[[runs]]\nname = 'a b'\n", "folder name"),
    ("name = 'x'\n", "runs"),
    ("[[runs]]\nname = 'a'\n[[runs]]\nname = 'a'\n", "twice"),
    ("name = '../x'\n[[runs]]\nname = 'a'\n", "names files"),
    ("[[runs\n", "invalid TOML"),
    ("basline = 'STG'\n[[runs]]\nname = 'a'\n", "unknown key.*did you mean 'baseline'"),
    ("baseline = 'STGG'\n[[runs]]\nname = 'a'\nfamily = 'STG'\n", "baseline = 'STGG': neither a family of its runs .STG."),
])
def test_plan_toml_errors(tmp_path: Path, text: str, problem: str) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    with pytest.raises(FormatError, match=problem):
        load_plan_toml(bad)


def test_a_plan_s_baseline_is_a_family_a_run_or_a_family_s_codec_points(tmp_path: Path) -> None:
    for fine in ("STG", "a", "STG + codec"):
        path = tmp_path / "plan.toml"
        path.write_text(f"baseline = '{fine}'\n[[runs]]\nname = 'a'\nfamily = 'STG'\n")
        assert load_plan_toml(path).baseline == fine


def test_run_plan_is_resumable(tmp_path: Path) -> None:
    plan_path = tmp_path / "PLAN.toml"
    plan_path.write_text(PLAN_TOML)
    out = tmp_path / "exp"
    messages: list[str] = []
    first = run_plan("DATA", plan_path, out, preset="cpu", extra_overrides=["train.iterations=10"],
                     codec_qualities=[4], runner=fake_runner, check_options=False, python=sys.executable, log=messages.append)
    status = {o.name: o.status for o in first.outcomes}
    assert status == {"stg": "finished", "stg-q4": "finished", "pre": "finished", "pre-q4": "finished",
                      "c1": "finished", "c1-q4": "finished", "c3": "finished", "c3-q4": "finished",
                      "broken": "failed"}
    calls = _invocations(out)
    trains = [c for c in calls if c.startswith("train")]
    assert len(trains) == 5 and all("--set train.iterations=10" in c and "--preset cpu" in c for c in trains)
    # c3's trainer wrote no eval.json, so the runner evaluated it; every run got compress + eval of q4.
    assert sum(c.startswith("eval") and c.endswith("c3 --json") for c in calls) == 1
    assert sum(c.startswith("compress") for c in calls) == 4
    assert all(run_is_finished(out / n) for n in ("stg", "pre", "c1", "c3")) and not run_is_finished(out / "broken")
    assert json.loads((out / "c1" / "experiment.json").read_text())["family"] == "ST-KNN"
    rows = _results(out)
    assert [r["name"] for r in rows][:2] == ["stg", "stg-q4"] and len(rows) == 9
    c1 = next(r for r in rows if r["name"] == "c1")
    assert float(c1["psnr"]) == pytest.approx(29.7) and c1["status"] == "finished"
    assert "compaction.case=1" in c1["overrides"] and "train.iterations=10" in c1["overrides"]
    assert next(r for r in rows if r["name"] == "broken")["status"] == "failed"
    assert any("FAILED" in m for m in messages)
    report = first.report
    assert report is not None and report.plot_png.is_file()
    md = report.markdown.read_text()
    assert "Case 3" in md and "ST-KNN + codec" in md and "BD-rate" in md
    assert "broken" in str(first) and "failed" in str(first)

    # Second invocation: only the failed run is launched again; nothing else trains, compresses or evaluates.
    second = run_plan("DATA", plan_path, out, preset="cpu", extra_overrides=["train.iterations=10"],
                      codec_qualities=[4], runner=fake_runner, check_options=False, python=sys.executable, log=messages.append)
    new_calls = _invocations(out)[len(calls):]
    assert len(new_calls) == 1 and new_calls[0].startswith("train") and "fake.fail=1" in new_calls[0]
    assert {o.name: o.status for o in second.outcomes}["c1"] == "skipped"
    assert len(_results(out)) == 9

    # An evaluation record made while c1 still trained (`stgc eval` of the half-trained run: no iterations) is
    # stale once the run has finished: the runner scores the finished model instead of reporting that record.
    record = json.loads((out / "c1" / "eval.json").read_text())
    del record["iterations"]
    (out / "c1" / "eval.json").write_text(json.dumps(record | {"psnr": 12.0}))
    assert not run_is_finished(out / "c1")
    third = run_plan("DATA", plan_path, out, preset="cpu", extra_overrides=["train.iterations=10"],
                     codec_qualities=[4], runner=fake_runner, check_options=False, python=sys.executable, log=messages.append)
    c1_calls = [c for c in _invocations(out)[len(calls) + 1:] if f"{out / 'c1'}" in c]
    assert len(c1_calls) == 1 and c1_calls[0].startswith("eval"), c1_calls  # not trained, not compressed again
    assert {o.name: o.status for o in third.outcomes}["c1"] == "finished"
    assert run_is_finished(out / "c1")
    assert float(next(r for r in _results(out) if r["name"] == "c1")["psnr"]) == pytest.approx(29.7)


MINI_PLAN = """
name = "mini"
[[runs]]
name = "stg"
family = "STG"
overrides = { "compaction.method" = "none" }
"""


def _run_mini(out: Path, plan_path: Path, *overrides: str, preset: str = "cpu", data: str = "DATA") -> dict[str, Any]:
    result = run_plan(data, plan_path, out, preset=preset, extra_overrides=list(overrides), codec_qualities=[],
                      runner=fake_runner, check_options=False, python=sys.executable, log=lambda m: None)
    (outcome,) = result.outcomes
    return {"status": outcome.status, "message": outcome.message}


def test_a_finished_run_made_with_other_settings_is_not_reused_as_this_plans(tmp_path: Path) -> None:
    plan_path = tmp_path / "PLAN.toml"
    plan_path.write_text(MINI_PLAN)
    out = tmp_path / "exp"
    assert _run_mini(out, plan_path, "train.iterations=10")["status"] == "finished"
    trained = len(_invocations(out))
    # The same plan again, or with only how it runs changed: the finished run is this plan's run.
    assert _run_mini(out, plan_path, "train.iterations=10", "train.threads=1")["status"] == "skipped"
    for changed in (dict(overrides=("train.iterations=20",)), dict(overrides=("train.iterations=10",), preset="paper"),
                    dict(overrides=("train.iterations=10",), data="OTHER")):
        outcome = _run_mini(out, plan_path, *changed["overrides"], preset=changed.get("preset", "cpu"),
                            data=changed.get("data", "DATA"))
        assert outcome["status"] == "failed" and "other settings" in outcome["message"], changed
    assert "train.iterations: 10 then, 20 now" in _run_mini(out, plan_path, "train.iterations=20")["message"]
    assert len(_invocations(out)) == trained  # nothing trained, resumed or evaluated under the new settings
    rows = _results(out)
    assert [r["status"] for r in rows] == ["failed"] and rows[0]["psnr"] == ""


def test_a_run_copied_in_by_hand_is_checked_against_its_config(tmp_path: Path) -> None:
    plan_path = tmp_path / "PLAN.toml"
    plan_path.write_text(MINI_PLAN)
    out = tmp_path / "exp"
    run = out / "stg"
    run.mkdir(parents=True)
    (run / "config.json").write_text(json.dumps({"data": {}, "model": {}, "train": {"iterations": 10},
                                                 "compaction": {"method": "st-knn"}}))  # a pruned model, not "stg"
    outcome = _run_mini(out, plan_path)
    assert outcome["status"] == "failed" and "compaction.method: st-knn in its config.json, none in the plan" in \
        outcome["message"]
    assert not _invocations(out)


def test_interrupted_run_is_resumed(tmp_path: Path) -> None:
    out = tmp_path / "exp"
    run = out / "stg"
    run.mkdir(parents=True)
    # What a killed trainer leaves: the runner's experiment.json, a config and a checkpoint, no summary, no evaluation.
    plan = load_plan("table2")
    one = type(plan)(plan.name, plan.runs[:1], plan.baseline)
    (run / "experiment.json").write_text(json.dumps({"name": "stg", "overrides": one.runs[0].overrides,
                                                     "preset": "paper"}))
    (run / "config.json").write_text("{}")
    (run / "checkpoint.pt").write_bytes(b"x")
    result = run_plan("DATA", one, out, preset="paper", runner=fake_runner, check_options=False, python=sys.executable,
                      log=lambda m: None)
    (call,) = _invocations(out)
    assert "--resume" in call and "--set" not in call
    assert result.outcomes[0].status == "finished"


def test_dry_run_launches_nothing(tmp_path: Path) -> None:
    result = run_plan("DATA", "table3", tmp_path, runner=fake_runner, check_options=False, dry_run=True, log=lambda m: None)
    assert all(o.status == "dry-run" for o in result.outcomes) and len(result.outcomes) == 9
    assert f"stgc.cli train {Path('DATA').resolve()}" in result.outcomes[1].message and not _invocations(tmp_path)


@pytest.mark.parametrize("plan_name", ["table2", "table3", "demo"])
def test_plan_overrides_are_real_config_keys(plan_name: str) -> None:
    """Every override of the built-in plans names a field the trainer's configs have, with a valid value."""
    from stgc.data.preprocess import MODES
    from stgc.demo import DEMO_SCENE, demo_plan
    from stgc.options import resolve_configs

    plan = demo_plan() if plan_name == "demo" else load_plan(plan_name)
    assert DEMO_SCENE.is_dir()
    for spec in plan.runs:
        assert spec.overrides["data.preprocess"] in MODES
        configs = resolve_configs("cpu", {}, {}, dict(spec.overrides))
        assert configs["data"].preprocess == spec.overrides["data.preprocess"]
        assert configs["compaction"].method == spec.overrides["compaction.method"]
        if "compaction.case" in spec.overrides:
            assert configs["compaction"].case == int(spec.overrides["compaction.case"])
            assert configs["compaction"].criterion == spec.overrides["compaction.criterion"]


def test_two_plans_share_one_folder_and_train_their_common_runs_once(tmp_path: Path) -> None:
    out = tmp_path / "exp"
    quiet = {"runner": fake_runner, "check_options": False, "python": sys.executable, "log": lambda m: None}
    run_plan("DATA", "table2", out, preset="cpu", **quiet)
    trained_by_table2 = [c for c in _invocations(out) if c.startswith("train")]
    run_plan("DATA", "table3", out, preset="cpu", **quiet)
    trained_by_table3 = [c for c in _invocations(out) if c.startswith("train")][len(trained_by_table2):]
    assert len(trained_by_table2) == 6
    assert len(trained_by_table3) == 4 and all("criterion=scale" in c for c in trained_by_table3)
    assert len(_results(out, "table2")) == 6 and len(_results(out, "table3")) == 9
    assert (out / "report-table2" / "report.md").is_file() and (out / "report-table3" / "report.md").is_file()


def test_plan_options_are_checked_before_the_first_run(tmp_path: Path) -> None:
    from stgc.config import ConfigError

    plan_path = tmp_path / "p.toml"
    plan_path.write_text("name = 'p'\n[[runs]]\nname = 'good'\n[runs.overrides]\n'compaction.method' = 'st-knn'\n"
                         "'compaction.case' = '2'\n"
                         "[[runs]]\nname = 'typo'\n[runs.overrides]\n'train.iteratons' = '10'\n")
    calls = []
    with pytest.raises(ConfigError, match="run 'typo'.*did you mean train.iterations"):
        run_plan("DATA", plan_path, tmp_path / "out", runner=lambda cmd, log: calls.append(cmd) or 0,
                 make_report_files=False, log=lambda m: None)
    assert calls == []  # not even the good run started


FINETUNE_TOML = """
name = "rate"
baseline = "STG"
[[runs]]
name = "stg"
family = "STG"
overrides = { "compaction.method" = "none", "data.preprocess" = "none" }
[[runs]]
name = "rate-a"
family = "rate-aware"
from = "stg"
iterations = 100
overrides = { "train.quantization_aware.iterations" = 100, "train.quantization_aware.rate_weight" = 0.001 }
[[runs]]
name = "rate-b"
family = "rate-aware"
from = "rate-a"
iterations = 50
overrides = { "train.quantization_aware.iterations" = 50, "train.quantization_aware.rate_weight" = 0.01 }
codec_qualities = [2]
"""


def test_fine_tuning_runs_start_from_their_finished_source(tmp_path: Path) -> None:
    plan_path = tmp_path / "rate.toml"
    plan_path.write_text(FINETUNE_TOML)
    out = tmp_path / "exp"
    result = run_plan("DATA", plan_path, out, preset="cpu", extra_overrides=["train.threads=1"], runner=fake_runner,
                      codec_qualities=[1, 3], python=sys.executable, log=lambda m: None)
    assert [o.name for o in result.outcomes] == ["stg", "stg-q1", "stg-q3", "rate-a", "rate-a-q1", "rate-a-q3",
                                                 "rate-b", "rate-b-q2"]  # rate-b names its own codec quality
    assert {o.status for o in result.outcomes} == {"finished"}
    calls = [c for c in _invocations(out) if not c.startswith(("compress", "eval"))]
    assert [c.split()[0] for c in calls] == ["train", "finetune", "finetune"]  # each after its source
    assert calls[1].startswith(f"finetune {out / 'stg'} --out {out / 'rate-a'} --iterations 100 --overwrite")
    # --set wins over the plan in every run: its train.* options reach the fine-tuning runs too.
    assert "train.quantization_aware.rate_weight=0.001" in calls[1] and "--set train.threads=1" in calls[1]
    assert calls[2].startswith(f"finetune {out / 'rate-a'} --out {out / 'rate-b'} --iterations 50")
    # The checked options are the source's with the run's own on top (train.threads came from --set).
    rows = {r["name"]: r for r in _results(out, "rate")}
    assert "train.threads=1" in rows["rate-b"]["overrides"] and "rate_weight=0.01" in rows["rate-b"]["overrides"]
    assert float(rows["rate-b"]["psnr"]) == pytest.approx(float(rows["stg"]["psnr"]) - 0.2)
    assert rows["rate-b"]["rate_point"] == "rp01" and rows["rate-a"]["rate_point"] == "rp02"
    again = run_plan("DATA", plan_path, out, preset="cpu", extra_overrides=["train.threads=1"], runner=fake_runner,
                     python=sys.executable, log=lambda m: None)
    assert {o.status for o in again.outcomes} == {"skipped"}, [o.message for o in again.outcomes]
    assert len(_invocations(out)) == 3 + 2 * 5


def test_a_fine_tuning_gets_only_the_set_options_that_act_in_it(tmp_path: Path) -> None:
    """The plan's check leaves --set's options out of the runs where they act on nothing, but the fine-tuning's
    command took them all: `stgc finetune` refuses such an option, so the run failed after its source had trained."""
    plan = FINETUNE_TOML.replace('overrides = { "compaction.method" = "none", "data.preprocess" = "none" }',
                                 'overrides = { "compaction.method" = "none", "data.preprocess" = "none", '
                                 '"model.variant" = "lite" }', 1)
    plan += """[[runs]]
name = "full"
family = "full"
overrides = { "compaction.method" = "none", "data.preprocess" = "none" }
"""
    plan_path = tmp_path / "rate.toml"
    plan_path.write_text(plan)
    out = tmp_path / "exp"
    run_plan("DATA", plan_path, out, preset="cpu", extra_overrides=["train.lr.decoder=0.0002"], runner=fake_runner,
             python=sys.executable, log=lambda m: None)
    calls = [c for c in _invocations(out) if c.startswith(("train", "finetune"))]
    assert sorted(c.split()[0] for c in calls) == ["finetune", "finetune", "train", "train"]
    full = [c for c in calls if f"--out {out / 'full'} " in c]
    assert len(full) == 1 and "train.lr.decoder=0.0002" in full[0]
    assert all("train.lr.decoder" not in c for c in calls if c not in full)  # the lite run and its fine-tunings


def test_set_options_win_over_the_plan_in_fine_tuning_runs_too(tmp_path: Path) -> None:
    plan_path = tmp_path / "rate.toml"
    plan_path.write_text(FINETUNE_TOML)
    from stgc.config import ConfigError

    # An option the plan varies between its runs is refused: under --set they would all train alike, each under the
    # name of its own value.
    with pytest.raises(ConfigError, match="varies it between its runs"):
        run_plan("DATA", plan_path, tmp_path / "refused", preset="cpu", runner=fake_runner, python=sys.executable,
                 extra_overrides=["train.quantization_aware.rate_weight=0.05"], log=lambda m: None)
    plan_path.write_text(FINETUNE_TOML.replace(', "train.quantization_aware.rate_weight" = 0.01', ""))
    out = tmp_path / "exp"
    run_plan("DATA", plan_path, out, preset="cpu", extra_overrides=["train.quantization_aware.rate_weight=0.05"],
             runner=fake_runner, python=sys.executable, log=lambda m: None)
    finetunes = [c for c in _invocations(out) if c.startswith("finetune")]
    assert len(finetunes) == 2
    for call in finetunes:  # not the plan's 0.001 and 0.01
        assert call.count("rate_weight=") == 1 and call.endswith("rate_weight=0.05"), call


@pytest.mark.parametrize("change, reported", [
    (('iterations = 50', 'iterations = 500'), "50 fine-tuning iterations then, 500 now"),
    (('from = "rate-a"', 'from = "stg"'), "fine-tuned from"),
])
def test_a_finished_fine_tuning_run_with_another_source_or_length_is_not_reused(
        tmp_path: Path, change: tuple[str, str], reported: str) -> None:
    plan_path = tmp_path / "rate.toml"
    plan_path.write_text(FINETUNE_TOML)
    out = tmp_path / "exp"
    run_plan("DATA", plan_path, out, preset="cpu", runner=fake_runner, python=sys.executable, log=lambda m: None)
    # rate-b's own options hide what its source added, so only its recorded source and length can tell.
    plan_path.write_text(FINETUNE_TOML.replace(*change))
    calls = len(_invocations(out))
    result = run_plan("DATA", plan_path, out, preset="cpu", runner=fake_runner, python=sys.executable,
                      log=lambda m: None)
    outcome = next(o for o in result.outcomes if o.name == "rate-b")
    assert outcome.status == "failed" and reported in outcome.message, outcome.message
    assert len(_invocations(out)) == calls


def _trained_config(run: Path, preset: str, sets: dict[str, str]) -> None:
    """A config.json as `stgc train` writes it (every option of every section), for these options."""
    from stgc.options import resolve_configs
    from stgc.train.loop import _config_dict

    configs = resolve_configs(preset, {}, {}, sets)
    run.mkdir(parents=True)
    saved = {name: _config_dict(configs[name]) for name in ("data", "model", "train", "compaction")}
    saved["data"]["path"] = str(Path("DATA").resolve())
    (run / "config.json").write_text(json.dumps(saved))


def test_a_run_whose_preset_defaults_moved_is_not_reused(tmp_path: Path) -> None:
    from stgc.experiment.runner import reuse_mismatch

    sets = {"compaction.method": "none", "data.preprocess": "none"}
    run = tmp_path / "exp" / "stg"
    _trained_config(run, "cpu", sets)
    assert reuse_mismatch(run, "DATA", "cpu", sets) is None
    # The same plan entry and recorded options, but the run was trained when the preset meant something else.
    (run / "experiment.json").write_text(json.dumps({"name": "stg", "overrides": sets, "preset": "cpu",
                                                     "data": str(Path("DATA").resolve())}))
    saved = json.loads((run / "config.json").read_text())
    saved["train"]["iterations"] += 3000
    (run / "config.json").write_text(json.dumps(saved))
    assert "train.iterations" in (reuse_mismatch(run, "DATA", "cpu", sets) or "")
    # A run copied in by hand from another preset (no experiment.json), options equal to the plan's.
    other = tmp_path / "exp2" / "stg"
    _trained_config(other, "paper", sets)
    assert "train.iterations" in (reuse_mismatch(other, "DATA", "cpu", sets) or "")


def test_an_old_or_unreadable_config_or_an_option_left_auto_is_compared_not_skipped(tmp_path: Path) -> None:
    """A key an older config.json lacks is compared as SAVED_BEFORE says it trained; a config.json that cannot be
    read is a difference, not a pass; a value the plan leaves 'auto' or None is compared unless training resolves
    it from the data (the frame window, the densification schedule)."""
    from stgc.experiment.runner import reuse_mismatch

    sets = {"compaction.method": "none", "data.preprocess": "none"}

    def saved_run(name: str, edit) -> Path:
        run = tmp_path / name / "stg"
        _trained_config(run, "cpu", sets)
        saved = json.loads((run / "config.json").read_text())
        edit(saved)
        (run / "config.json").write_text(json.dumps(saved))
        return run

    assert reuse_mismatch(saved_run("today", lambda c: None), "DATA", "cpu", sets) is None
    old = saved_run("old", lambda c: c["train"]["floaters"].pop("scale_min_opacity"))  # trained as 0.0
    assert "train.floaters.scale_min_opacity" in (reuse_mismatch(old, "DATA", "cpu", sets) or "")
    unknown = saved_run("unknown", lambda c: c["train"].update(option_of_another_version=1))
    assert "cannot be compared" in (reuse_mismatch(unknown, "DATA", "cpu", sets) or "")
    cameras = saved_run("cameras", lambda c: c["data"].update(test_cameras=[1, 2]))  # the plan's None: compared
    assert "data.test_cameras" in (reuse_mismatch(cameras, "DATA", "cpu", sets) or "")
    colour = saved_run("colour", lambda c: c["train"].update(colour_correction="on"))
    assert "train.colour_correction" in (reuse_mismatch(colour, "DATA", "cpu", sets) or "")
    resolved = saved_run("resolved", lambda c: c["train"]["densify"].update(interval=100, rounds=6))
    assert reuse_mismatch(resolved, "DATA", "cpu", sets) is None
    # An option an older config lacks whose plan value is 'auto' resolves by the data: not known here.
    older = saved_run("older", lambda c: [c["model"].pop(k) for k in ("decoder_ray_origin", "decoder_ray_direction")])
    assert reuse_mismatch(older, "DATA", "cpu", sets) is None
    # An option that acts on nothing in either run (remeasure_at_settle without a window) is no difference.
    idle = saved_run("idle", lambda c: c["train"]["quantization_aware"].pop("remeasure_at_settle"))
    assert reuse_mismatch(idle, "DATA", "cpu", sets) is None
    # The same for compaction options a reference run does not use and a lite model's decoder options: an earlier
    # runner passed --set's to them, and the run trained alike (it was refused as made with other settings).
    reference = {"compaction.method": "reference", "compaction.case": "4", "data.preprocess": "none"}
    _trained_config(tmp_path / "ref" / "stg", "cpu", {**reference, "compaction.ratio_max": "0.05"})
    assert reuse_mismatch(tmp_path / "ref" / "stg", "DATA", "cpu", reference) is None
    lite = {**sets, "model.variant": "lite"}
    _trained_config(tmp_path / "lite" / "stg", "cpu", {**lite, "model.decoder_seed": "3"})
    assert reuse_mismatch(tmp_path / "lite" / "stg", "DATA", "cpu", lite) is None
    # A plan that now names the value a run trained with unnamed (its default then) still names that run.
    (idle / "experiment.json").write_text(json.dumps({"name": "stg", "overrides": sets, "preset": "cpu",
                                                      "data": str(Path("DATA").resolve())}))
    named = {**sets, "train.quantization_aware.remeasure_at_settle": "false"}
    assert reuse_mismatch(idle, "DATA", "cpu", named) is None
    assert "remeasure_at_settle: unset then, true now" in (reuse_mismatch(idle, "DATA", "cpu", {
        **sets, "train.quantization_aware.remeasure_at_settle": "true"}) or "")
    # A pruned run saved before the pair options existed pruned as the paper does: not one that asks for them.
    pruned = {"compaction.method": "st-knn", "compaction.case": "2", "data.preprocess": "none",
              **{f"compaction.{k}": str(v) for k, v in PAPER_RULE.items()}}
    _trained_config(tmp_path / "pruned" / "stg", "cpu", pruned)
    saved = json.loads((tmp_path / "pruned" / "stg" / "config.json").read_text())
    for key in ("keeper_time_coverage", "merge_opacity", "pair_order"):
        saved["compaction"].pop(key)
    (tmp_path / "pruned" / "stg" / "config.json").write_text(json.dumps(saved))
    assert reuse_mismatch(tmp_path / "pruned" / "stg", "DATA", "cpu", pruned) is None
    for key, value in (("merge_opacity", "true"), ("pair_order", "size"), ("keeper_time_coverage", "0.5")):
        assert f"compaction.{key}" in (reuse_mismatch(tmp_path / "pruned" / "stg", "DATA", "cpu",
                                                      {**pruned, f"compaction.{key}": value}) or ""), key
    # Nor is it one of today's defaults (the least-seen losers first, since session 37).
    today = {k: v for k, v in pruned.items() if k != "compaction.pair_order"}
    assert "compaction.pair_order: distance in its config.json, weight in the plan" in (
        reuse_mismatch(tmp_path / "pruned" / "stg", "DATA", "cpu", today) or "")


def test_a_run_on_part_of_the_recording_or_named_by_format_is_checked_against_the_data(tmp_path: Path) -> None:
    """The frame window a plan leaves unset is the whole recording: a run saved with fewer frames is another run.
    A format given by name is the one `auto` finds, either way round."""
    from scenes import write_panoptic_scene

    from stgc.experiment.runner import reuse_mismatch

    scene = write_panoptic_scene(tmp_path / "data", views=4, frames=3)
    sets = {"compaction.method": "none", "data.preprocess": "none"}

    def saved_run(name: str, data: dict, plan_sets: dict[str, str] = sets) -> str | None:
        run = tmp_path / name / "stg"
        _trained_config(run, "cpu", sets)
        saved = json.loads((run / "config.json").read_text())
        saved["data"].update(path=str(scene.root), **data)
        (run / "config.json").write_text(json.dumps(saved))
        return reuse_mismatch(run, scene.root, "cpu", plan_sets)

    assert saved_run("whole", {"start": 0, "duration": 3, "format": "panoptic"}) is None
    assert "data.duration: 2 in its config.json, 3 in the plan" in (saved_run("part", {"start": 0, "duration": 2})
                                                                    or "")
    assert saved_run("named", {"start": 0, "duration": 3}, {**sets, "data.format": "panoptic"}) is None
    assert "data.format" in (saved_run("other", {"start": 0, "duration": 3, "format": "blender"}) or "")


def test_a_failed_source_fails_its_fine_tuning_runs_without_launching_them(tmp_path: Path) -> None:
    plan_path = tmp_path / "rate.toml"
    plan_path.write_text(FINETUNE_TOML.replace('"data.preprocess" = "none" }', '"data.preprocess" = "none", "fake.fail" = "1" }', 1))
    out = tmp_path / "exp"
    result = run_plan("DATA", plan_path, out, runner=fake_runner, check_options=False, python=sys.executable,
                      log=lambda m: None)
    assert [o.status for o in result.outcomes] == ["failed"] * 3
    assert "source run 'stg' failed" in result.outcomes[1].message
    assert [c.split()[0] for c in _invocations(out)] == ["train"]


def test_a_set_rate_aware_option_reaches_the_windows_and_skips_the_runs_without_one(tmp_path: Path) -> None:
    """--set applies to every run, but a rate-aware option acts only where a window is: the `stg` run trains
    without it (`stgc train` would refuse it there), the fine-tuning runs get it. A plan entry's own such option
    without a window is refused before anything trains."""
    plan_path = tmp_path / "rate.toml"
    plan_path.write_text(FINETUNE_TOML)
    out = tmp_path / "exp"
    result = run_plan("DATA", plan_path, out, preset="cpu", runner=fake_runner, python=sys.executable,
                      extra_overrides=["train.quantization_aware.lr_scale=0.02"], log=lambda m: None)
    assert {o.status for o in result.outcomes} == {"finished"}
    calls = [c for c in _invocations(out) if c.startswith(("train", "finetune"))]
    assert [("lr_scale=0.02" in c) for c in calls] == [False, True, True], calls
    plan_path.write_text(FINETUNE_TOML.replace('"compaction.method" = "none", "data.preprocess" = "none"',
                                               '"compaction.method" = "none", "data.preprocess" = "none", '
                                               '"train.quantization_aware.quality" = 1'))
    from stgc.config import ConfigError

    with pytest.raises(ConfigError, match="run 'stg'.*without a rate-aware window"):
        run_plan("DATA", plan_path, tmp_path / "refused", preset="cpu", runner=fake_runner, python=sys.executable,
                 log=lambda m: None)


def test_a_run_that_raises_fails_its_row_and_the_runs_that_need_it(tmp_path: Path, monkeypatch) -> None:
    """A problem found while a run is handled (a damaged file it reads) fails that run's row, and the fine-tuning
    runs that need it get rows saying so, instead of the plan ending without them."""
    import stgc.experiment.runner as runner_module
    from stgc.errors import StgcError

    def broken(spec, *args, **kwargs):
        raise StgcError(f"{spec.name}: a damaged file")

    monkeypatch.setattr(runner_module, "_train_and_eval", broken)
    plan_path = tmp_path / "rate.toml"
    plan_path.write_text(FINETUNE_TOML)
    result = run_plan("DATA", plan_path, tmp_path / "exp", preset="cpu", runner=fake_runner, python=sys.executable,
                      use_ray=False, log=lambda m: None)
    assert [(o.name, o.status) for o in result.outcomes] == [("stg", "failed"), ("rate-a", "failed"),
                                                            ("rate-b", "failed")]
    assert "a damaged file" in result.outcomes[0].message and "source run 'stg' failed" in result.outcomes[1].message
    assert [r["name"] for r in _results(tmp_path / "exp", "rate")] == ["stg", "rate-a", "rate-b"]


@pytest.mark.parametrize("run, problem", [
    ('name = "x"\nfrom = "later"\niterations = 5', "must name a run listed before it"),
    ('name = "x"\nfrom = "stg"', "needs iterations = N >= 1"),
    ('name = "x"\nfrom = "stg"\niterations = 5\noverrides = { "data.downscale" = 2 }', "train.* options only"),
    ('name = "x"\niterations = 5', "counts the fine-tuning of a 'from' run"),
    ('name = "x"\ncodec_qualities = [0]', "codec_qualities must be a list"),
    ('name = "x"\nloss_reference = "later"', "must name a run listed before it"),
    ('name = "x"\nfrom = "stg"\niterations = 5\nloss_reference = "stg"', "keeps its source's compaction"),
    ('name = "x"\nloss_reference = "stg"\noverrides = { "compaction.loss_reference" = "y" }', "not with the"),
    # A misspelt or mistyped key would be dropped, and the run train something else under its name.
    ('name = "x"\noveride = { "compaction.method" = "st-knn" }', "unknown key.*'overide' .did you mean 'overrides'"),
    ('name = "x"\nloss_referense = "stg"', "unknown key.*did you mean 'loss_reference'"),
    ('name = "x"\nfrom = ["stg"]\niterations = 5', "from = \\['stg'\\]: a string"),
    ('name = "x"\nfamily = 3', "family = 3: a string"),
    ('name = "x"\ncodec_qualities = [2, 2]', "distinct codec qualities"),
    ('name = "x"\nfrom = "stg"\niterations = 5\noverrides = { "train.iterations" = 9 }', "not as the train.iter"),
])
def test_fine_tuning_runs_and_loss_references_in_a_plan_are_checked(tmp_path: Path, run: str, problem: str) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text(f'[[runs]]\nname = "stg"\n[[runs]]\n{run}\n[[runs]]\nname = "later"\n')
    with pytest.raises(FormatError, match=problem):
        load_plan_toml(bad)


REFERENCE_TOML = """
name = "budget"
[[runs]]
name = "pruned-first"
overrides = { "compaction.method" = "st-knn", "compaction.loss_signal" = "probe", "compaction.loss_budget_db" = 0.3 }
[[runs]]
name = "ref"
overrides = { "compaction.method" = "reference", "compaction.case" = 4 }
[[runs]]
name = "budget"
loss_reference = "ref"
overrides = { "compaction.method" = "st-knn", "compaction.case" = 4, "compaction.loss_signal" = "probe", "compaction.loss_budget_db" = 0.3 }
"""


def test_a_run_with_a_loss_reference_trains_after_it_and_is_pointed_at_its_folder(tmp_path: Path) -> None:
    plan_path = tmp_path / "budget.toml"
    plan_path.write_text(REFERENCE_TOML)
    out = tmp_path / "exp"
    result = run_plan("DATA", plan_path, out, preset="cpu", runner=fake_runner, python=sys.executable,
                      log=lambda m: None)
    assert {o.status for o in result.outcomes} == {"finished"}
    calls = [c for c in _invocations(out) if c.startswith("train")]
    folders = [c.split()[3] for c in calls]  # the first wave's two may run in either order
    assert sorted(folders[:2]) == [str(out / "pruned-first"), str(out / "ref")] and folders[2] == str(out / "budget")
    assert f"compaction.loss_reference={out / 'ref'}" in calls[2]
    assert "loss_reference" not in calls[0] + calls[1]
    failing = tmp_path / "failing.toml"
    failing.write_text(REFERENCE_TOML.replace('"compaction.case" = 4 }', '"compaction.case" = 4, "fake.fail" = "1" }', 1))
    failed = run_plan("DATA", failing, tmp_path / "exp2", runner=fake_runner, check_options=False,
                      python=sys.executable, log=lambda m: None)
    assert failed.outcomes[-1].status == "failed" and "loss reference run 'ref' failed" in failed.outcomes[-1].message


def test_plan_tasks_get_absolute_paths_whatever_the_user_typed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # A Ray worker on another node reads a relative path against its own working directory.
    import stgc.experiment.runner as runner

    tasks: list[Any] = []
    monkeypatch.setattr(runner, "run_tasks", lambda given, **kw: tasks.extend(given))
    monkeypatch.chdir(tmp_path)
    (tmp_path / "PLAN.toml").write_text(MINI_PLAN)
    run_plan("DATA", "PLAN.toml", "exp", make_report_files=False, check_options=False, log=lambda m: None)
    (task,) = tasks
    spec, run_dir, data_path = task.args[:3]
    assert run_dir == tmp_path / "exp" / "stg" and Path(data_path) == tmp_path / "DATA"



def test_a_moved_experiment_folder_keeps_its_fine_tuning_runs(tmp_path: Path) -> None:
    plan_path = tmp_path / "rate.toml"
    plan_path.write_text(FINETUNE_TOML)
    run_plan("DATA", plan_path, tmp_path / "exp", preset="cpu", runner=fake_runner, python=sys.executable,
             log=lambda m: None)
    (tmp_path / "exp").rename(tmp_path / "moved")
    again = run_plan("DATA", plan_path, tmp_path / "moved", preset="cpu", runner=fake_runner, python=sys.executable,
                     log=lambda m: None)
    assert {o.status for o in again.outcomes} == {"skipped"}, [o.message for o in again.outcomes]
    # So does a run pruned against a loss reference in the folder (recorded as an absolute path that moved too).
    plan_path.write_text(REFERENCE_TOML)
    run_plan("DATA", plan_path, tmp_path / "budget", preset="cpu", runner=fake_runner, python=sys.executable,
             log=lambda m: None)
    (tmp_path / "budget").rename(tmp_path / "budget-moved")
    again = run_plan("DATA", plan_path, tmp_path / "budget-moved", preset="cpu", runner=fake_runner,
                     python=sys.executable, log=lambda m: None)
    assert {o.status for o in again.outcomes} == {"skipped"}, [o.message for o in again.outcomes]


def test_a_baseline_recorded_with_set_compaction_options_is_still_this_plans(tmp_path: Path) -> None:
    """An earlier runner passed --set's compaction options to runs that prune nothing too, and recorded them; they
    never acted there, so the finished baseline is reused (it was refused as made with other settings)."""
    from stgc.experiment.runner import reuse_mismatch

    run = tmp_path / "exp" / "stg"
    run.mkdir(parents=True)
    then = {"compaction.method": "none", "compaction.rotation_weight": "0.02"}
    (run / "experiment.json").write_text(json.dumps({"name": "stg", "overrides": then, "preset": "cpu",
                                                     "data": str(tmp_path / "DATA")}))
    assert reuse_mismatch(run, tmp_path / "DATA", "cpu", {"compaction.method": "none"}) is None
    assert "compaction.rotation_weight" in (reuse_mismatch(run, tmp_path / "DATA", "cpu", {
        "compaction.method": "st-knn", "compaction.rotation_weight": "0.05"}) or "")
    # The method itself is never dropped: a pruned run is not a plan's unpruned one.
    (run / "experiment.json").write_text(json.dumps({"name": "stg", "overrides": {"compaction.method": "st-knn"},
                                                     "preset": "cpu", "data": str(tmp_path / "DATA")}))
    assert "compaction.method: st-knn then" in (reuse_mismatch(run, tmp_path / "DATA", "cpu", {}) or "")


def test_a_loss_reference_is_the_same_folder_however_spelled(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from stgc.experiment.runner import reuse_mismatch

    monkeypatch.chdir(tmp_path)
    run = tmp_path / "exp" / "budget"
    run.mkdir(parents=True)
    # Recorded when the experiment was run with a relative --out; today's runner passes absolute paths.
    then = {"compaction.method": "st-knn", "compaction.loss_reference": "exp/stg"}
    (run / "experiment.json").write_text(json.dumps({"name": "budget", "overrides": then, "preset": "cpu",
                                                     "data": str(tmp_path / "DATA")}))
    now = {**then, "compaction.loss_reference": str(tmp_path / "exp" / "stg")}
    assert reuse_mismatch(run, tmp_path / "DATA", "cpu", now) is None
    other = {**then, "compaction.loss_reference": str(tmp_path / "exp" / "other")}
    assert "compaction.loss_reference" in (reuse_mismatch(run, tmp_path / "DATA", "cpu", other) or "")


def test_set_compaction_options_skip_the_runs_that_prune_nothing_and_a_plan_that_sets_them_there_is_refused(
        tmp_path: Path) -> None:
    from stgc.config import ConfigError
    from stgc.experiment.runner import check_plan_options, run_overrides

    plan = load_plan_toml_text(tmp_path, MINI_PLAN + '[[runs]]\nname = "c2"\nfamily = "ST-KNN"\n'
                               'overrides = { "compaction.method" = "st-knn", "compaction.case" = 2 }\n')
    extra = {"compaction.criterion": "scale"}
    stg, c2 = plan.runs
    assert "compaction.criterion" not in run_overrides(plan, stg, extra, tmp_path)  # `stgc train` would refuse it
    assert run_overrides(plan, c2, extra, tmp_path)["compaction.criterion"] == "scale"
    check_plan_options(plan, "cpu", extra, tmp_path)
    # The same for options that act only with another's value: --set's EMA decay reaches the EMA run only.
    smoothing = load_plan_toml_text(tmp_path, MINI_PLAN + '[[runs]]\nname = "c2"\nfamily = "ST-KNN"\n'
                                    'overrides = { "compaction.method" = "st-knn", "compaction.case" = 2 }\n'
                                    '[[runs]]\nname = "c2-ema"\nfamily = "ST-KNN"\noverrides = { '
                                    '"compaction.method" = "st-knn", "compaction.loss_signal" = "training", '
                                    '"compaction.loss_budget_db" = 0, "compaction.loss_smoothing" = "ema" }\n')
    decay = {"compaction.ema_decay": "0.8"}
    assert ["compaction.ema_decay" in run_overrides(smoothing, spec, decay, tmp_path) for spec in smoothing.runs] \
        == [False, False, True]
    check_plan_options(smoothing, "cpu", decay, tmp_path)
    wrong = load_plan_toml_text(tmp_path, MINI_PLAN.replace('"compaction.method" = "none" }',
                                                            '"compaction.method" = "none", "compaction.case" = 3 }'))
    with pytest.raises(ConfigError, match="run 'stg'.*compaction.method is none"):
        check_plan_options(wrong, "cpu", {}, tmp_path)
    too_long = load_plan_toml_text(tmp_path, FINETUNE_TOML.replace(
        '"train.quantization_aware.iterations" = 50', '"train.quantization_aware.iterations" = 80'))
    with pytest.raises(ConfigError, match="run 'rate-b'.*longer than the continuation's 50"):
        check_plan_options(too_long, "cpu", {}, tmp_path)


def load_plan_toml_text(folder: Path, text: str) -> Any:
    path = folder / "plan.toml"
    path.write_text(text)
    return load_plan_toml(path)


def test_the_compress_command_writes_with_the_codec_options_it_is_built_from() -> None:
    """The runner checks a codec point's file against the options it compresses with (written_without_window_depths
    takes the same CodecConfig): the command must carry them all to `stgc compress`."""
    from stgc.cli import build_parser, compress_config
    from stgc.codec import CodecConfig
    from stgc.experiment.runner import build_compress_command

    for config in (CodecConfig(quality=2), CodecConfig(quality=4, allocation="ladder", zstd_level=9,
                                                       adaptive_delta=False, position_bits=14)):
        cmd = build_compress_command("RUN", "RUN/model.stgc", config, python="py")
        assert cmd[:3] == ["py", "-m", "stgc.cli"]
        assert compress_config(build_parser().parse_args(cmd[3:])) == config


def test_options_left_to_the_data_are_compared_as_the_data_resolves_them(tmp_path: Path) -> None:
    """A plan leaves the scaling lr to the data's official config (N3DV: 1.5e-3): a run saved with another value,
    as every run was before the per-dataset values, is another run; one saved with the data's value is this one."""
    from stgc.experiment.runner import reuse_mismatch
    from scenes import write_n3dv_scene

    data = write_n3dv_scene(tmp_path / "n3dv")
    sets = {"compaction.method": "none", "data.preprocess": "none", "data.init_source": "random"}

    def saved_with(name: str, changes: dict[str, dict]) -> str | None:
        run = tmp_path / name / "stg"
        _trained_config(run, "cpu", sets)
        saved = json.loads((run / "config.json").read_text())
        saved["data"].update(path=str(data), start=0, duration=2, format="n3dv", near_plane=0.2)
        saved["train"]["densify"].update(interval=500, rounds=20, prune_in_rounds=True, max_growth=2.0)
        saved["model"].update(trbf_scale_init=0.0, decoder_activation="sigmoid")
        for section, values in changes.items():
            saved[section].update(values)
        (run / "config.json").write_text(json.dumps(saved))
        return reuse_mismatch(run, data, "cpu", sets)

    assert saved_with("n3dv", {"train": {"lr": {**_lr(), "scaling": 1.5e-3}}}) is None
    assert "train.lr.scaling: 0.005 in its config.json, 0.0015 in the plan" in (
        saved_with("old", {"train": {"lr": {**_lr(), "scaling": 5e-3}}}) or "")
    assert "train.densify.rounds: 6 in its config.json, 20 in the plan" in (saved_with("rounds", {
        "train": {"lr": {**_lr(), "scaling": 1.5e-3}, "densify": {**_densify(), "rounds": 6}}}) or "")
    # A plan that named the data's value then and leaves it to the data now asks for the same run.
    run = tmp_path / "n3dv" / "stg"
    (run / "experiment.json").write_text(json.dumps({"name": "stg", "preset": "cpu", "data": str(data),
                                                     "overrides": {**sets, "train.lr.scaling": "0.0015"}}))
    assert reuse_mismatch(run, data, "cpu", sets) is None


def _lr() -> dict:
    from stgc.train.config import LearningRates
    from stgc.train.loop import _config_dict

    return _config_dict(LearningRates())


def _densify() -> dict:
    from stgc.train.config import DensifyConfig
    from stgc.train.loop import _config_dict

    return _config_dict(DensifyConfig().resolved(sparse_cloud=True))


def test_a_plan_is_refused_before_training_where_it_would_fail_or_mislead_after(tmp_path: Path) -> None:
    """A codec baseline without codec points, a --set option acting in no run or of a bad value, a loss reference
    that is no reference run: each refused before anything trains, not after hours."""
    from stgc.config import ConfigError

    plan_path = tmp_path / "PLAN.toml"
    plan_path.write_text(PLAN_TOML.replace('baseline = "STG"', 'baseline = "STG + codec"'))
    with pytest.raises(ConfigError, match="no codec rate points: give --codec-quality"):
        run_plan("DATA", plan_path, tmp_path / "a", runner=fake_runner, python=sys.executable, log=lambda m: None)
    plan_path.write_text(PLAN_TOML)
    for sets, problem in ((["train.quantization_aware.rate_weight=0.01"], "acts on nothing in any run"),
                          (["compaction.ratio_max=banana"], "--set compaction.ratio_max=banana: .*float"),
                          (["train.iterations=ten"], "--set train.iterations=ten")):
        with pytest.raises(ConfigError, match=problem):
            run_plan("DATA", plan_path, tmp_path / "b", extra_overrides=sets, runner=fake_runner,
                     python=sys.executable, log=lambda m: None)
    plan_path.write_text(REFERENCE_TOML.replace('"compaction.method" = "reference", "compaction.case" = 4',
                                                '"compaction.method" = "none"'))
    with pytest.raises(ConfigError, match="loss_reference 'ref' trains with compaction.method=none"):
        run_plan("DATA", plan_path, tmp_path / "c", runner=fake_runner, python=sys.executable, log=lambda m: None)
    assert not any((tmp_path / folder).exists() for folder in "abc")  # nothing written, not even the folder


def test_a_report_whose_baseline_failed_says_so_and_no_stale_report_stays(tmp_path: Path) -> None:
    plan_path = tmp_path / "PLAN.toml"
    plan_path.write_text(MINI_PLAN)
    out = tmp_path / "exp"
    assert _run_mini(out, plan_path, "train.iterations=10")["status"] == "finished"
    report = out / "report-mini" / "report.md"
    assert report.is_file()
    # Now the only run fails (other settings than the finished one): no report can be made, the old one goes.
    assert _run_mini(out, plan_path, "train.iterations=20")["status"] == "failed"
    assert not report.exists() and not (out / "report-mini" / "report.json").exists()


def test_a_baseline_without_results_gives_a_report_without_bd_deltas(tmp_path: Path) -> None:
    from stgc.eval.report import ReportRow, make_report

    rows = [ReportRow("c1", "ST-KNN", mbps=1.0, psnr=30.0), ReportRow("c2", "ST-KNN", mbps=0.8, psnr=29.5)]
    with pytest.raises(ValueError, match="baseline 'STG' is neither"):
        make_report(rows, tmp_path / "r", "STG")
    report = make_report(rows, tmp_path / "r", "STG", baseline_may_be_missing=True)
    assert report.bd == [] and report.baseline is None
    assert "No BD deltas: baseline 'STG' is neither" in report.markdown.read_text()


def test_a_value_spelt_otherwise_or_a_default_dropped_from_the_plan_is_the_same_run(tmp_path: Path) -> None:
    plan_path = tmp_path / "PLAN.toml"
    plan_path.write_text(MINI_PLAN.replace('{ "compaction.method" = "none" }',
                                           '{ "compaction.method" = "st-knn", "compaction.case" = 2 }'))
    out = tmp_path / "exp"
    assert _run_mini(out, plan_path, "compaction.criterion=timestamp")["status"] == "finished"
    assert _run_mini(out, plan_path)["status"] == "skipped"  # the default, named then, unnamed now
    outcome = _run_mini(out, plan_path, "compaction.criterion=scale")
    assert "compaction.criterion: timestamp then, scale now" in outcome["message"]
    out = tmp_path / "exp2"
    assert _run_mini(out, plan_path, "compaction.case=2")["status"] == "finished"
    assert _run_mini(out, plan_path, "compaction.case=02")["status"] == "skipped"


def test_set_values_valid_with_a_run_s_own_options_and_a_fine_tuned_loss_reference(tmp_path: Path) -> None:
    """--set values are checked for their names and types alone (a window longer than the preset's run is fine
    where the plan's runs are longer), while a loss reference that is a fine-tuning run (which trains without
    compaction) is refused before anything trains."""
    from stgc.config import ConfigError

    plan_path = tmp_path / "long.toml"
    plan_path.write_text(MINI_PLAN.replace('{ "compaction.method" = "none" }',
                                           '{ "compaction.method" = "none", "train.iterations" = 20000 }'))
    result = run_plan("DATA", plan_path, tmp_path / "long", extra_overrides=["train.quantization_aware.iterations=10000"],
                      runner=fake_runner, python=sys.executable, log=lambda m: None, dry_run=True)
    assert [o.status for o in result.outcomes] == ["dry-run"]
    plan_path.write_text(REFERENCE_TOML.replace('loss_reference = "ref"', 'loss_reference = "ref-ft"').replace(
        '[[runs]]\nname = "budget"', '[[runs]]\nname = "ref-ft"\nfrom = "ref"\niterations = 5\n[[runs]]\nname = "budget"'))
    with pytest.raises(ConfigError, match="loss_reference 'ref-ft' trains with compaction.method=none"):
        run_plan("DATA", plan_path, tmp_path / "ft", runner=fake_runner, python=sys.executable, log=lambda m: None)


@pytest.mark.parametrize("change, acting, idle", [
    ("mask-prices-rotation-index",
     {"train.quantization_aware.iterations": "100", "train.quantization_aware.rate_weight": "0.001",
      "train.quantization_aware.mask": "true"},
     {"train.quantization_aware.iterations": "100", "train.quantization_aware.rate_weight": "0.001"}),
    ("two-view-tracks-kept", {"data.min_track_length": "2"},
     {"data.min_track_length": "2", "data.init_source": "random"}),
    ("unmeasured-prune-damage-backs-off", {"compaction.method": "st-knn"},
     {"compaction.method": "st-knn", "compaction.loss_signal": "probe_psnr"}),
    ("slow-start-threshold", {"compaction.method": "st-knn"},  # slow start: the default since session 42
     {"compaction.method": "st-knn", "compaction.ratio_increase": "additive"}),
])
def test_session_36_s_behaviour_changes_act_on_their_runs_only(change, acting, idle) -> None:
    from stgc.options import resolve_configs
    from stgc.train.behaviour import missing_behaviour

    def acts(sets: dict[str, str]) -> bool:
        return change in {c.name for c in missing_behaviour({}, resolve_configs("cpu", {}, {}, sets))}

    assert acts(acting) and not acts(idle) and not acts({})


def test_a_run_trained_before_a_behaviour_change_that_acts_on_it_is_not_reused(tmp_path: Path) -> None:
    """config.json records the behaviour changes its code had (stgc.train.behaviour): an ST-KNN run whose capped
    clone/split rounds reach its window trained before 'compaction-not-refilled' is another run; a run the change
    cannot move (no compaction, or no cap) is still reused."""
    from stgc.experiment.runner import reuse_mismatch
    from stgc.train.behaviour import BEHAVIOUR_KEY, recorded_behaviour

    def saved_run(name: str, sets: dict[str, str], behaviour: list[str] | None) -> Path:
        run = tmp_path / name / "stg"
        _trained_config(run, "cpu", sets)
        saved = json.loads((run / "config.json").read_text())
        saved["train"]["densify"].update(interval=500, rounds=20, prune_in_rounds=True, max_growth=2.0)
        if behaviour is not None:
            saved[BEHAVIOUR_KEY] = behaviour
        (run / "config.json").write_text(json.dumps(saved))
        return run

    # (The paper's pair order and signal: the weight order's and the prune-damage budget's own changes would act too.)
    pruned = {"compaction.method": "st-knn", "data.preprocess": "none", "train.densify.interval": "500",
              "train.densify.rounds": "20", "train.densify.max_growth": "2", "train.densify.prune_in_rounds": "true",
              "compaction.pair_order": "distance", "compaction.loss_signal": "training", "compaction.loss_budget_db": "0"}
    assert reuse_mismatch(saved_run("today", pruned, recorded_behaviour()), "DATA", "cpu", pruned) is None
    before = reuse_mismatch(saved_run("before", pruned, None), "DATA", "cpu", pruned) or ""
    assert "compaction-not-refilled" in before
    unpruned = {**pruned, "compaction.method": "none"}
    assert reuse_mismatch(saved_run("unpruned", unpruned, None), "DATA", "cpu", unpruned) is None
    uncapped = {**pruned, "train.densify.max_growth": "0"}
    run = saved_run("uncapped", uncapped, None)
    saved = json.loads((run / "config.json").read_text())
    saved["train"]["densify"]["max_growth"] = 0.0
    (run / "config.json").write_text(json.dumps(saved))
    assert reuse_mismatch(run, "DATA", "cpu", uncapped) is None
    # The importance criterion's views (every frame since 'importance-every-frame') move only its own runs.
    importance = {**uncapped, "compaction.criterion": "importance"}
    run = saved_run("importance", importance, ["compaction-not-refilled"])
    saved = json.loads((run / "config.json").read_text())
    saved["train"]["densify"]["max_growth"] = 0.0
    (run / "config.json").write_text(json.dumps(saved))
    assert "importance-every-frame" in (reuse_mismatch(run, "DATA", "cpu", importance) or "")
