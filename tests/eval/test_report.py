"""Reports: the paper's Table 2/3 numbers through make_report, plot files, BD deltas, runs on disk."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from PIL import Image

from stgc.eval.bjontegaard import bd_psnr, bd_rate
from stgc.eval.report import ReportRow, make_report, rate_points, report_from_runs, rows_from_run

TABLE2 = [
    ("Trained model", "STG", 433_936, 62.9, 527.68, 35.58),
    ("with preprocessing", "STG", 204_371, 29.62, 248.53, 35.32),
    ("Case 1", "ST-KNN (proposed)", 199_736, 28.95, 242.89, 35.39),
    ("Case 2", "ST-KNN (proposed)", 164_985, 23.91, 200.64, 35.01),
    ("Case 3", "ST-KNN (proposed)", 141_714, 20.54, 172.34, 34.8),
    ("Case 4", "ST-KNN (proposed)", 124_224, 18.01, 151.07, 34.26),
]
TABLE3_SCALE = [(132.41, 34.54), (91.52, 33.78), (70.67, 32.18), (55.78, 31.13)]
TABLE3_TIMESTAMP = [(133.37, 34.62), (91.42, 33.68), (68.72, 32.36), (56.55, 31.08)]


def _table2_rows() -> list[ReportRow]:
    return [ReportRow(name=n, family=f, num_gaussians=g, size_mb=s, mbps=m, psnr=p) for n, f, g, s, m, p in TABLE2]


def test_table2_report_files(tmp_path: Path) -> None:
    report = make_report(_table2_rows(), tmp_path, baseline="STG", title="Table 2 (paper numbers)")
    md = report.markdown.read_text()
    assert "| STG | Trained model | rp02 | 433,936 | 62.90 | 527.68 | 35.58 |" in md
    assert "|  | Case 4 | rp01 | 124,224 | 18.01 | 151.07 | 34.26 |" in md
    assert "YUV-PSNR" not in md  # none of the rows has it
    # Change vs the baseline's highest-rate point: Case 4 is -71.4 % rate at -1.32 dB (the paper's 3.5x).
    assert "-71.4 %" in md and "-1.32" in md
    with Image.open(report.plot_png) as im:
        assert im.size[0] > 800 and im.size[1] > 600
    assert "<svg" in report.plot_svg.read_text()
    (bd,) = report.bd
    assert bd.family == "ST-KNN (proposed)" and bd.baseline == "STG"
    expected = bd_rate([248.53, 527.68], [35.32, 35.58], [151.07, 172.34, 200.64, 242.89],
                       [34.26, 34.8, 35.01, 35.39])
    assert bd.bd_rate == pytest.approx(expected)
    saved = json.loads(report.json_path.read_text())
    assert saved["baseline"] == "STG" and len(saved["rows"]) == 6


def test_table3_bd_between_criteria(tmp_path: Path) -> None:
    rows = [ReportRow(f"Case {i + 1}", "scale", m, p) for i, (m, p) in enumerate(TABLE3_SCALE)]
    rows += [ReportRow(f"Case {i + 1}", "timestamp", m, p) for i, (m, p) in enumerate(TABLE3_TIMESTAMP)]
    report = make_report(rows, tmp_path, baseline="scale", bd_method="cubic")
    (bd,) = report.bd
    args = ([m for m, _ in TABLE3_SCALE], [p for _, p in TABLE3_SCALE],
            [m for m, _ in TABLE3_TIMESTAMP], [p for _, p in TABLE3_TIMESTAMP])
    assert bd.bd_rate == pytest.approx(bd_rate(*args, method="cubic"))
    assert bd.bd_psnr == pytest.approx(bd_psnr(*args, method="cubic"))
    # The paper's conclusion: no significant difference between the two criteria.
    assert abs(bd.bd_psnr) < 0.15


def test_rate_scaled_family_reports_its_factor(tmp_path: Path) -> None:
    base = [ReportRow(f"p{i}", "A", m, p) for i, (m, p) in enumerate(TABLE3_SCALE)]
    half = [ReportRow(f"p{i}", "B", m * 0.5, p) for i, (m, p) in enumerate(TABLE3_SCALE)]
    single = [ReportRow("only", "C", 100.0, 33.0)]
    report = make_report(base + half + single, tmp_path)
    by_family = {b.family: b for b in report.bd}
    assert report.baseline == "A"
    assert by_family["B"].bd_rate == pytest.approx(-50.0, abs=1e-9)
    assert by_family["C"].bd_rate is None and "n/a" in by_family["C"].note
    assert "n/a" in report.markdown.read_text()
    with pytest.raises(ValueError, match="baseline"):
        make_report(base, tmp_path, baseline="nope")


def _fake_run(root: Path, name: str, config: dict, record: dict, meta: dict | None = None) -> Path:
    d = root / name
    d.mkdir()
    (d / "config.json").write_text(json.dumps(config))
    (d / "eval.json").write_text(json.dumps(record))
    if meta:
        (d / "experiment.json").write_text(json.dumps(meta))
    return d


def test_report_from_runs(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    runs.mkdir()
    a = _fake_run(runs, "stg", {"data": {"preprocess": "none"}, "compaction": {"method": "none"}},
                  {"psnr": 30.0, "ssim": 0.9, "mbps": 10.0, "size_mb": 1.19, "num_gaussians": 8000})
    b = _fake_run(runs, "pre", {"data": {"preprocess": "stg-isolated"}, "compaction": {"method": "none"}},
                  {"psnr": 29.5, "mbps": 6.0, "num_gaussians": 5000})
    c = _fake_run(runs, "c1", {"data": {}, "compaction": {"method": "st-knn", "case": 1, "criterion": "scale"}},
                  {"psnr": 29.4, "mbps": 4.0})
    (c / "model_q5.stgc").write_bytes(b"0123456789")
    (c / "eval_model_q5.json").write_text(json.dumps({"psnr": 29.0, "mbps": 0.5, "size_bytes": 10}))
    d = _fake_run(runs, "named", {}, {"psnr": 29.0, "mbps": 3.0}, {"family": "Custom", "label": "mine"})
    empty = runs / "unfinished"
    empty.mkdir()
    report = report_from_runs([a, b, c, d, empty], tmp_path / "out", baseline="stg")
    fams = {r.family for r in report.rows}
    assert fams == {"STG", "ST-KNN (scale)", "ST-KNN (scale) + codec", "Custom"}
    names = {r.name for r in report.rows}
    assert {"no preprocessing", "preprocessing stg-isolated", "Case 1", "Case 1 q5", "mine"} <= names
    md = report.markdown.read_text()
    assert "unfinished" in md and report.baseline == "STG"
    assert report.plot_png.is_file() and str(report).startswith("report written")


def test_a_record_made_before_the_run_finished_is_not_its_result(tmp_path: Path, caplog) -> None:
    """`stgc eval` of a run still training scores its latest saved model. While the run trains, the report names
    the row half-trained; once the run has finished, that record is not the run's result and is left out (the
    experiment runner scores such a run again)."""
    config = {"data": {}, "compaction": {"method": "none"}}
    run = _fake_run(tmp_path, "r", config, {"psnr": 20.0, "mbps": 3.0, "training_finished": False})
    (row,) = rows_from_run(run)
    assert row.name.endswith("(half-trained)")
    (run / "train_summary.json").write_text(json.dumps({"finished": True, "iterations": 9000}))
    with caplog.at_level("WARNING"):
        assert rows_from_run(run) == []
    assert "before the training finished" in caplog.text
    (run / "eval.json").write_text(json.dumps({"psnr": 25.0, "mbps": 3.0, "iterations": 6000}))  # an earlier end
    assert rows_from_run(run) == []
    (run / "eval.json").write_text(json.dumps({"psnr": 27.0, "mbps": 3.0, "iterations": 9000,
                                               "training_finished": True}))
    (row,) = rows_from_run(run)
    assert row.psnr == 27.0 and "half-trained" not in row.name
    # The same for a bitstream's record: one of an earlier iteration's model is not the run's codec point.
    (run / "model_q2.stgc").write_bytes(b"0123456789")
    earlier = {"psnr": 25.0, "mbps": 0.5, "size_bytes": 10, "iterations": 3000}  # by its iterations alone
    (run / "eval_model_q2.json").write_text(json.dumps(earlier))
    with caplog.at_level("WARNING"):
        assert [r.name for r in rows_from_run(run)] == [row.name]
    assert "holds the model of iteration 3000" in caplog.text
    (run / "eval_model_q2.json").write_text(json.dumps({**earlier, "iterations": 9000, "training_finished": True}))
    assert [r.name for r in rows_from_run(run)] == [row.name, f"{row.name} q2"]


def test_rate_axis_turns_logarithmic_when_the_rates_span_more_than_ten_times(tmp_path):
    from stgc.eval.report import rate_axis_is_log

    close = [ReportRow(name="a", family="f", mbps=10.0, psnr=30.0), ReportRow(name="b", family="f", mbps=60.0, psnr=31.0)]
    wide = close + [ReportRow(name="c", family="codec", mbps=0.9, psnr=29.5)]
    assert not rate_axis_is_log(close) and rate_axis_is_log(wide)
    # Rows without a PSNR are not plotted, so they do not widen the axis.
    assert not rate_axis_is_log(close + [ReportRow(name="d", family="codec", mbps=0.5, psnr=None)])
    report = make_report(wide, tmp_path / "r")
    assert report.plot_png is not None and report.plot_png.stat().st_size > 0
    # Written again with nothing to plot: no plot of the earlier rows stands beside the new table.
    again = make_report([ReportRow(name="d", family="codec", mbps=0.5, psnr=None)], tmp_path / "r")
    assert again.plot_png is None and sorted(p.name for p in (tmp_path / "r").iterdir()) == ["report.json",
                                                                                           "report.md"]


def test_rate_points_name_four_points_per_curve_spread_over_log_rate(tmp_path):
    """MPEG's rp01..rp04, rp01 the lowest rate: a curve of four or fewer points names them all in rate order; a
    longer one its lowest, its highest and the points nearest 1/3 and 2/3 of the way in log rate."""
    rates = [0.1, 0.12, 0.2, 0.45, 0.5, 1.0, 2.2, 10.0]  # log10: -1 ... 1; thirds at 10^(-1/3) and 10^(1/3)
    curve = [ReportRow(f"lambda {k}", "rate-aware", m, 30 + k) for k, m in enumerate(rates)]
    short = [ReportRow(f"q{k}", "codec", m, 27 + m) for k, m in enumerate([3.0, 1.0, 2.0])]
    names = rate_points(curve + short)
    assert {r.mbps: names[id(r)] for r in curve if id(r) in names} == {0.1: "rp01", 0.45: "rp02", 2.2: "rp03",
                                                                        10.0: "rp04"}
    assert [names[id(r)] for r in short] == ["rp03", "rp01", "rp02"]
    # A cloud (two runs at three codec qualities): the rate points name its Pareto front, the curve the BD deltas
    # and the plot use; a point another beats (a higher rate for a lower PSNR) names none.
    cloud = [ReportRow(n, "cloud", m, p) for n, m, p in
             [("a q1", 1.0, 30.0), ("b q2", 2.0, 29.5), ("a q3", 3.0, 32.0), ("b q3", 3.5, 31.5)]]
    names = rate_points(cloud)
    assert {r.name: names.get(id(r)) for r in cloud} == {"a q1": "rp01", "b q2": None, "a q3": "rp02", "b q3": None}
    rows = [ReportRow("a", "A", 1.0, 30.0, extra={"psnr_yuv": 33.25}), ReportRow("b", "A", 2.0, 31.0)]
    md = make_report(rows, tmp_path, baseline="A").markdown.read_text()
    assert "| A | a | rp01 | – | – | 1.00 | 30.00 | 33.25 |" in md and "|  | b | rp02 | – | – | 2.00 | 31.00 | – |" in md


def test_rd_plot_labels_points_and_keeps_the_legend_off_the_curves_only_while_they_fit(tmp_path):
    """A few curves: every point labelled, the legend inside the axes. Many: no point labels (they would overlap;
    the table names them) and the legend beside the axes, not over the curves."""
    import matplotlib.pyplot as plt

    from stgc.eval.report import LABELLED_POINTS_MAX, LEGEND_INSIDE_MAX, rd_figure

    def rows(families: int, points: int) -> list[ReportRow]:
        return [ReportRow(name=f"f{f} p{p}", family=f"family {f}", mbps=1.0 + p + 0.1 * f, psnr=30.0 + p - 0.2 * f)
                for f in range(families) for p in range(points)]

    def legend_is_beside_axes(fig) -> bool:
        fig.canvas.draw()
        ax = fig.axes[0]
        return bool(ax.get_legend().get_window_extent().x0 >= ax.get_window_extent().x1)

    few = rows(2, 3)
    fig = rd_figure(few, "few", baseline="family 0")
    assert sorted(t.get_text() for t in fig.axes[0].texts) == sorted(r.name for r in few)
    assert not legend_is_beside_axes(fig)
    plt.close(fig)

    many = rows(LEGEND_INSIDE_MAX + 2, 4)
    assert len(many) > LABELLED_POINTS_MAX
    fig = rd_figure(many, "many", baseline="family 0")
    assert len(fig.axes[0].texts) == 0
    assert legend_is_beside_axes(fig)
    assert len(fig.axes[0].get_legend().get_texts()) == LEGEND_INSIDE_MAX + 2
    plt.close(fig)
    # Fourteen curves (as the learned-mask plan draws): fourteen colours, none repeated.
    fig = rd_figure(rows(14, 2), "fourteen", baseline=None)
    assert len({line.get_color() for line in fig.axes[0].get_lines()}) == 14
    plt.close(fig)
    # The saved PNG holds the legend beside the axes too (bbox_inches="tight" widens it).
    report = make_report(many, tmp_path / "r")
    assert report.plot_png is not None
    with Image.open(report.plot_png) as png:
        assert png.width > 1.5 * png.height


def test_bd_deltas_use_each_familys_pareto_front(tmp_path):
    base = [(1.0, 30.0), (2.0, 32.0), (4.0, 34.0), (8.0, 36.0)]
    test = [(0.8, 30.0), (1.6, 32.0), (3.2, 34.0), (6.4, 36.0)]  # the same curve at 0.8x the rate: BD-rate -20 %
    # A cloud: a second run's codec points that other points beat (lower PSNR at a higher rate), one in each family.
    rows = [ReportRow(f"b{i}", "base", m, p) for i, (m, p) in enumerate(base + [(5.0, 33.0)])]
    rows += [ReportRow(f"t{i}", "test", m, p) for i, (m, p) in enumerate(test + [(4.0, 33.5)])]
    (bd,) = make_report(rows, tmp_path, baseline="base").bd
    assert bd.bd_rate == pytest.approx(-20.0, abs=1e-6)  # through every point it zigzags: about -15 %
    assert bd.points == 4
    assert "1 dominated point(s) of this curve left out" in bd.note
    assert "1 dominated point(s) of the baseline left out" in bd.note
    # The note names the ranges the deltas average over (a delta over a sliver of PSNR is noise).
    assert "BD-rate over 30.00-36.00 dB (6.00 dB shared)" in bd.note and "BD-PSNR over 1-6.4 Mbps" in bd.note
    # The reference of the table's last two columns is the baseline's best point, not a dominated one at a higher
    # rate.
    report = make_report(rows + [ReportRow("b9", "base", 9.0, 35.0)], tmp_path / "more", baseline="base")
    assert "Reference for the last two columns: base / b3." in report.markdown.read_text()


def test_an_exact_render_counts_at_the_psnr_ceiling_and_a_point_without_a_psnr_is_said_to_be_left_out(tmp_path):
    """An infinite PSNR (identical images) read as "no PSNR" dropped the curve's best point without a word; it
    counts at the ceiling the evaluation uses (100 dB), and a point left out for want of a PSNR is named."""
    base = [ReportRow(f"b{i}", "base", m, p) for i, (m, p) in enumerate([(10.0, 30.0), (20.0, 33.0)])]
    exact = ReportRow.from_mapping({"name": "t1", "family": "test", "mbps": 25.0, "psnr": "inf"})
    assert exact.psnr == 100.0
    rows = [*base, ReportRow("t0", "test", 12.0, 31.0), exact]
    (bd,) = make_report(rows, tmp_path / "a", baseline="base").bd
    assert bd.points == 2
    unscored = ReportRow.from_mapping({"name": "t1", "family": "test", "mbps": 25.0, "psnr": "nan"})
    (bd,) = make_report([*base, ReportRow("t0", "test", 12.0, 31.0), unscored], tmp_path / "b", baseline="base").bd
    assert bd.points == 1 and "1 point(s) of this curve without a rate and a finite PSNR left out" in bd.note


def test_a_rate_aware_run_without_experiment_json_is_not_reported_as_stg(tmp_path) -> None:
    from stgc.eval.report import describe_run

    plain = {"data": {"preprocess": "none"}, "compaction": {"method": "none"}}
    assert describe_run(tmp_path / "stg", plain) == ("STG", "no preprocessing")
    window = {"iterations": 500, "mask": True, "rate_weight": 3e-4}
    masked = {**plain, "train": {"quantization_aware": window}}
    assert describe_run(tmp_path / "mask-3e-4", masked) == ("learned mask", "mask-3e-4")
    rate_aware = {**plain, "train": {"quantization_aware": {**window, "mask": False}}}
    assert describe_run(tmp_path / "rate-1e-3", rate_aware) == ("rate-aware", "rate-1e-3")
    control = {**plain, "train": {"quantization_aware": {"iterations": 500, "simulate": False}}}
    assert describe_run(tmp_path / "control", control) == ("rate-aware control", "control")


def test_a_record_with_a_value_that_is_no_number_names_its_file_and_a_baseline_may_be_a_runs_path(tmp_path):
    from stgc.errors import FormatError

    config = {"data": {}, "compaction": {"method": "none"}}
    good = _fake_run(tmp_path, "good", config, {"psnr": 27.0, "mbps": 3.0})
    other = _fake_run(tmp_path, "other", {"data": {}, "compaction": {"method": "st-knn", "case": 2}},
                      {"psnr": 26.0, "mbps": 2.0})
    assert report_from_runs([good, other], tmp_path / "out", baseline=str(other)).baseline == "ST-KNN (timestamp)"
    bad = _fake_run(tmp_path, "bad", config, {"psnr": "abc", "mbps": 3.0})
    with pytest.raises(FormatError, match="not an evaluation record") as info:
        rows_from_run(bad)
    assert info.value.path == bad / "eval.json"
