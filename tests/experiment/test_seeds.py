"""A plan over several seeds: each run once per seed, the report's means, spread and paired changes."""

from __future__ import annotations

import csv
import json
import statistics
import sys
from pathlib import Path

import pytest
from test_runner import _invocations, _results, fake_runner

from stgc.config import ConfigError
from stgc.errors import FormatError
from stgc.experiment import load_plan, load_plan_toml, run_plan
from stgc.experiment.plans import with_seeds

SEEDED_TOML = """
name = "mini"
baseline = "STG"
{seeds}
[[runs]]
name = "stg"
family = "STG"
overrides = {{ "compaction.method" = "none" }}
[[runs]]
name = "c1"
family = "ST-KNN"
label = "Case 1"
overrides = {{ "compaction.method" = "st-knn", "compaction.case" = 1 }}
[[runs]]
name = "c3"
family = "ST-KNN"
label = "Case 3"
overrides = {{ "compaction.method" = "st-knn", "compaction.case" = 3 }}
"""


def _plan(tmp_path: Path, seeds: str = "", extra: str = "") -> Path:
    path = tmp_path / "PLAN.toml"
    path.write_text(SEEDED_TOML.format(seeds=seeds) + extra)
    return path


def test_seeds_train_each_run_once_per_seed_and_pair_fine_tunings_and_references_by_seed(tmp_path: Path) -> None:
    extra = """
[[runs]]
name = "ft"
from = "c1"
iterations = 5
overrides = { "train.quantization_aware.iterations" = 5 }
[[runs]]
name = "ref"
overrides = { "compaction.method" = "reference" }
[[runs]]
name = "budget"
loss_reference = "ref"
overrides = { "compaction.method" = "st-knn", "compaction.loss_signal" = "probe" }
"""
    plan = load_plan_toml(_plan(tmp_path, "seeds = [0, 2]", extra))
    assert plan.seeds == (0, 2)
    assert [r.name for r in plan.runs] == ["stg", "stg-seed2", "c1", "c1-seed2", "c3", "c3-seed2", "ft", "ft-seed2",
                                           "ref", "ref-seed2", "budget", "budget-seed2"]
    by_name = {r.name: r for r in plan.runs}
    assert by_name["c1-seed2"].overrides == {"compaction.method": "st-knn", "compaction.case": "1", "train.seed": "2"}
    assert by_name["stg"].overrides["train.seed"] == "0" and by_name["stg"].entry_name == "stg"
    assert (by_name["ft-seed2"].source, by_name["budget-seed2"].reference) == ("c1-seed2", "ref-seed2")
    assert (by_name["ft"].source, by_name["budget"].reference) == ("c1", "ref")
    assert by_name["c3-seed2"].seed == 2 and by_name["c3-seed2"].entry_name == "c3"
    # The built-in tables take seeds from the command line; the same seeds again change nothing.
    table2 = load_plan("table2", seeds=[0, 1])
    assert len(table2.runs) == 12 and table2.runs[1].name == "stg-seed1"
    assert with_seeds(table2, [0, 1]) == table2


@pytest.mark.parametrize(("seeds", "extra", "problem"), [
    ("seeds = []", "", "non-empty list"),
    ("seeds = [1, 1]", "", "distinct integers"),
    ("seeds = [-1]", "", "distinct integers"),
    ("seeds = ['a']", "", "distinct integers"),
    ("seeds = 3", "", "non-empty list"),
    ("seeds = [0, 1]", '[[runs]]\nname = "s"\noverrides = { "train.seed" = 4 }\n', "sets train.seed"),
    ("seeds = [0, 1]", '[[runs]]\nname = "c1-seed1"\n', "would name two runs"),
])
def test_bad_seeds_are_refused_naming_the_plan(tmp_path: Path, seeds: str, extra: str, problem: str) -> None:
    with pytest.raises(FormatError, match=problem) as error:
        load_plan_toml(_plan(tmp_path, seeds, extra))
    assert "PLAN.toml" in str(error.value)


def test_seeds_given_twice_must_agree(tmp_path: Path) -> None:
    path = _plan(tmp_path, "seeds = [0, 1]")
    assert load_plan(path, seeds=[0, 1]).seeds == (0, 1)
    with pytest.raises(ConfigError, match="give them in one place"):
        load_plan(path, seeds=[0, 2])


