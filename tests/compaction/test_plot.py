"""plot_compaction: a real PNG from a compaction log; bad logs are reported with the file and the problem."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from stgc.compaction import (
    STKNNCompactor,
    plot_compaction,
    read_compaction_log,
)
from stgc.compaction.plot import loss_label
from stgc.errors import DataError

from .compaction_helpers import make_model, paper_rule, random_params


def test_plot_from_a_run_directory(tmp_path):
    model = make_model(random_params(300, 7, motion_scale=0.02))
    compactor = STKNNCompactor(paper_rule(case=0, window_start=0.1, window_end=0.9, interval=5), 60)
    losses = np.random.default_rng(0).uniform(0.2, 0.3, 60)
    with open(tmp_path / "compaction.jsonl", "w") as f:
        for it in range(1, 61):
            event = compactor.step(it, 0.5, model, float(losses[it - 1]))
            if event:
                f.write(json.dumps(event) + "\n")
    assert len(read_compaction_log(tmp_path)) == 10
    out = plot_compaction(tmp_path, tmp_path / "plots" / "compaction.png")
    with Image.open(out) as img:
        assert img.format == "PNG" and img.width > 300 and img.height > 300
        pixels = np.asarray(img.convert("RGB"))
    assert pixels.std() > 10  # something was drawn
    assert [p.name for p in (tmp_path / "plots").iterdir()] == ["compaction.png"]  # no temporary left behind


def test_bad_logs_raise_data_error(tmp_path):
    with pytest.raises(DataError, match="no compaction log"):
        read_compaction_log(tmp_path)
    log = tmp_path / "compaction.jsonl"
    log.write_text("")
    with pytest.raises(DataError, match="no pruning steps"):
        read_compaction_log(log)
    log.write_text('{"iteration": 5, "ratio": 0.1}\n{"iteration": 6,\n')
    with pytest.raises(DataError, match="line 2 is not JSON"):
        plot_compaction(log, tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()
    # Records of the wrong types were drawn as if they were numbers (a PNG, exit 0).
    for bad, said in (('{"iteration": "x"}', "iteration 'x' is not a non-negative integer"),
                      ('{"iteration": 3, "ratio": "high"}', "ratio 'high' is not a number")):
        log.write_text('{"iteration": 1, "ratio": 0.1}\n' + bad + "\n")
        with pytest.raises(DataError, match=f"line 2: {said}"):
            plot_compaction(log, tmp_path / "x.png")
        assert not (tmp_path / "x.png").exists()


def test_a_last_line_cut_short_by_a_kill_is_skipped_but_a_bad_middle_line_is_not(tmp_path):
    log = tmp_path / "compaction.jsonl"
    log.write_text('{"iteration": 5, "ratio": 0.1}\n{"iteration": 6, "rat')
    assert [r["iteration"] for r in read_compaction_log(log)] == [5]
    log.write_text('{"iteration": 5, "ratio": 0.1}\n{"iteration": 6, "rat\n{"iteration": 7, "ratio": 0.1}\n')
    with pytest.raises(DataError, match="line 2 is not JSON"):
        read_compaction_log(log)


def test_the_loss_panel_names_the_signal_the_controller_compared():
    assert loss_label([{"iteration": 1, "loss_signal": "probe"}]).startswith("probe loss")
    assert loss_label([{"iteration": 1, "loss_signal": "training"}]) == "smoothed training loss"
    assert loss_label([{"iteration": 1}]) == "smoothed training loss"  # logs written before the probe signal existed
    mixed = loss_label([{"iteration": 1, "loss_signal": "training"}, {"iteration": 2, "loss_signal": "probe"}])
    assert "probe" in mixed and "training" in mixed


def test_a_run_with_a_loss_reference_gets_a_panel_of_its_loss_above_the_reference(tmp_path):
    base = {"ratio": 0.01, "loss_signal": "probe", "removed": 3, "gaussians_left": 100, "loss_budget": 0.035}
    records = [{**base, "iteration": it, "smoothed_loss": 0.02 * (1 + 0.01 * k), "reference_loss": 0.02}
               for k, it in enumerate(range(10, 110, 10))]
    log = tmp_path / "compaction.jsonl"
    log.write_text("".join(json.dumps(r) + "\n" for r in records))
    with Image.open(plot_compaction(log, tmp_path / "with.png")) as img:
        referenced = img.height
    for r in records:
        del r["reference_loss"]
    log.write_text("".join(json.dumps(r) + "\n" for r in records))
    with Image.open(plot_compaction(log, tmp_path / "without.png")) as img:
        plain = img.height
    assert referenced == pytest.approx(plain * 4 / 3, rel=0.02)  # a fourth panel of the same height
