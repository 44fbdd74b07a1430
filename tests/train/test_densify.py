"""Density control keeps the model, Adam's moments and the trainer's statistics aligned row by row."""

from __future__ import annotations

import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from stgc.config import ConfigError, validate_config
from stgc.model import STGModel
from stgc.train.config import (
    DensifyConfig,
    FloaterConfig,
    QuantizationAwareConfig,
    TrainConfig,
    opacity_reset_iterations,
    resolve_schedule,
)
from stgc.train.densify import (
    DensificationStats,
    apply_prune,
    clone_and_split,
    prune_mask_floaters,
    prune_mask_low_opacity,
    prune_mask_nonfinite,
)
from stgc.train.loop import learning_rates, xyz_learning_rate


def _model(n: int = 40, seed: int = 0) -> STGModel:
    rng = np.random.default_rng(seed)
    cloud = SimpleNamespace(
        xyz=rng.normal(size=(n, 3)).astype(np.float32),
        rgb=rng.uniform(size=(n, 3)).astype(np.float32),
        time=rng.uniform(size=n).astype(np.float32),
    )
    return STGModel.from_points(cloud, variant="full", scene_extent=2.0)


def _optimizer_with_moments(model: STGModel) -> torch.optim.Adam:
    """An optimizer whose per-row moments encode the row identity: row i has exp_avg == i (+ column offset)."""
    opt = model.make_optimizer(learning_rates(TrainConfig().resolved(sparse_cloud=False, family=None), model.scene_extent), 1e-4)
    for p in model.params.values():
        p.grad = torch.ones_like(p)
    opt.step()
    n = model.num_gaussians
    for p in model.params.values():
        st = opt.state[p]
        rows = torch.arange(n, dtype=torch.float32)[:, None]
        st["exp_avg"].copy_(rows.expand_as(p) + 0.5)
        st["exp_avg_sq"].copy_(rows.expand_as(p) + 1.5)
    return opt


def _row_ids(opt: torch.optim.Adam, model: STGModel) -> dict[str, torch.Tensor]:
    return {k: opt.state[p]["exp_avg"][:, 0] - 0.5 for k, p in model.params.items()}


