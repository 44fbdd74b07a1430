"""Spatiotemporal nearest-neighbour pair matching (paper section III.1).

Every Gaussian i is a reference. Its nearest other Gaussian is searched (a) with every Gaussian at its own most
visible time mu_t (the canonical xyz and the raw rotation), and (b) with every Gaussian evaluated at the current
training time t (the STG polynomials). i and j are *matched* when both searches return the same j: the two are then
close where each is most visible and still close at t, i.e. they follow similar trajectories.

Distance. Each Gaussian at one time is the 7-D point [x / E, w * q], with x the position, E the scene extent, q the
unit quaternion with its sign made canonical (w >= 0, since q and -q are one rotation) and w = `rotation_weight`
(0 = position only, a 3-D search). Dividing by E makes w scene independent: with w = 0.01 a 30 degree rotation
difference (quaternion chord 2 sin(7.5 deg) = 0.26) weighs as much as 0.26 % of the scene extent, the order of the
nearest-neighbour spacing of a few 100k Gaussians on the scene's surfaces, so rotation separates neighbours that are
about equally close without overriding position. The sign rule is discontinuous where the quaternion's scalar
part is 0 (rotations near 180 degrees): two close rotations on either side lie up to 2 x `rotation_weight` apart,
so a near-duplicate there may lose to a farther neighbour. 0.03-0.05 % of the Gaussians of trained panoptic models
have a scalar part below 0.05 (session 25), so this is left as is.

A pair's *distance*, used to sort pairs for pruning, is the mean of its Euclidean 7-D distances over all the
searched times (canonical, t and any extra sampled times): both members must be close along the whole trajectory,
not only at t, and the mean is symmetric in the pair, so the two directions of a mutual pair get the same distance.

Ties. The nearest neighbour of i is the closest j != i; among exactly equal distances the smallest index wins (what
`argmin` does in the brute-force reference). Exact ties arise from duplicates (a clone is an exact copy of its source
until the optimizer moves it): all copies of a neighbour are equally near, and the smallest index among them is
taken, so both searches pick the same copy. Ties between distinct points at equal distance have measure zero for
trained parameters and are left to the tree.

Speed. scipy's cKDTree, queried with the points in the tree's own leaf order (neighbouring queries then walk the same
nodes and stay in cache: about 3x faster than the input order at 500k), with 2 workers. Rows with non-finite
features (a diverged Gaussian) take no part: they are never matched.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch
from scipy.spatial import cKDTree


class SpacetimeModel(Protocol):
    """What matching needs from a model (the `stgc.model.STGModel` contract)."""

    params: dict[str, torch.nn.Parameter]
    scene_extent: float

    def means_at(self, t: float) -> torch.Tensor: ...

    def rotations_at(self, t: float) -> torch.Tensor: ...


def _workers() -> int:
    return max(1, min(2, os.cpu_count() or 1))


def canonical_quaternions(q: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z) with w >= 0. A zero quaternion (STG's EMS inserts them) maps to identity; a
    non-finite one stays non-finite (a diverged row, which the searches leave out)."""
    q = np.asarray(q, dtype=np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    degenerate = norm[:, 0] <= 1e-12
    out = q / np.where(norm > 1e-12, norm, 1.0)
    out[degenerate] = (1.0, 0.0, 0.0, 0.0)
    # A float -0.0 w keeps its sign bit; compare, do not use np.sign, so w == 0 rows are left as they are.
    out[out[:, 0] < 0] *= -1.0
    return out


def knn_features(positions: np.ndarray, quaternions: np.ndarray, scene_extent: float, rotation_weight: float) -> np.ndarray:
    """The 7-D (3-D when rotation_weight is 0) points of the matching distance, float64 [N, 7|3]."""
    if not scene_extent > 0:
        raise ValueError(f"scene_extent must be positive, got {scene_extent}")
    pos = np.asarray(positions, dtype=np.float64) / float(scene_extent)
    if rotation_weight == 0:
        return np.ascontiguousarray(pos)
    return np.ascontiguousarray(np.hstack([pos, rotation_weight * canonical_quaternions(quaternions)]))


def to_float64_numpy(x: torch.Tensor) -> np.ndarray:
    return x.detach().to("cpu", torch.float64).numpy()


def matching_times(t: float, sample_times: int) -> list[float]:
    """The times of the non-canonical searches: t first, then `sample_times` evenly spaced ones in (0, 1)."""
    return [float(t)] + [(k + 0.5) / sample_times for k in range(sample_times)]


def spacetime_features(
    model: SpacetimeModel, t: float, rotation_weight: float, sample_times: int = 0
) -> list[np.ndarray]:
    """Features of every search: [canonical (xyz, raw rotation), at t, at each extra sampled time]."""
    extent = float(model.scene_extent)
    with torch.no_grad():
        spaces = [knn_features(to_float64_numpy(model.params["xyz"]), to_float64_numpy(model.params["rotation"]), extent, rotation_weight)]
        for time in matching_times(t, sample_times):
            spaces.append(
                knn_features(to_float64_numpy(model.means_at(time)), to_float64_numpy(model.rotations_at(time)), extent, rotation_weight)
            )
        # A diverged rotation is never matched, also where the distance leaves rotations out (rotation_weight 0).
        diverged = ~torch.isfinite(model.params["rotation"]).all(dim=1)
        if "omega" in model.params:
            diverged |= ~torch.isfinite(model.params["omega"]).all(dim=1)
    rows = diverged.cpu().numpy()
    for features in spaces:
        features[rows] = np.nan
    return spaces


def nearest_other(features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For every row: index of the nearest other row (ties: smallest index) and the distance. Non-finite rows: -1, inf.

    Exact (a k-d tree search, not an approximation)."""
    features = np.asarray(features, dtype=np.float64)
    n = features.shape[0]
    nn = np.full(n, -1, dtype=np.int64)
    dist = np.full(n, np.inf)
    valid = np.flatnonzero(np.isfinite(features).all(axis=1))
    if valid.size < 2:
        return nn, dist
    pts = np.ascontiguousarray(features[valid])
    tree = cKDTree(pts, leafsize=32, balanced_tree=False, compact_nodes=False)
    order = tree.indices  # leaf order: consecutive queries are spatial neighbours
    d2, i2 = tree.query(pts[order], k=2, workers=_workers())
    local = np.empty((pts.shape[0], 2), dtype=np.int64)
    dloc = np.empty((pts.shape[0], 2))
    local[order], dloc[order] = i2, d2
    rows = np.arange(pts.shape[0])
    # The query point itself is normally first; with a duplicate both are at distance 0 in either order.
    first_is_self = local[:, 0] == rows
    best = np.where(first_is_self, local[:, 1], local[:, 0])
    best_d = np.where(first_is_self, dloc[:, 1], dloc[:, 0])
    # Exact duplicates: every copy of the neighbour is equally near, so the smallest index among them that is not
    # the query wins. Only rows at distance 0 from their neighbour have copies; group those rows by value.
    dup = np.flatnonzero(best_d == 0.0)
    group = np.zeros(0, dtype=np.int64)
    if dup.size:
        _, group, counts = np.unique(pts[dup] + 0.0, axis=0, return_inverse=True, return_counts=True)  # (-0.0 = 0.0)
        group = group.reshape(-1)
        # Rows that differ by less than a squared distance can hold (below about 1.5e-154, the square root of the
        # smallest float64) are at distance 0 but alone in their group: the tree's answer stands for them.
        together = counts[group] >= 2
        dup = dup[together]
        _, group = np.unique(group[together], return_inverse=True)
        group = group.reshape(-1)
    if dup.size:
        by_group = np.lexsort((dup, group))
        members, sorted_group = dup[by_group], group[by_group]
        starts = np.concatenate([[0], np.flatnonzero(np.diff(sorted_group)) + 1])
        smallest, second = members[starts], members[starts + 1]  # every group has >= 2 members
        group_of = np.full(pts.shape[0], -1, dtype=np.int64)
        group_of[dup] = group
        neighbour_group = group_of[best]
        rows_with_copies = np.flatnonzero(neighbour_group >= 0)
        g = neighbour_group[rows_with_copies]
        best[rows_with_copies] = np.where(smallest[g] == rows_with_copies, second[g], smallest[g])
    nn[valid] = valid[best]
    dist[valid] = best_d
    return nn, dist


def nearest_other_bruteforce(features: np.ndarray, chunk: int = 1024, rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Reference for `nearest_other`: all pairwise distances (torch.cdist, float64, in chunks of query rows).

    `rows` restricts the queries to some rows (the benchmark estimates the full cost from a subsample)."""
    feats = torch.from_numpy(np.asarray(features, dtype=np.float64))
    finite = torch.isfinite(feats).all(dim=1)
    data = torch.where(finite[:, None], feats, torch.zeros_like(feats))
    query_rows = torch.arange(feats.shape[0]) if rows is None else torch.as_tensor(rows, dtype=torch.int64)
    nn = np.full(query_rows.numel(), -1, dtype=np.int64)
    dist = np.full(query_rows.numel(), np.inf)
    if int(finite.sum()) < 2:
        return nn, dist
    for s in range(0, query_rows.numel(), chunk):
        q = query_rows[s : s + chunk]
        # Not the matrix-product formula: it loses precision for near-duplicates and could reorder close ties.
        d = torch.cdist(data[q], data, compute_mode="donot_use_mm_for_euclid_dist")
        d[:, ~finite] = torch.inf
        d[torch.arange(q.numel()), q] = torch.inf
        best = torch.argmin(d, dim=1)  # first minimum: the smallest index among exact ties
        ok = finite[q]
        nn[s : s + q.numel()] = torch.where(ok, best, -1).numpy()
        dist[s : s + q.numel()] = torch.where(ok, d[torch.arange(q.numel()), best], torch.inf).numpy()
    return nn, dist


@dataclass(frozen=True)
class PairMatches:
    """Matched pairs, one per unordered pair, in the order of their reference Gaussian."""

    reference: np.ndarray  # [P] int64, the reference Gaussian i
    partner: np.ndarray  # [P] int64, its nearest neighbour j in every search
    distance: np.ndarray  # [P] float64, mean over the searches of the 7-D distance
    matched_references: int  # references whose searches agreed, before mutual pairs were merged

    def __len__(self) -> int:
        return int(self.reference.size)

    def subset(self, keep: np.ndarray) -> PairMatches:
        """The pairs where the boolean `keep` is true (matched_references unchanged: it counts the searches)."""
        return PairMatches(self.reference[keep], self.partner[keep], self.distance[keep], self.matched_references)


def match_from_neighbors(neighbors: Sequence[np.ndarray], distances: Sequence[np.ndarray]) -> PairMatches:
    """Combine the per-search nearest neighbours into matched pairs (shared by the fast path and the reference)."""
    if len(neighbors) < 2:
        raise ValueError("matching needs at least two searches (canonical and current time)")
    nn0 = neighbors[0]
    agree = nn0 >= 0
    for nn in neighbors[1:]:
        agree &= nn == nn0
    reference = np.flatnonzero(agree)
    partner = nn0[reference]
    distance = np.mean([d[reference] for d in distances], axis=0) if reference.size else np.zeros(0)
    # A mutual pair (i -> j and j -> i) is one pair: keep it at its smaller reference index.
    mutual = np.zeros(nn0.shape[0], dtype=bool)
    mutual[reference] = True
    duplicate = mutual[partner] & (nn0[partner] == reference) & (partner < reference)
    keep = ~duplicate
    return PairMatches(
        reference=reference[keep].astype(np.int64),
        partner=partner[keep].astype(np.int64),
        distance=np.asarray(distance, dtype=np.float64)[keep],
        matched_references=int(reference.size),
    )


def match_pairs(spaces: Sequence[np.ndarray]) -> PairMatches:
    """Pairs whose nearest neighbour agrees in every search space (k-d tree, exact)."""
    results = [nearest_other(f) for f in spaces]
    return match_from_neighbors([r[0] for r in results], [r[1] for r in results])


def match_pairs_bruteforce(spaces: Sequence[np.ndarray]) -> PairMatches:
    """`match_pairs` with O(N^2) brute-force searches: the test and benchmark reference."""
    results = [nearest_other_bruteforce(f) for f in spaces]
    return match_from_neighbors([r[0] for r in results], [r[1] for r in results])


def match_spatiotemporal_pairs(
    model: SpacetimeModel, t: float, rotation_weight: float = 0.01, sample_times: int = 0
) -> PairMatches:
    """Spatiotemporal KNN pairs of a model at training time t (see the module docstring for the distance)."""
    return match_pairs(spacetime_features(model, t, rotation_weight, sample_times))
