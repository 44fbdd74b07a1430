"""Spatiotemporal pair matching: constructed scenes with known answers, and agreement with brute force."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from stgc.compaction import (
    match_pairs,
    match_pairs_bruteforce,
    match_spatiotemporal_pairs,
    nearest_other,
    nearest_other_bruteforce,
    spacetime_features,
)
from stgc.compaction.matching import canonical_quaternions, knn_features

from .compaction_helpers import make_model, random_params, static_params


def _pairs(matches) -> set[tuple[int, int]]:
    return {tuple(sorted(p)) for p in zip(matches.reference.tolist(), matches.partner.tolist())}


def _grid(n_side: int, spacing: float) -> np.ndarray:
    """A jittered lattice: an exact one would have distance ties that floats break arbitrarily."""
    g = np.arange(n_side) * spacing
    lattice = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    return lattice + np.random.default_rng(5).uniform(-0.05, 0.05, lattice.shape) * spacing


@pytest.mark.parametrize("dims", [3, 7])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_nearest_other_equals_bruteforce_with_duplicates_and_nonfinite_rows(dims, seed):
    rng = np.random.default_rng(seed)
    pts = rng.random((1500, dims))
    pts[:, 3:] *= 0.05
    pts[10] = pts[3]  # a duplicate pair
    pts[20] = pts[21] = pts[22] = pts[7]  # four copies: the smallest other index must win
    pts[40] = pts[41] = pts[7] + 1e-3  # two copies near them: whoever is nearest to them, copy 40 is the answer
    pts[30, 1] = np.nan  # a diverged Gaussian: never a neighbour, never matched
    nn, d = nearest_other(pts)
    ref_nn, ref_d = nearest_other_bruteforce(pts, chunk=256)
    np.testing.assert_array_equal(nn, ref_nn)
    np.testing.assert_allclose(d, ref_d, rtol=1e-12, atol=0)
    assert nn[3] == 10 and nn[10] == 3
    assert nn[7] == 20 and nn[20] == 7 and nn[21] == 7 and nn[22] == 7 and nn[40] == 41 and nn[41] == 40
    assert nn[30] == -1 and (nn != 30).all()


@pytest.mark.parametrize(
    "seed,rotation_weight,sample_times", [(0, 0.01, 0), (1, 0.0, 0), (2, 0.3, 0), (3, 0.01, 2), (4, 1.0, 1)]
)
def test_matching_equals_bruteforce_on_random_scenes(seed, rotation_weight, sample_times):
    model = make_model(random_params(1200, seed, motion_scale=0.05), scene_extent=2.0)
    t = 0.1 + 0.2 * seed
    spaces = spacetime_features(model, t, rotation_weight, sample_times)
    assert len(spaces) == 2 + sample_times
    assert spaces[0].shape[1] == (3 if rotation_weight == 0 else 7)
    fast, slow = match_pairs(spaces), match_pairs_bruteforce(spaces)
    assert len(fast) > 50  # the scenes are built so that many, but not all, references agree
    assert fast.matched_references < 1200
    np.testing.assert_array_equal(fast.reference, slow.reference)
    np.testing.assert_array_equal(fast.partner, slow.partner)
    np.testing.assert_allclose(fast.distance, slow.distance, rtol=1e-12)
    assert np.all(np.diff(fast.reference) > 0)  # pairs follow the order of the reference Gaussians
    assert len(_pairs(fast)) == len(fast)  # mutual pairs appear once


def test_matching_uses_mean_distance_over_searches():
    model = make_model(random_params(400, 9, motion_scale=0.05))
    spaces = spacetime_features(model, 0.7, 0.01)
    m = match_pairs(spaces)
    i, j = m.reference, m.partner
    expected = 0.5 * (np.linalg.norm(spaces[0][i] - spaces[0][j], axis=1) + np.linalg.norm(spaces[1][i] - spaces[1][j], axis=1))
    np.testing.assert_allclose(m.distance, expected, rtol=1e-12)


def _scene_with_movers(move_a: np.ndarray, move_b: np.ndarray, offset_b: np.ndarray):
    """Static background lattice (spacing 1) plus two movers A, B (mu_t 0.5) starting near lattice point (2, 2, 2)."""
    background = _grid(5, 1.0)
    start = np.array([2.5, 2.5, 2.5])
    xyz = np.vstack([background, start, start + offset_b])
    params = static_params(xyz)
    a, b = len(background), len(background) + 1
    params["motion"][a, 0:3] = torch.as_tensor(move_a, dtype=torch.float32)
    params["motion"][b, 0:3] = torch.as_tensor(move_b, dtype=torch.float32)
    return make_model(params, scene_extent=5.0), a, b


def test_two_gaussians_on_the_same_trajectory_are_matched():
    velocity = np.array([1.2, 0.0, 0.0])  # linear motion: x(t) = x + v (t - 0.5)
    model, a, b = _scene_with_movers(velocity, velocity, np.array([0.02, 0.0, 0.0]))
    for t in (0.0, 0.3, 0.9):
        pairs = _pairs(match_spatiotemporal_pairs(model, t, rotation_weight=0.01))
        assert (a, b) in pairs


def test_gaussians_that_cross_at_t_but_diverge_are_not_matched():
    # A and B start 0.6 apart at their mu_t = 0.5 and move towards each other: at t = 0.8 both sit at x = 2.8,
    # and at t = 0.5 each one's nearest Gaussian is a static background Gaussian put beside it.
    model, a, b = _scene_with_movers(np.array([1.0, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0]), np.array([0.6, 0.0, 0.0]))
    params = {k: v.detach().clone() for k, v in model.params.items()}
    extra = static_params(np.array([[2.5, 2.5, 2.55], [3.1, 2.5, 2.55]]))
    merged = {k: torch.cat([params[k], extra[k]]) for k in params}
    model = make_model(merged, scene_extent=5.0)
    spaces = spacetime_features(model, 0.8, 0.01)
    nn_canonical, _ = nearest_other(spaces[0])
    nn_at_t, _ = nearest_other(spaces[1])
    assert nn_at_t[a] == b and nn_at_t[b] == a  # they cross at t ...
    assert nn_canonical[a] != b and nn_canonical[b] != a  # ... but are not neighbours where they are most visible
    assert not any(a in p and b in p for p in _pairs(match_pairs(spaces)))


def test_rotation_weight_separates_equally_close_neighbours():
    # Reference R at the origin; P1 and P2 both at distance 0.1, P1 a bit closer but rotated by 90 degrees.
    xyz = np.array([[0.0, 0, 0], [0.099, 0, 0], [-0.1, 0, 0], [5, 5, 5], [-5, 5, 5]])
    params = static_params(xyz)
    params["rotation"][1] = torch.tensor([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
    params["rotation"][2] = torch.tensor([-1.0, 0, 0, 0])  # -identity: the same rotation as R
    model = make_model(params, scene_extent=1.0)
    nn_pos, _ = nearest_other(spacetime_features(model, 0.5, 0.0)[0])
    nn_rot, _ = nearest_other(spacetime_features(model, 0.5, 0.1)[0])
    assert nn_pos[0] == 1
    assert nn_rot[0] == 2


def test_canonical_quaternions_sign_and_degenerate():
    q = np.array([[-2.0, 0, 0, 0], [0.0, 0, 0, 0], [0.5, -0.5, 0.5, -0.5], [-0.5, 0.5, 0.5, 0.5]])
    c = canonical_quaternions(q)
    np.testing.assert_allclose(c, [[1, 0, 0, 0], [1, 0, 0, 0], [0.5, -0.5, 0.5, -0.5], [0.5, -0.5, -0.5, -0.5]])
    f = knn_features(np.ones((4, 3)) * 4.0, q, scene_extent=2.0, rotation_weight=0.5)
    np.testing.assert_allclose(f[:, :3], 2.0)
    np.testing.assert_allclose(f[:, 3:], 0.5 * c)


def test_rows_closer_than_a_squared_distance_can_hold_are_not_taken_for_copies():
    # Squared distances of 1e-170 underflow to 0: the rows are at distance 0 without being equal. Each is alone in
    # its value group; the tree's neighbour stands (it crashed indexing a group of one).
    pts = np.array([[0, 0, 0, 1e-170], [0, 0, 0, 2e-170], [0, 0, 0, 3e-170], [1, 1, 1, 0]], dtype=float)
    nn, d = nearest_other(pts)
    assert d[:3].tolist() == [0.0, 0.0, 0.0] and set(nn[:3].tolist()) <= {0, 1, 2}
    assert all(nn[i] != i for i in range(4)) and nn[3] in (0, 1, 2)
    pts[3] = pts[0]  # a real copy as well: every row still gets another row at distance 0
    nn, d = nearest_other(pts)
    assert d.tolist() == [0.0] * 4 and all(nn[i] not in (i, -1) for i in range(4))


def _pair_at(b_offset: np.ndarray, b_quadratic: np.ndarray, extra: np.ndarray | None = None):
    """Background lattice (spacing 1, extent 5) with A static at (2.5, 2.5, 2.5) and B beside it moving as
    b_quadratic (t - 0.5)^2: at the same place at mu_t = 0.5 and t = 0.5, apart at the sampled times 0.25, 0.75."""
    start = np.array([2.5, 2.5, 2.5])
    rows = [_grid(5, 1.0), start[None], (start + b_offset)[None]] + ([] if extra is None else [extra])
    params = static_params(np.vstack(rows))
    a = len(rows[0])
    params["motion"][a + 1, 3:6] = torch.as_tensor(b_quadratic, dtype=torch.float32)
    return make_model(params, scene_extent=5.0), a, a + 1


def test_sample_times_must_agree_too_and_enter_the_mean_distance():
    # B drifts 0.01 further from A at the sampled times: still its neighbour there, the distance's mean moves.
    model, a, b = _pair_at(np.array([0.02, 0.0, 0.0]), np.array([0.16, 0.0, 0.0]))
    for k, expected in ((0, 0.02), (2, (0.02 + 0.02 + 0.03 + 0.03) / 4)):
        m = match_spatiotemporal_pairs(model, 0.5, rotation_weight=0.0, sample_times=k)
        (at,) = np.flatnonzero((m.reference == a) & (m.partner == b))
        assert m.distance[at] == pytest.approx(expected / 5.0, rel=1e-5)
    # B reaches another Gaussian C at the sampled times: matched at mu_t and t alone, not when those must agree.
    model, a, b = _pair_at(np.array([0.02, 0.0, 0.0]), np.array([16.0, 0.0, 0.0]), extra=np.array([[3.53, 2.5, 2.5]]))
    assert (a, b) in _pairs(match_spatiotemporal_pairs(model, 0.5, rotation_weight=0.0, sample_times=0))
    assert (a, b) not in _pairs(match_spatiotemporal_pairs(model, 0.5, rotation_weight=0.0, sample_times=2))


@pytest.mark.parametrize("rotation_weight", [0.01, 0.0])
@pytest.mark.parametrize("diverged", ["rotation", "omega"])
def test_a_row_with_a_non_finite_rotation_or_omega_is_never_matched(rotation_weight, diverged):
    # A NaN quaternion read as the identity: the diverged row matched its healthy twin and could outlive it.
    model, a, b = _pair_at(np.array([0.001, 0.0, 0.0]), np.zeros(3))
    assert (a, b) in _pairs(match_spatiotemporal_pairs(model, 0.5, rotation_weight=rotation_weight))
    model.params[diverged].data[a, 1] = float("nan")
    assert not any(a in p for p in _pairs(match_spatiotemporal_pairs(model, 0.5, rotation_weight=rotation_weight)))
    assert not np.isfinite(canonical_quaternions(np.array([[np.nan, 0.0, 0.0, 0.0]]))).all()