def test_clone_and_split_moves_moments_with_rows_and_zeroes_new_ones():
    model = _model()
    opt = _optimizer_with_moments(model)
    n0 = model.num_gaussians
    # Half small (cloned), half large (split); only rows with index % 3 == 0 have a large gradient.
    with torch.no_grad():
        model.params["scaling"][: n0 // 2] = np.log(0.001)
        model.params["scaling"][n0 // 2 :] = np.log(0.5)
    stats = DensificationStats(n0)
    grads = torch.where(torch.arange(n0) % 3 == 0, 1e-3, 1e-5)
    stats.add(torch.arange(n0), grads, torch.ones(n0, dtype=torch.bool))
    before = {k: p.detach().clone() for k, p in model.params.items()}
    clone_rows = [i for i in range(n0 // 2) if i % 3 == 0]
    split_rows = [i for i in range(n0 // 2, n0) if i % 3 == 0]

    report = clone_and_split(model, stats, 2e-4, 0.01, 2, torch.Generator().manual_seed(0))

    assert report == {"cloned": len(clone_rows), "split": len(split_rows)}
    n1 = n0 + len(clone_rows) + len(split_rows)  # each split row becomes 2 and the original goes
    assert model.num_gaussians == n1 and len(stats) == n1
    survivors = [i for i in range(n0) if i not in split_rows]
    ids = _row_ids(opt, model)
    for key, p in model.params.items():
        assert opt.state[p]["exp_avg"].shape == p.shape
        # Surviving originals keep their own moments, in order; every new row starts at zero.
        assert torch.equal(ids[key][: len(survivors)], torch.tensor(survivors, dtype=torch.float32))
        assert torch.all(opt.state[p]["exp_avg"][len(survivors):] == 0)
        assert torch.all(opt.state[p]["exp_avg_sq"][len(survivors):] == 0)
    # Clones: exact copies except a fresh temporal centre in [0, 1].
    k = len(survivors)
    clone = {key: p.detach()[k : k + len(clone_rows)] for key, p in model.params.items()}
    assert torch.equal(clone["xyz"], before["xyz"][clone_rows])
    assert torch.equal(clone["features_dc"], before["features_dc"][clone_rows])
    assert torch.all((clone["trbf_center"] >= 0) & (clone["trbf_center"] <= 1))
    # Split children: scale / (0.8 * 2), positions near the parent (within 5 parent sigmas).
    children = {key: p.detach()[k + len(clone_rows) :] for key, p in model.params.items()}
    parents = torch.tensor(split_rows * 2)
    assert torch.allclose(children["scaling"], before["scaling"][parents] - np.log(1.6), atol=1e-6)
    assert torch.all((children["xyz"] - before["xyz"][parents]).norm(dim=1) < 5 * 0.5 * np.sqrt(3))
    assert torch.all(stats.count == 0)  # statistics restart after each round


def test_prunes_remove_rows_from_model_moments_and_statistics_alike():
    model = _model()
    opt = _optimizer_with_moments(model)
    n0 = model.num_gaussians
    stats = DensificationStats(n0)
    stats.add(torch.arange(n0), torch.arange(n0, dtype=torch.float32), torch.ones(n0, dtype=torch.bool))
    with torch.no_grad():
        model.params["opacity"][::4] = -10.0  # sigmoid ~ 4.5e-5 < 0.005
        model.params["motion"][5, 2] = float("nan")
    remove = prune_mask_low_opacity(model, 0.005) | prune_mask_nonfinite(model)
    expected = [i for i in range(n0) if i % 4 != 0 and i != 5]
    assert apply_prune(model, stats, remove) == n0 - len(expected)
    for ids in _row_ids(opt, model).values():
        assert torch.equal(ids, torch.tensor(expected, dtype=torch.float32))
    assert torch.equal(stats.grad_sum, torch.tensor(expected, dtype=torch.float64))


@pytest.mark.parametrize("values", [[], [float("nan")], [float("inf")], [float("-inf")],
                                    [float("inf"), float("-inf")], [3e38, 3e38]])
def test_the_non_finite_rows_are_found_exactly_whatever_the_sums_do(values):
    """The scan first asks whether each parameter's sum is finite: an inf beside a -inf, or finite values whose sum
    overflows, must still give exactly the rows with a NaN or inf."""
    model = _model()
    with torch.no_grad():
        for k, value in enumerate(values):
            model.params["motion"][3 + k, 1] = value
    expected = torch.zeros(model.num_gaussians, dtype=torch.bool)
    for p in model.params.values():
        expected |= ~torch.isfinite(p.detach()).reshape(model.num_gaussians, -1).all(dim=1)
    assert torch.equal(prune_mask_nonfinite(model), expected)
    assert int(expected.sum()) == sum(not math.isfinite(v) for v in values)


def test_opacity_reset_caps_opacity_and_clears_its_moments_only():
    model = _model()
    opt = _optimizer_with_moments(model)
    with torch.no_grad():
        model.params["opacity"][:5] = -6.0  # below the cap stays
    low = model.params["opacity"].detach()[:5].clone()
    model.reset_opacity(0.01)
    op = model.params["opacity"]
    assert torch.all(torch.sigmoid(op) <= 0.01 + 1e-7)
    assert torch.equal(op.detach()[:5], low)
    assert torch.all(opt.state[op]["exp_avg"] == 0) and torch.all(opt.state[op]["exp_avg_sq"] == 0)
    assert torch.all(opt.state[model.params["xyz"]]["exp_avg"][:, 0] == torch.arange(40) + 0.5)
    # The optimizer still updates the (new) opacity tensor.
    op.grad = torch.ones_like(op)
    before = op.detach().clone()
    opt.step()
    assert not torch.equal(model.params["opacity"].detach(), before)


def test_near_camera_rule():
    model = _model()
    with torch.no_grad():
        model.params["xyz"][0] = torch.tensor([5.0, 0.0, 0.0])
        model.params["scaling"][1] = np.log(3.0)
    centers = np.array([[5.05, 0.0, 0.0]])
    remove = prune_mask_floaters(model, centers, near_camera=0.05, max_world_scale=0.0)
    assert remove.tolist() == [True] + [False] * 39  # 0.05 < 0.05*E = 0.1


def _scene(centres: np.ndarray, seed: int = 0) -> STGModel:
    """Points at `centres` with small scales, the scene extent of cameras on a circle of radius 1.5 around them."""
    rng = np.random.default_rng(seed)
    cloud = SimpleNamespace(xyz=centres.astype(np.float32), rgb=rng.uniform(size=(len(centres), 3)),
                            time=rng.uniform(size=len(centres)))
    model = STGModel.from_points(cloud, variant="full", scene_extent=1.1 * 1.5)
    with torch.no_grad():
        model.params["scaling"].fill_(np.log(0.05))
    return model


def _camera_ring(count: int = 8, radius: float = 1.5) -> np.ndarray:
    angles = np.linspace(0, 2 * np.pi, count, endpoint=False)
    return np.column_stack([radius * np.cos(angles), radius * np.sin(angles), np.zeros(count)])


def test_scale_rule_removes_gaussians_larger_than_the_scene_around_the_cameras():
    # Cameras on a circle of radius 1.5 around a unit ball of points: the scene radius is E = 1.65.
    rng = np.random.default_rng(1)
    model = _scene(rng.uniform(-1, 1, size=(400, 3)))
    cameras = _camera_ring()
    with torch.no_grad():
        model.params["scaling"][0] = np.log(2.0)  # larger than the scene: removed
        model.params["scaling"][1, 0] = np.log(1.5)  # a wall-sized sheet within it: kept
    remove = prune_mask_floaters(model, cameras, near_camera=0.0, max_world_scale=1.0)
    assert remove.nonzero().ravel().tolist() == [0]
    assert not prune_mask_floaters(model, cameras, near_camera=0.0, max_world_scale=0.0).any()


def test_scale_rule_with_an_opacity_gate_keeps_large_translucent_gaussians():
    # Two Gaussians larger than the scene: an opaque one (a haze over a held-out view) and a translucent one;
    # with the default scale_min_opacity (0.5) only the opaque one goes, with 0 both do.
    rng = np.random.default_rng(3)
    model = _scene(rng.uniform(-1, 1, size=(200, 3)))
    cameras = _camera_ring()
    with torch.no_grad():
        model.params["scaling"][[0, 1]] = np.log(2.0)
        model.params["opacity"][0] = torch.logit(torch.tensor(0.9))
        model.params["opacity"][1] = torch.logit(torch.tensor(0.1))
    gated = prune_mask_floaters(model, cameras, near_camera=0.0, max_world_scale=1.0,
                                scale_min_opacity=FloaterConfig().scale_min_opacity)
    assert gated.nonzero().ravel().tolist() == [0]
    ungated = prune_mask_floaters(model, cameras, near_camera=0.0, max_world_scale=1.0)
    assert ungated.nonzero().ravel().tolist() == [0, 1]


def test_floater_options_are_validated():
    with pytest.raises(ConfigError, match="floaters.scale_min_opacity"):
        validate_config(FloaterConfig(scale_min_opacity=1.5), "floaters")
    with pytest.raises(ConfigError, match="floaters.max_world_scale"):
        validate_config(FloaterConfig(max_world_scale=-1.0), "floaters")


def test_error_guided_sampling_options_and_the_seed_are_validated():
    """Each failed mid-training, after the run's folder was written (a ZeroDivisionError for patch 0)."""
    from stgc.train import TrainConfig
    from stgc.train.config import EMSConfig

    for bad, name in ((EMSConfig(patch=0), "ems.patch"), (EMSConfig(error_quantile=1.5), "ems.error_quantile"),
                      (EMSConfig(depth_near=8.0), "ems.depth_near"), (EMSConfig(min_gap=-1), "ems.min_gap")):
        with pytest.raises(ConfigError, match=name):
            validate_config(TrainConfig(ems=bad), "train")
    with pytest.raises(ConfigError, match="train.seed"):
        validate_config(TrainConfig(seed=-1), "train")
    validate_config(TrainConfig(), "train")


def test_scale_rule_keeps_a_far_background_of_a_forward_facing_rig():
    # Cameras within 0.2 of the origin (E = 0.22 by their spread), the scene up to 10 away: with the default
    # threshold a background Gaussian of size 3 at distance 10 is part of the scene (a rule in units of E would
    # remove it); one of 12 is not.
    rng = np.random.default_rng(2)
    near = rng.uniform(-1, 1, size=(300, 3)) + [0, 0, 3]
    background = np.column_stack([rng.uniform(-5, 5, 100), rng.uniform(-3, 3, 100), np.full(100, 10.0)])
    model = _scene(np.vstack([near, background]))
    model.scene_extent = 0.22
    cameras = np.array([[-0.2, 0, 0], [0.2, 0, 0], [0, 0.2, 0], [0, -0.2, 0]])
    with torch.no_grad():
        model.params["scaling"][300] = np.log(3.0)
        model.params["scaling"][301] = np.log(12.0)
    remove = prune_mask_floaters(model, cameras, near_camera=0.0, max_world_scale=FloaterConfig().max_world_scale)
    assert remove.nonzero().ravel().tolist() == [301]


def test_floater_rules_stop_before_a_learned_mask_window():
    official = DensifyConfig().resolved(sparse_cloud=False)
    plain = TrainConfig(iterations=3000, schedule_scale=0.1, densify=official)
    assert resolve_schedule(plain).floaters_until == 3000
    simulated = replace(plain, quantization_aware=QuantizationAwareConfig(iterations=500))
    assert resolve_schedule(simulated).floaters_until == 3000  # no mask: the rows may change
    masked = replace(plain, quantization_aware=QuantizationAwareConfig(iterations=500, mask=True))
    assert resolve_schedule(masked).floaters_until == 2500


def test_schedule_scaling_and_xyz_decay():
    official = DensifyConfig().resolved(sparse_cloud=False)
    sched = resolve_schedule(TrainConfig(iterations=3000, schedule_scale=0.1, densify=official))
    assert sched.iterations == 3000 and sched.densify_start == 50 and sched.densify_interval == 10
    assert sched.densify_end == 50 + 6 * 10 and sched.opacity_reset_interval == 300
    assert sched.save_iterations[-1] == 3000 and 700 in sched.save_iterations
    assert not sched.is_densify_step(50) and sched.is_densify_step(60) and not sched.is_densify_step(65)
    for start in (0, 50, 51, 60, 61, 2995, 3000):  # the first step is_densify_step accepts, found by walking
        walked = next((i for i in range(start, 3001) if sched.is_densify_step(i)), None)
        assert sched.first_densify_step(start) == walked, start
    cfg = TrainConfig()
    assert xyz_learning_rate(cfg, 2.0, 0, 100) == pytest.approx(3.2e-4)
    assert xyz_learning_rate(cfg, 2.0, 100, 100) == pytest.approx(3.2e-6)
    assert xyz_learning_rate(cfg, 2.0, 50, 100) == pytest.approx(np.sqrt(3.2e-4 * 3.2e-6))


def test_train_config_is_cli_ready():
    from stgc.config import apply_overrides, from_dict, iter_fields, to_dict
    from stgc.train import train_preset

    specs = list(iter_fields(TrainConfig))
    assert all(s.help for s in specs), [s.dotted for s in specs if not s.help]
    cfg = apply_overrides(train_preset("cpu"), {"densify.rounds": "12", "save_iterations": "100,200",
                                                "stop_after": "none", "ems.enabled": "true"})
    assert cfg.densify.rounds == 12 and cfg.save_iterations == (100, 200) and cfg.ems.enabled
    assert from_dict(TrainConfig, to_dict(cfg)) == cfg
    assert train_preset("paper").schedule_scale == 1.0
    cpu = train_preset("cpu")
    assert resolve_schedule(replace(cpu, densify=cpu.densify.resolved(False))).iterations < 30000
    with pytest.raises(ValueError, match="resolve"):
        resolve_schedule(cpu)  # interval and rounds left to the data: nothing may guess them


def test_densification_defaults_follow_the_initial_clouds_kind_and_an_explicit_value_wins():
    unset = DensifyConfig()
    assert unset.resolved(sparse_cloud=False) == replace(unset, **DensifyConfig.OFFICIAL)
    sparse = unset.resolved(sparse_cloud=True)
    assert (sparse.interval, sparse.rounds, sparse.max_growth) == (500, 20, 2.0)
    assert replace(unset, rounds=9).resolved(sparse_cloud=True).rounds == 9
    assert replace(unset, max_growth=0.0).resolved(sparse_cloud=True).cap(1000) == 0
    assert sparse.cap(1000) == 2000


def test_gaussian_budget_takes_the_largest_gradients_and_never_exceeds_the_cap():
    model = _model(40)
    with torch.no_grad():  # rows 0-19 small (a clone adds 1), rows 20-39 large (a split into 2 adds 1 as well)
        model.params["scaling"][:20] = np.log(0.001)
        model.params["scaling"][20:] = np.log(0.5)
    stats = DensificationStats(40)
    grads = torch.linspace(1.0, 40.0, 40, dtype=torch.float64) * 1e-3  # every row a candidate; row 39 largest
    stats.add(torch.arange(40), grads, torch.ones(40, dtype=torch.bool))
    xyz_before = model.params["xyz"].detach().clone()
    done = clone_and_split(model, stats, 1e-4, 0.01, 2, torch.Generator().manual_seed(0), max_gaussians=46)
    assert model.num_gaussians == 46
    assert done == {"cloned": 0, "split": 6}  # the six largest gradients are rows 34-39, all large: split
    kept = model.params["xyz"].detach()[:34]
    torch.testing.assert_close(kept, xyz_before[:34])  # the rest wait; the originals of the split rows are gone
    # Without room nothing changes; without a cap all 40 go.
    stats.add(torch.arange(46), torch.ones(46, dtype=torch.float64), torch.ones(46, dtype=torch.bool))
    assert clone_and_split(model, stats, 1e-4, 0.01, 2, torch.Generator(), max_gaussians=46) == {"cloned": 0, "split": 0}


def test_the_growth_cap_is_relative_to_the_initial_count_and_the_smaller_cap_wins():
    from stgc.train.config import DensifyConfig

    assert DensifyConfig().cap(10_000) == 0
    assert DensifyConfig(max_growth=2.0).cap(15_000) == 30_000
    assert DensifyConfig(max_growth=2.0, max_gaussians=20_000).cap(15_000) == 20_000
    assert DensifyConfig(max_gaussians=20_000).cap(15_000) == 20_000


def test_trainer_records_the_densification_its_initial_cloud_called_for(tmp_path):
    import json

    from scenes import write_panoptic_scene

    from stgc.data import DataConfig, open_dataset
    from stgc.model import STGModel
    from stgc.train.loop import Trainer

    scene = write_panoptic_scene(tmp_path / "scene", views=4, frames=1, width=24, height=18)
    dataset = open_dataset(scene.root)  # Panoptic ships no points: stgc triangulates a sparse cloud
    quiet = TrainConfig(iterations=1, eval_at_end=False, progress=False, tensorboard=False, checkpoint_every=0)
    recorded = {}
    for name, data_cfg in (("auto", DataConfig()), ("shipped", DataConfig(init_source="data"))):
        model = STGModel.from_state_dict(scene.model.state_dict())
        Trainer(dataset, data_cfg, None, quiet, None, tmp_path / name, model=model)
        recorded[name] = json.loads((tmp_path / name / "config.json").read_text())["train"]["densify"]
    assert (recorded["auto"]["interval"], recorded["auto"]["rounds"], recorded["auto"]["max_growth"]) == (500, 20, 2.0)
    assert (recorded["shipped"]["interval"], recorded["shipped"]["rounds"]) == (100, 6)


@pytest.mark.parametrize("prune_in_rounds", [False, True])
def test_pruning_in_clone_split_rounds_is_an_option(prune_in_rounds):
    """Off (official STG): a faint Gaussian outlives a clone/split round; on (3DGS): the round removes it, and the
    statistics stay row-aligned with the model."""
    from stgc.train.densify import DensityControl

    model = _model(40)
    with torch.no_grad():
        model.params["opacity"][:5] = -8.0  # sigmoid ~ 3e-4, below the 0.005 threshold
    cfg = replace(DensifyConfig(), prune_in_rounds=prune_in_rounds).resolved(sparse_cloud=True)
    schedule = resolve_schedule(replace(TrainConfig(), densify=cfg, schedule_scale=0.2, iterations=6000))
    control = DensityControl(cfg, FloaterConfig(max_world_scale=0.0), schedule, model.num_gaussians, np.zeros((0, 3)))
    first_round = schedule.densify_start + schedule.densify_interval
    report = control.step(first_round, model, torch.Generator().manual_seed(0))
    assert control.rounds_done == 1
    assert model.num_gaussians == (35 if prune_in_rounds else 40)
    assert report.get("pruned_opacity", 0) == (5 if prune_in_rounds else 0)
    # Unset, it follows the initial cloud: on with the sparse-cloud schedule, off with the official one.
    assert DensifyConfig().resolved(sparse_cloud=True).prune_in_rounds is True
    assert DensifyConfig().resolved(sparse_cloud=False).prune_in_rounds is False
    assert control.stats.count.shape[0] == model.num_gaussians


def test_the_official_count_adds_the_views_a_temporally_invisible_gaussian_is_in_frustum_of():
    """densify.stats_count 'in_frustum': a view counts for every Gaussian whose 3-sigma box reaches it, rendered or
    culled as temporally invisible (official STG: 0 to the sum, 1 to the count); 'rendered' counts only the rendered
    ones. Positions worked out by hand: a 64x48 camera at the origin looking down +z, f = 50."""
    from stgc.data.cameras import Camera
    from stgc.train.densify import DensityControl, reaches_view

    model = _model(4)
    with torch.no_grad():
        # In view; behind the camera; far right of the image with a tiny scale (u = 1032, radius 0.3 px); 8 px right
        # of the image with scale 1 (u = 72, radius 30 px: its box reaches in).
        model.params["xyz"].copy_(torch.tensor([[0.0, 0, 5], [0, 0, -5], [100, 0, 5], [4.0, 0, 5]]))
        model.params["motion"].zero_()
        model.params["scaling"].copy_(torch.log(torch.tensor([[0.1] * 3, [0.1] * 3, [0.01] * 3, [1.0] * 3])))
    camera = Camera("c", 0, 0.5, np.array([[50.0, 0, 32], [0, 50, 24], [0, 0, 1]]), np.eye(4), 64, 48)
    assert reaches_view(model, camera, 0.5).tolist() == [True, False, False, True]

    render = SimpleNamespace(index=torch.tensor([0]), raster=SimpleNamespace(
        visible=torch.tensor([True]), means2d_grad_ndc_norm=lambda: torch.tensor([0.25])))
    counts = {}
    for count in ("rendered", "in_frustum"):
        densify = DensifyConfig(stats_count=count).resolved(False)
        schedule = resolve_schedule(TrainConfig(iterations=3000, densify=densify))
        density = DensityControl(densify, FloaterConfig(), schedule, 4, np.zeros((1, 3)))
        density.observe(render, 1, 2, model, camera, 0.5)
        counts[count] = density.stats.count.tolist()
        assert density.stats.grad_sum.tolist() == [0.5, 0, 0, 0]  # the gradient of view 1 of 2, times 2
    assert counts == {"rendered": [1, 0, 0, 0], "in_frustum": [1, 0, 0, 1]}


def test_no_clone_split_round_falls_after_the_schedule_s_last_even_where_rounds_are_owed():
    """A continuation past densify_end whose source owes rounds (densification switched on, more rounds) cloned on
    at every later densification step, past the end its config.json records and the mask window's check assumes."""
    from stgc.train.densify import DensityControl

    model = _model(40)
    cfg = DensifyConfig().resolved(sparse_cloud=False)
    schedule = resolve_schedule(replace(TrainConfig(), densify=cfg, schedule_scale=0.01, iterations=300))
    control = DensityControl(cfg, FloaterConfig(max_world_scale=0.0), schedule, model.num_gaussians, np.zeros((0, 3)))
    assert control.rounds_done == 0 and control.collecting  # as a source trained without densification
    after = schedule.densify_end + schedule.densify_interval
    assert schedule.is_densify_step(after)
    control.stats.grad_sum[:] = 1.0  # every row above the gradient threshold
    control.stats.count[:] = 1
    report = control.step(after, model, torch.Generator().manual_seed(0))
    assert model.num_gaussians == 40 and control.rounds_done == 0 and "cloned" not in report
    assert not control.collecting  # nor are statistics gathered any more, a resume included
    resumed = DensityControl(cfg, FloaterConfig(max_world_scale=0.0), schedule, 40, np.zeros((0, 3)))
    resumed.load_state_dict(control.state_dict())
    assert not resumed.collecting


def test_clone_split_does_not_refill_what_compaction_removed():
    """A sparse cloud's capped rounds run into the ST-KNN window: refilling to the cap undid the window's first
    pruning steps (panoptic Case 2, session 30: every Gaussian removed before iteration 3150 came back)."""
    from stgc.train.densify import DensityControl

    model = _model(40)
    cfg = replace(DensifyConfig(max_growth=1.5).resolved(sparse_cloud=True), prune_in_rounds=False)
    schedule = resolve_schedule(replace(TrainConfig(), densify=cfg, schedule_scale=0.01, iterations=300))
    control = DensityControl(cfg, FloaterConfig(max_world_scale=0.0), schedule, model.num_gaussians, np.zeros((0, 3)))
    assert control.cap() == 60
    keep = torch.ones(40, dtype=torch.bool)
    keep[:10] = False  # a compaction step removes ten
    model.prune(keep)
    control.rows_kept(keep)
    assert control.cap() == 50
    resumed = DensityControl(cfg, FloaterConfig(max_world_scale=0.0), schedule, 40, np.zeros((0, 3)))
    resumed.load_state_dict(control.state_dict())
    assert resumed.cap() == 50
    control.stats.grad_sum[:] = 1.0  # every row above the gradient threshold
    control.stats.count[:] = 1
    first_round = schedule.first_densify_step(1)
    control.step(first_round, model, torch.Generator().manual_seed(0))
    assert model.num_gaussians == 50  # 30 + 20, not back to 60
    # Without a cap, nothing changes.
    uncapped = DensityControl(replace(cfg, max_growth=0.0), FloaterConfig(max_world_scale=0.0), schedule, 40,
                              np.zeros((0, 3)))
    uncapped.rows_kept(keep)
    assert uncapped.cap() == 0


@pytest.mark.parametrize("reset_options", [
    {}, {"opacity_reset_interval": 0}, {"opacity_reset_interval": 500, "opacity_reset_until": 400},
    {"opacity_reset_interval": 500, "opacity_reset_until": 1600}, {"opacity_reset_interval": 20000},
    {"opacity_reset_interval": 10000, "opacity_reset_until": 30000}, {"opacity_reset_interval": 3000},
])
@pytest.mark.parametrize("scale", [0.05, 0.3, 1.0])
def test_the_opacity_resets_are_known_before_the_data_resolves_the_schedule(reset_options, scale):
    """`opacity_reset_iterations` (which option checks use before any data is read) and the resolved schedule's list
    are the iterations at which training resets (`Schedule.is_opacity_reset`, asked at every iteration)."""
    cfg = replace(TrainConfig(iterations=9000, schedule_scale=scale),
                  densify=replace(DensifyConfig(), **reset_options))
    schedule = resolve_schedule(cfg.resolved(sparse_cloud=True, family=None))
    resets = tuple(i for i in range(1, cfg.iterations + 1) if schedule.is_opacity_reset(i))
    assert opacity_reset_iterations(cfg) == schedule.opacity_resets() == resets
