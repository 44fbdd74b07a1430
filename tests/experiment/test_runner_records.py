"""What the plan runner takes for a run's numbers: a codec point's file only when it is the point the runner would
write, a run's evaluation only when the run finished, a record only when it scored the model the run ended with;
and RUN/experiment.json labels a run shared by several plans by each plan (the fake `stgc.cli` of
fake_stgc_cli.py: no training)."""

from __future__ import annotations

import csv
import importlib.util
import json
import sys
from pathlib import Path
from typing import Any

import pytest

from stgc.codec import encode, read_stgc_header
from stgc.codec.synthetic import synthetic_model
from stgc.experiment import run_plan
from stgc.experiment.runner import subprocess_runner

FAKE_CLI = Path(__file__).with_name("fake_stgc_cli.py")

PLAN = """
name = "{name}"
baseline = "{family}"
[[runs]]
name = "stg"
family = "{family}"
label = "{label}"
overrides = {{ "compaction.method" = "none" }}
"""


def fake_runner(cmd: list[str], log_path: Path) -> int:
    """The real command line with `-m stgc.cli` swapped for the fake script."""
    assert cmd[1:3] == ["-m", "stgc.cli"], cmd
    return subprocess_runner([cmd[0], str(FAKE_CLI), *cmd[3:]], log_path)


def _plan(tmp_path: Path, name: str = "mini", family: str = "STG", label: str = "trained") -> Path:
    path = tmp_path / f"{name}.toml"
    path.write_text(PLAN.format(name=name, family=family, label=label))
    return path


def _run(plan: Path, out: Path, qualities: tuple[int, ...] = (), runner: Any = fake_runner) -> Any:
    return run_plan("DATA", plan, out, preset="cpu", codec_qualities=list(qualities), runner=runner,
                    check_options=False, python=sys.executable, log=lambda message: None)


def _fake_stgc_bytes(quality: int, metadata: dict[str, Any]) -> bytes:
    """The fake's own .stgc writer (fake_stgc_cli.stgc_bytes)."""
    spec = importlib.util.spec_from_file_location("fake_stgc_cli", FAKE_CLI)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return bytes(module.stgc_bytes(quality, metadata))


def _calls(out: Path) -> list[str]:
    path = out / "invocations.txt"
    return path.read_text().splitlines() if path.exists() else []


def _rows(out: Path, plan: str = "mini") -> dict[str, dict[str, str]]:
    with open(out / f"results-{plan}.csv") as f:
        return {row["name"]: row for row in csv.DictReader(f)}


def _real_stgc(path: Path, quality: int, metadata: dict[str, Any]) -> None:
    """A .stgc as stgc's encoder writes it, of a small synthetic model."""
    arrays, _ = synthetic_model(20, "lite")
    path.write_bytes(encode(arrays, "lite", None, quality, metadata=metadata))


def _run_config(run: Path) -> dict[str, Any]:
    config = json.loads((run / "config.json").read_text())
    return {key: config[key] for key in ("data", "model")}


# Every kind of file with a current evaluation record of it (the case a record could hide), two without.
@pytest.mark.parametrize(("written", "evaluated"), [
    *[(kind, True) for kind in ("quality-5", "earlier-model", "ladder-allocation", "zstd-level", "no-run-config",
                                "another-run", "damaged")],
    ("earlier-model", False), ("another-run", False),
], ids=lambda value: ("record-current" if value else "record-stale") if isinstance(value, bool) else value)
def test_a_codec_point_s_file_is_compressed_again_unless_it_is_the_point_the_runner_writes(
        tmp_path: Path, written: str, evaluated: bool) -> None:
    """A RUN/model_q1.stgc of another quality, of an earlier iteration's model, written with other codec options, of
    another run's model (`stgc eval` records it `foreign`), or one stgc cannot read, is not the run's q1 point: the runner compresses it again instead of publishing it, whether
    or not an evaluation record of that very file is there."""
    plan, out = _plan(tmp_path), tmp_path / "exp"
    _run(plan, out, (1,))
    run, point = out / "stg", out / "stg" / "model_q1.stgc"
    made = {"source": "stg", "iteration": 10, "run_config": _run_config(run)}  # as compress of the run records
    if written == "quality-5":
        _real_stgc(point, 5, made)
    elif written == "earlier-model":
        _real_stgc(point, 1, made | {"iteration": 5})
    elif written == "ladder-allocation":
        _real_stgc(point, 1, made | {"allocation_option": "ladder"})
    elif written == "zstd-level":
        _real_stgc(point, 1, made | {"codec_options": {"zstd_level": 3}})
    elif written == "no-run-config":
        _real_stgc(point, 1, {k: v for k, v in made.items() if k != "run_config"})
    elif written == "another-run":
        other = _run_config(run)
        other["data"] = {**other["data"], "duration": 7}
        _real_stgc(point, 1, made | {"run_config": other})
    else:
        point.write_bytes(b"\0" * 5000)
    if evaluated:  # `stgc eval` of that file: its record is current
        assert fake_runner([sys.executable, "-m", "stgc.cli", "eval", str(point), "--json"], tmp_path / "log") == 0
    before = len(_calls(out))

    result = _run(plan, out, (1,))
    again = _calls(out)[before:]
    assert [call.split()[0] for call in again] == ["compress", "eval"], again
    assert read_stgc_header(point).quality == 1  # what the fake writes: stgc reads it
    outcome = {o.name: o for o in result.outcomes}["stg-q1"]
    assert outcome.status == "finished"
    assert float(_rows(out)["stg-q1"]["mbps"]) == pytest.approx(point.stat().st_size * 8 / 1e6)

    before = len(_calls(out))
    _run(plan, out, (1,))
    assert _calls(out)[before:] == []  # the point it wrote is taken as it is


