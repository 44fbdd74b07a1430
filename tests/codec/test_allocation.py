"""Rate-distortion optimised bit allocation: the knapsack against brute force, the optimiser on a scene whose
sensitivities are known, and compress_run on a real dataset."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
import torch

from stgc.codec import CodecConfig, compress_run, read_stgc, views
from stgc.codec.allocation import (
    _GRID,
    LOSS_BUDGET_DB,
    Option,
    budget_db,
    candidate_bits,
    coarser_bits,
    encoder_settings,
    optimise_allocation,
    solve,
    with_fractional_depths,
)
from stgc.codec.format import bits_for, decode, encode, groups_for
from stgc.codec.synthetic import synthetic_model
from stgc.errors import DataError
from stgc.model import STGModel


def _brute_force(options, budget):
    best = None
    for combo in itertools.product(*options.values()):
        if sum(o.error for o in combo) <= budget:
            cost = sum(o.bytes for o in combo)
            if best is None or cost < best:
                best = cost
    return best


@pytest.mark.parametrize("seed", range(6))
def test_knapsack_is_feasible_and_as_cheap_as_brute_force(seed):
    rng = np.random.default_rng(seed)
    options = {}
    for g in range(4):
        bits = np.arange(3, 3 + rng.integers(3, 6))
        errors = np.sort(rng.uniform(0, 0.5, len(bits)))[::-1]  # fewer bits, more error
        sizes = np.sort(rng.integers(100, 5000, len(bits)))
        options[f"G{g}"] = [Option(int(b), int(s), float(e)) for b, s, e in zip(bits, sizes, errors)]
    budget = 0.6
    chosen = solve(options, budget)
    assert chosen is not None
    picked = [next(o for o in options[t] if o.depth == d) for t, d in chosen.items()]
    assert sum(o.error for o in picked) <= budget  # errors are rounded up, never down
    # Rounding up can only cost what a budget smaller by one grid step per group would.
    tighter = _brute_force(options, budget - len(options) * budget / _GRID)
    assert sum(o.bytes for o in picked) <= tighter
    assert sum(o.bytes for o in picked) >= _brute_force(options, budget)


def test_knapsack_edge_cases():
    options = {"A": [Option(2, 10, 0.5), Option(4, 20, 0.0)], "B": [Option(3, 5, 0.2), Option(5, 9, 0.0)]}
    assert solve(options, 0.0) == {"A": 4, "B": 5}  # only the error-free options fit
    assert solve(options, 0.3) == {"A": 4, "B": 3}
    assert solve(options, 1.0) == {"A": 2, "B": 3}
    assert solve({"A": [Option(2, 10, 0.5)]}, 0.1) is None


def test_step_shapes_equalise_errors_and_fractional_depths_interpolate():
    # Error grows with the square of the step: a component 4x less visible gets a step 2x (1 bit) coarser.
    assert coarser_bits([1.0, 0.25, 1 / 16, 0.3, 0.0, 1e-9]) == [0.0, 1.0, 2.0, 0.75, 4.0, 4.0]
    assert coarser_bits([0.0, -1e-9]) == [0.0, 0.0]  # nothing measurable: no shaping
    options = with_fractional_depths([Option(3.0, 100, 0.4), Option(4.0, 200, 0.1), Option(5.0, 300, 0.0)])
    assert [o.depth for o in options] == [3.0, 3.25, 3.5, 3.75, 4.0, 4.25, 4.5, 4.75, 5.0]
    assert options[2].bytes == 150 and options[2].error == pytest.approx(0.2)  # geometric mean of 0.4 and 0.1
    assert options[6].error == pytest.approx(0.05)  # towards an error-free depth: linear
    bits, scales = encoder_settings("full", {"MOTN": 6.75, "POSI": 12.0, "ROTN": 7.5},
                                    {"MOTN": [0.0] * 6 + [1.0] * 3})
    assert bits == {"MOTN": 7, "POSI": 12, "ROTN": 8}
    assert scales["MOTN"] == pytest.approx([2**0.25] * 6 + [2**1.25] * 3)
    assert scales["ROTN"] == pytest.approx([2**0.5] * 3) and "POSI" not in scales


def test_budgets_and_candidates():
    assert [budget_db(q) for q in (1, 2, 3, 4, 5)] == [1.0, 0.3, 0.1, 0.03, 0.01]
    assert list(LOSS_BUDGET_DB.values()) == sorted(LOSS_BUDGET_DB.values(), reverse=True)
    with pytest.raises(ValueError):
        budget_db(6)
    assert candidate_bits("POSI") == list(range(10, 19))  # ladder q1 - 2 .. ladder q5
    assert min(candidate_bits("OMGA")) >= 2


def _projection_renderer(weights: dict[str, float], seed: int = 0, views: int = 4, calls: list | None = None):
    """A stand-in renderer: `views` 'views' of 64 pixels, each pixel a sum over Gaussians of attribute columns
    times a smooth function of the Gaussian's position (so, like a real renderer, it does not depend on the
    Gaussians' order). The error a group's quantization adds scales with its weight; weight 0: the group does not
    show. Called with no view list it renders all (for the tests' own references); `calls` records each list."""
    rng = np.random.default_rng(seed)
    freq = rng.normal(0, 0.3, (views, 64, 3))
    phase = rng.uniform(0, 2 * np.pi, (views, 64, 1))

    def render(arrays, decoder_state, which=None):
        which = list(range(views)) if which is None else list(which)
        if calls is not None:
            calls.append(which)
        pos = np.stack([np.asarray(arrays[c], np.float64) for c in "xyz"])
        basis = np.cos(np.einsum("vpk,kn->vpn", freq[which], pos) + phase[which]) / math.sqrt(pos.shape[1])
        images = sum(w * basis @ np.asarray(arrays[name], np.float64) for name, w in weights.items())
        return [0.5 + 0.05 * img.reshape(8, 8, 1).repeat(3, axis=2) for img in images]

    return render


def test_optimiser_spends_bits_where_they_show_and_meets_its_budget():
    arrays, decoder = synthetic_model(1500, "full", seed=1)
    render = _projection_renderer({"f_dc_0": 1.0, "f_dc_3": 1.0, "scale_0": 0.02})
    reference = render(arrays, decoder)
    rng = np.random.default_rng(5)
    truth = [r + rng.normal(0, 0.002, r.shape) for r in reference]  # the model's own error: 54 dB
    result = optimise_allocation(arrays, "full", decoder, render, truth, 0.1)
    assert result.within_budget and result.loss_bound_db <= 0.1
    lowest = {t: candidate_bits(t)[0] for t in result.depths}
    # Groups the views do not depend on get the coarsest depth (positions do show: they move the basis); the one
    # that dominates gets more than scale.
    for tag in ("TCEN", "MOTN", "OPAC", "ROTN", "OMGA", "FT__"):
        assert result.depths[tag] == lowest[tag], tag
    assert result.depths["FDC_"] > result.depths["SCAL"]
    # Inside FDC_ only f_dc_0 and f_dc_3 show: the four invisible components get the coarsest steps.
    assert result.shapes["FDC_"] == [0.0, 4.0, 4.0, 0.0, 4.0, 4.0]
    summary = result.summary()
    assert summary["mode"] == "rd-optimised" and summary["views"] == 4 and summary["depths"] == result.depths
    assert summary["coarser_bits"] == result.shapes

    tighter = optimise_allocation(arrays, "full", decoder, render, truth, 0.01)
    assert tighter.depths["FDC_"] > result.depths["FDC_"]


def test_the_table_renders_a_subset_of_the_views_and_rate_control_renders_them_all():
    arrays, decoder = synthetic_model(1500, "full", seed=1)
    calls: list[list[int]] = []
    render = _projection_renderer({"f_dc_0": 1.0, "f_dc_3": 1.0, "scale_0": 0.02}, views=16, calls=calls)
    reference = render(arrays, decoder)
    rng = np.random.default_rng(5)
    truth = [r + rng.normal(0, 0.002, r.shape) for r in reference]
    calls.clear()
    result = optimise_allocation(arrays, "full", decoder, render, truth, 0.1)
    assert result.within_budget and result.views == 16
    assert calls[0] == list(range(16))  # the reference
    table = [c for c in calls if len(c) == 8]
    assert table and all(c == table[0] for c in table)
    assert table[0][0] == 0 and table[0][-1] == 15  # spread over the views
    # The step-shape probes, one per component of each shaped group, render 4 of the table's views.
    probes = [c for c in calls if len(c) == 4]
    assert len(probes) == sum(len(v) for v in result.shapes.values())
    assert all(c == probes[0] for c in probes) and set(probes[0]) <= set(table[0])
    assert probes[0][0] == 0 and probes[0][-1] == 15
    assert all(len(c) in (4, 8, 16) for c in calls)
    rounds = [c for c in calls[1:] if len(c) == 16]
    assert 1 <= len(rounds) <= result.rounds  # a round that repeats an allocation reuses its measurement
    # The sweep stops early: fewer trials than every candidate depth of every group (table: near-lossless + sweep).
    table_trials = len(table) - 1
    assert table_trials < sum(len(candidate_bits(t)) for t in result.depths)


def test_optimiser_rejects_bad_input():
    arrays, decoder = synthetic_model(100, "full", seed=1)
    render = _projection_renderer({"f_dc_0": 1.0})
    with pytest.raises(ValueError, match="at least one"):
        optimise_allocation(arrays, "full", decoder, render, [], 0.1)
    with pytest.raises(ValueError, match="budget"):
        optimise_allocation(arrays, "full", decoder, render, render(arrays, decoder), 0.0)


@pytest.fixture
def toys_run(tmp_path, blender_toys):
    from stgc.data import open_dataset

    dataset = open_dataset(blender_toys, downscale=4, start=0, duration=2)
    arrays, decoder = synthetic_model(300, "full", seed=2, extent=float(dataset.scene_extent()))
    model = STGModel.from_ply_arrays(arrays, "full", decoder)
    run = tmp_path / "run"
    model.save(run / "point_cloud" / "iteration_10")
    config = {"data": {"path": str(blender_toys), "downscale": 4, "start": 0, "duration": 2},
              "model": {"variant": "full"}}
    (run / "config.json").write_text(json.dumps(config))
    return run


def test_compress_run_optimises_bit_depths_on_the_runs_training_views(toys_run):
    config = CodecConfig(allocation="optimised", allocation_views=2)
    result = compress_run(toys_run, toys_run / "rd.stgc", quality=3, config=config)
    assert result.allocation is not None and result.allocation["views"] == 2
    assert result.allocation["within_budget"] and result.allocation["train_view_loss_bound_db"] <= 0.1
    # An untrained model's own error is large, so the budget buys coarse depths: below the ladder's q3 in total.
    ladder_q3 = sum(bits_for(g, 3) for g in groups_for("full"))
    depths = result.allocation["depths"]
    assert sum(depths.values()) < ladder_q3
    stored = read_stgc(toys_run / "rd.stgc")
    assert stored.metadata["allocation"]["depths"] == depths
    for section in stored.header.sections:
        if section.tag in depths:
            assert section.bits >= math.ceil(depths[section.tag])  # the outlier guard may add bits
    assert "rd-optimised" in str(result)

    ladder = compress_run(toys_run, toys_run / "ladder.stgc", quality=3, config=CodecConfig(allocation="ladder"))
    assert ladder.allocation is None and "fixed ladder" in str(ladder)
    assert "allocation" not in read_stgc(toys_run / "ladder.stgc").metadata


def test_views_rendered_side_by_side_give_the_same_file_as_in_turn(toys_run, monkeypatch):
    pools = []

    class CountingPool(views.ThreadPoolExecutor):
        def map(self, *args, **kwargs):
            pools.append(self)
            return super().map(*args, **kwargs)

    monkeypatch.setattr(views, "ThreadPoolExecutor", CountingPool)
    config = CodecConfig(allocation="optimised", allocation_views=4)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        compress_run(toys_run, toys_run / "in_turn.stgc", quality=3, config=config)
        assert not pools
        torch.set_num_threads(2)
        compress_run(toys_run, toys_run / "side_by_side.stgc", quality=3, config=config)
        assert pools  # the views went through the pool
        assert torch.get_num_threads() == 2  # restored after the allocation
    finally:
        torch.set_num_threads(threads)
    assert (toys_run / "in_turn.stgc").read_bytes() == (toys_run / "side_by_side.stgc").read_bytes()


def test_optimised_allocation_without_the_dataset_is_a_clear_error_and_auto_falls_back(toys_run, tmp_path):
    config_path = toys_run / "config.json"
    saved = json.loads(config_path.read_text())
    saved["data"]["path"] = str(tmp_path / "gone")
    config_path.write_text(json.dumps(saved))
    with pytest.raises(DataError, match="training images"):
        compress_run(toys_run, tmp_path / "x.stgc", config=CodecConfig(allocation="optimised"))
    assert not (tmp_path / "x.stgc").exists()
    auto = compress_run(toys_run, tmp_path / "y.stgc", config=CodecConfig(allocation="auto"))
    assert auto.allocation is None


def test_optimiser_on_the_lite_variant_shapes_its_three_colour_channels():
    arrays, _ = synthetic_model(800, "lite", seed=3)
    render = _projection_renderer({"f_dc_0": 1.0, "motion_0": 0.5})
    reference = render(arrays, None)
    rng = np.random.default_rng(6)
    truth = [r + rng.normal(0, 0.002, r.shape) for r in reference]
    result = optimise_allocation(arrays, "lite", None, render, truth, 0.3)
    assert result.within_budget and "FT__" not in result.depths
    assert set(result.shapes) == {"MOTN", "FDC_", "OMGA"}
    assert result.shapes["FDC_"][0] == 0.0 and result.shapes["FDC_"][1:] == [4.0, 4.0]  # only red shows
    assert result.shapes["MOTN"][0] == 0.0 and min(result.shapes["MOTN"][1:]) == 4.0
    group_bits, step_scales = result.encoder_settings()
    decoded = decode(encode(arrays, "lite", None, group_bits=group_bits, step_scales=step_scales))
    assert decoded.num_gaussians == 800