def test_a_plan_over_seeds_reports_each_run_s_mean_spread_and_change_against_the_baseline_seed_by_seed(
        tmp_path: Path) -> None:
    out = tmp_path / "exp"
    quiet = {"runner": fake_runner, "python": sys.executable, "log": lambda m: None, "preset": "cpu"}
    # A plan trained once (seed 0) earlier: its runs are the seed-0 runs of the same plan over seeds.
    run_plan("DATA", _plan(tmp_path), out, **quiet)
    trained = len(_invocations(out))
    result = run_plan("DATA", _plan(tmp_path), out, codec_qualities=[4], seeds=[0, 1, 2], **quiet)
    assert not result.failed
    new_trainings = [c for c in _invocations(out)[trained:] if c.startswith("train")]
    assert len(new_trainings) == 6 and all("train.seed=0" not in c for c in new_trainings)
    assert {o.name: o.status for o in result.outcomes}["c1"] == "skipped"
    rows = _results(out)
    assert {(r["name"], r["seed"]) for r in rows if r["name"].startswith("c1")} == {
        ("c1", "0"), ("c1-q4", "0"), ("c1-seed1", "1"), ("c1-seed1-q4", "1"), ("c1-seed2", "2"),
        ("c1-seed2-q4", "2")}
    # Each seed's runs are curves of their own: every seed's unpruned run is its STG curve's one point.
    assert {r["name"]: r["rate_point"] for r in rows if r["name"].startswith("stg") and "-q" not in r["name"]} == {
        "stg": "rp01", "stg-seed1": "rp01", "stg-seed2": "rp01"}

    # The stand-in trainer's scores (fake_stgc_cli._eval_record): PSNR 30 - 0.3 case - 0.1 seed (1 + case), Gaussians
    # 100,000 / (1 + case) - 100 seed case; the baseline is STG's run, stg, of the same seed.
    def psnr(case: int, seed: int) -> float:
        return 30.0 - 0.3 * case - 0.1 * seed * (1 + case)

    def gaussians(case: int, seed: int) -> int:
        return int(100_000 / (1 + case)) - 100 * seed * case

    with open(out / "report-mini" / "seeds.csv") as f:
        spread = {row["entry"]: row for row in csv.DictReader(f)}
    assert list(spread) == ["stg", "stg-q4", "c1", "c1-q4", "c3", "c3-q4"]
    for case, entry in ((0, "stg"), (1, "c1"), (3, "c3")):
        row = spread[entry]
        assert row["seeds"] == "0 1 2" and row["paired_seeds"] == "0 1 2"
        assert float(row["psnr_mean"]) == pytest.approx(statistics.fmean(psnr(case, s) for s in range(3)))
        assert float(row["psnr_sd"]) == pytest.approx(statistics.stdev(psnr(case, s) for s in range(3)))
        deltas = [psnr(case, s) - psnr(0, s) for s in range(3)]
        assert float(row["delta_psnr_mean"]) == pytest.approx(statistics.fmean(deltas), abs=1e-12)
        assert float(row["delta_psnr_min"]) == pytest.approx(min(deltas), abs=1e-12)
        removed = [1 - gaussians(case, s) / gaussians(0, s) for s in range(3)]
        assert float(row["removed_mean"]) == pytest.approx(statistics.fmean(removed), abs=1e-12)
        assert float(row["num_gaussians_mean"]) == pytest.approx(statistics.fmean(gaussians(case, s)
                                                                                  for s in range(3)))
    assert float(spread["c1"]["delta_psnr_sd"]) == pytest.approx(0.1)  # -0.3, -0.4, -0.5 dB
    # A codec point is held against the baseline's trained model of the same seed (what "q2 vs float32" means).
    assert float(spread["c1-q4"]["delta_psnr_mean"]) == pytest.approx(-0.4 - 0.05)

    # The report's points are the means; its table says the spread and the paired change.
    report = json.loads((out / "report-mini" / "report.json").read_text())
    case1 = next(r for r in report["rows"] if r["extra"].get("run") == "c1")
    assert case1["psnr"] == pytest.approx(29.5) and case1["extra"]["seeds"] == [0, 1, 2]
    assert case1["extra"]["fps"] == pytest.approx(5.0)  # the record's other numbers are averaged too
    assert len(report["rows"]) == 6
    md = (out / "report-mini" / "report.md").read_text()
    assert "## Over the seeds" in md and "| Case 1 (c1) | 0 1 2 |" in md and "-0.40 ± 0.10 [-0.50, -0.30]" in md

    # Without seeds again, the report is the plain one and the seeds table goes with the seeds.
    run_plan("DATA", _plan(tmp_path), out, **quiet)
    assert not (out / "report-mini" / "seeds.csv").exists()
    assert "Over the seeds" not in (out / "report-mini" / "report.md").read_text()