def test_a_compress_that_cannot_write_the_run_s_final_model_fails_the_point(tmp_path: Path) -> None:
    """A run whose final model is gone compresses its latest, an earlier one: that file is not the run's point (and
    compressing it on every start of the plan would not mend it)."""
    def earlier_model(cmd: list[str], log_path: Path) -> int:
        code = fake_runner(cmd, log_path)
        if "compress" in cmd:  # what `stgc compress RUN` writes when RUN's latest model is iteration 5's
            out = Path(cmd[cmd.index("--out") + 1])
            out.write_bytes(_fake_stgc_bytes(1, {"iteration": 5, "run_config": _run_config(out.parent)}))
        return code

    plan, out = _plan(tmp_path), tmp_path / "exp"
    result = _run(plan, out, (1,), runner=earlier_model)
    outcome = {o.name: o for o in result.outcomes}["stg-q1"]
    assert outcome.status == "failed" and "iteration 5" in outcome.message and "model_q1.stgc" in outcome.message
    assert not any(call.startswith("eval") and "model_q1" in call for call in _calls(out))
    assert _rows(out)["stg-q1"]["mbps"] == "" and _rows(out)["stg"]["status"] == "finished"


def test_a_point_whose_evaluation_scored_an_earlier_model_fails(tmp_path: Path) -> None:
    """An evaluation record of the point's file naming another model than the run's final one (as `stgc eval`
    records a file of an earlier iteration) fails the point, with the reason, rather than leaving an empty row."""
    def scored_earlier(cmd: list[str], log_path: Path) -> int:
        code = fake_runner(cmd, log_path)
        if "eval" in cmd and cmd[cmd.index("eval") + 1].endswith(".stgc"):
            record = Path(cmd[cmd.index("eval") + 1]).with_name("eval_model_q1.json")
            record.write_text(json.dumps(json.loads(record.read_text()) | {"iterations": 5,
                                                                             "training_finished": False}))
        return code

    result = _run(_plan(tmp_path), tmp_path / "exp", (1,), runner=scored_earlier)
    outcome = {o.name: o for o in result.outcomes}["stg-q1"]
    assert outcome.status == "failed" and "eval_model_q1.json" in outcome.message and "iteration 5" in outcome.message
    assert _rows(tmp_path / "exp")["stg-q1"]["psnr"] == ""


def test_a_record_of_a_model_the_run_did_not_end_with_is_not_a_result(tmp_path: Path) -> None:
    """The runner's rows leave out what `stgc report` leaves out of the same run (scored_earlier_model): a record of
    an earlier iteration's model, or one made while the run trained."""
    from stgc.experiment.plans import load_plan_toml
    from stgc.experiment.runner import RunOutcome, _reported, write_results

    run = tmp_path / "stg"
    run.mkdir()
    (run / "train_summary.json").write_text(json.dumps({"finished": True, "iterations": 10}))
    numbers = {"psnr": 25.0, "mbps": 1.0, "size_mb": 0.1, "num_gaussians": 100}
    outcomes = [RunOutcome("stg", "STG", "trained", "skipped", run, {}, record=numbers | {"iterations": 10}),
                RunOutcome("stg-q1", "STG + codec", "trained q1", "skipped", run, {}, bitstream="model_q1.stgc",
                           record=numbers | {"iterations": 5, "mbps": 0.5}),
                RunOutcome("stg-q2", "STG + codec", "trained q2", "skipped", run, {}, bitstream="model_q2.stgc",
                           record=numbers | {"training_finished": False, "mbps": 0.7})]
    write_results(tmp_path / "results.csv", load_plan_toml(_plan(tmp_path)), outcomes, tmp_path)
    with open(tmp_path / "results.csv") as f:
        rows = {row["name"]: row for row in csv.DictReader(f)}
    assert rows["stg"]["psnr"] == "25.0"
    assert rows["stg-q1"]["psnr"] == rows["stg-q1"]["mbps"] == rows["stg-q1"]["rate_point"] == ""
    assert rows["stg-q2"]["psnr"] == ""
    assert [row.name for row in _reported(outcomes).values()] == ["trained"]