def test_the_cli_passes_its_seeds_to_the_plan(monkeypatch: pytest.MonkeyPatch) -> None:
    import stgc.cli

    calls = []
    monkeypatch.setattr(stgc.cli, "run_plan", lambda *a, **k: calls.append(k) or type(
        "R", (), {"failed": [], "__str__": lambda self: "ok"})())
    assert stgc.cli.main(["experiment", "DATA", "--plan", "table2", "--out", "OUT", "--seeds", "0", "3", "--no-ray"]) == 0
    assert calls[0]["seeds"] == [0, 3]



def test_a_seed_missing_from_a_run_is_said_and_a_seed_option_for_every_run_is_refused(tmp_path: Path) -> None:
    out = tmp_path / "exp"
    quiet = {"runner": fake_runner, "python": sys.executable, "log": lambda m: None, "preset": "cpu"}
    path = _plan(tmp_path, "seeds = [1, 2]")
    with pytest.raises(ConfigError, match="--set train.seed"):
        run_plan("DATA", path, out, extra_overrides=["train.seed=5"], **quiet)
    assert not run_plan("DATA", path, out, **quiet).failed
    # The baseline "STG" is a family; the plan's runs are "-seed<s>" folders, the report's points the entries'.
    md = (out / "report-mini" / "report.md").read_text()
    assert "| Case 1 (c1) | 1 2 |" in md and "fewer seeds" not in md
    # One seed of one run is not this plan's any more (made with other options): its row fails, the others stand,
    # and the report says which means are over fewer seeds.
    config = json.loads((out / "c3-seed2" / "config.json").read_text())
    config["compaction"]["case"] = 4
    (out / "c3-seed2" / "config.json").write_text(json.dumps(config))
    result = run_plan("DATA", path, out, **quiet)
    assert [o.name for o in result.failed] == ["c3-seed2"]
    md = (out / "report-mini" / "report.md").read_text()
    assert "Averaged over fewer seeds than the plan's [1, 2]** (a run failed): c3;" in md
    with open(out / "report-mini" / "seeds.csv") as f:
        by_entry = {row["entry"]: row for row in csv.DictReader(f)}
    assert by_entry["c3"]["seeds"] == "1" and by_entry["c3"]["paired_seeds"] == "1"
    assert by_entry["c1"]["seeds"] == "1 2"


def test_a_seed_scored_on_other_views_is_not_paired_with_the_baseline(tmp_path: Path) -> None:
    from stgc.eval.report import ReportRow
    from stgc.experiment.spread import seed_spread

    plan = load_plan_toml(_plan(tmp_path, "seeds = [1, 2]"))

    def row(psnr: float, gaussians: int, cameras: list[str], data: str = "DATA") -> ReportRow:
        return ReportRow("x", "f", 1.0, psnr, gaussians, extra={"data": data, "cameras": cameras})

    data = str(tmp_path / "DATA")  # the same folder however written
    rows = {("stg-seed1", None): row(30.0, 1000, ["0"], data), ("stg-seed2", None): row(29.0, 1000, ["0"]),
            ("c1-seed1", None): row(29.5, 500, ["0"], str(tmp_path / "." / "DATA")),
            ("c1-seed2", None): row(29.0, 400, ["1"])}  # another test camera
    (tmp_path / "DATA").mkdir()
    c1 = next(s for s in seed_spread(plan, rows) if s.entry == "c1")
    assert c1.delta_psnr == pytest.approx({1: -0.5}) and c1.removed == pytest.approx({1: 0.5})
    assert "cameras" not in c1.mean_row().extra  # its seeds were scored on different views


def test_a_report_that_fails_leaves_no_seeds_table_behind(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """seeds.csv goes beside a report that was written: one whose report failed leaves neither (an earlier seeds
    table, of other runs, would be read as this report's)."""
    import stgc.experiment.runner as runner

    out = tmp_path / "exp"
    quiet = {"runner": fake_runner, "python": sys.executable, "log": lambda m: None, "preset": "cpu"}
    run_plan("DATA", _plan(tmp_path), out, seeds=[0, 1], **quiet)
    assert (out / "report-mini" / "seeds.csv").exists()

    def failing(*args: object, **kwargs: object) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(runner, "make_report", failing)
    with pytest.raises(OSError, match="disk full"):
        run_plan("DATA", _plan(tmp_path), out, seeds=[0, 1], **quiet)
    assert not (out / "report-mini" / "seeds.csv").exists()