def test_a_failed_run_s_row_holds_no_numbers_of_an_earlier_evaluation(tmp_path: Path) -> None:
    """An eval.json made while the run trained (no, or other, iterations) stays beside a run whose evaluation then
    fails: the failed row must not carry its numbers."""
    plan, out = _plan(tmp_path), tmp_path / "exp"
    _run(plan, out)
    record = json.loads((out / "stg" / "eval.json").read_text())
    (out / "stg" / "eval.json").write_text(json.dumps(record | {"iterations": 6, "training_finished": False,
                                                                "psnr": 99.0}))

    def evaluation_killed(cmd: list[str], log_path: Path) -> int:
        return 137 if "eval" in cmd else fake_runner(cmd, log_path)

    result = _run(plan, out, runner=evaluation_killed)
    (outcome,) = result.outcomes
    assert outcome.status == "failed" and outcome.record is None
    row = _rows(out)["stg"]
    assert row["status"] == "failed" and row["psnr"] == "" and row["mbps"] == ""
    assert "99.00 dB" not in str(result)


def _entry(out: Path) -> dict[str, Any]:
    return json.loads((out / "stg" / "experiment.json").read_text())


def test_a_run_shared_by_two_plans_keeps_each_plan_s_family_and_label(tmp_path: Path) -> None:
    """table2 and table3 share runs under other family names: experiment.json keeps each plan's entry (by plan
    name), also when the second plan reuses the finished run; its top-level family and label stay the first
    plan's, as readers of the single-entry file take them."""
    out = tmp_path / "exp"
    first, second = _plan(tmp_path, "p1", "STG", "A"), _plan(tmp_path, "p2", "Other", "Z")
    _run(first, out)
    trained = len(_calls(out))
    result = _run(second, out)
    assert result.outcomes[0].status == "skipped" and len(_calls(out)) == trained
    entry = _entry(out)
    assert entry["plans"] == {"p1": {"name": "stg", "family": "STG", "label": "A"},
                              "p2": {"name": "stg", "family": "Other", "label": "Z"}}
    assert (entry["family"], entry["label"], entry["name"]) == ("STG", "A", "stg")
    assert entry["overrides"] == {"compaction.method": "none"} and entry["preset"] == "cpu"
    assert _rows(out, "p2")["stg"]["family"] == "Other"
    _run(first, out)  # each plan run again changes nothing
    _run(second, out)
    assert _entry(out) == entry
    # `stgc report --plan` names the run as that plan did; without it, or for a plan that did not list it, the first.
    from stgc.eval.report import rows_from_run

    named = {plan: [(row.family, row.name) for row in rows_from_run(out / "stg", plan=plan)]
             for plan in ("p1", "p2", "p3", None)}
    assert named["p2"][0] == ("Other", "Z") and named["p1"][0] == named["p3"][0] == named[None][0] == ("STG", "A")
    from stgc.errors import DataError
    from stgc.eval.report import report_from_runs

    with pytest.raises(DataError, match="--plan 'P2': no run's experiment.json lists that plan .they list: p1, p2."):
        report_from_runs([out / "stg"], tmp_path / "report", plan="P2")
    assert report_from_runs([out / "stg"], tmp_path / "report", plan="p2").rows[0].family == "Other"


def test_an_older_single_entry_experiment_json_is_read_as_the_first_plan_s(tmp_path: Path) -> None:
    out = tmp_path / "exp"
    first, second = _plan(tmp_path, "p1", "STG", "A"), _plan(tmp_path, "p2", "Other", "Z")
    _run(first, out)
    old = {k: v for k, v in _entry(out).items() if k != "plans"}  # as runners before per-plan entries wrote it
    (out / "stg" / "experiment.json").write_text(json.dumps(old))
    _run(second, out)
    assert _entry(out) == old | {"plans": {"p2": {"name": "stg", "family": "Other", "label": "Z"}}}


def test_a_run_trained_again_by_another_plan_keeps_the_first_plan_s_entry(tmp_path: Path) -> None:
    """A false start (no checkpoint) is trained again with --overwrite, which removes experiment.json with the rest
    of what was there: the entries of the plans that share the run are written back."""
    out = tmp_path / "exp"
    first, second = _plan(tmp_path, "p1", "STG", "A"), _plan(tmp_path, "p2", "Other", "Z")

    def killed(cmd: list[str], log_path: Path) -> int:
        return 137 if "train" in cmd else fake_runner(cmd, log_path)

    assert _run(first, out, runner=killed).outcomes[0].status == "failed"

    def overwriting(cmd: list[str], log_path: Path) -> int:
        if "--overwrite" in cmd:  # as `stgc train --overwrite` clears the folder's derived files
            (Path(cmd[cmd.index("--out") + 1]) / "experiment.json").unlink(missing_ok=True)
        return fake_runner(cmd, log_path)

    assert _run(second, out, runner=overwriting).outcomes[0].status == "finished"
    entry = _entry(out)
    assert set(entry["plans"]) == {"p1", "p2"} and (entry["family"], entry["label"]) == ("STG", "A")
