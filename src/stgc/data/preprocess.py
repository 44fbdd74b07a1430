"""Reduction of the merged initial point cloud before training, frame by frame (points of one time).

Two rules, named for what they do:

"stg-isolated" (the official STG code, `helper_model.interpolate_point`): the first frame keeps all its
points; every other frame keeps only its most isolated points. With d_i the distance of point i to its
nearest other point of the same frame, M the frame's point count and num_take = int(fraction · M), a
point is kept when d_i > s[-num_take], s being the d_i sorted ascending. The comparison is strict, so
(without ties) num_take − 1 points are kept, not num_take: the official off-by-one, replicated. When
num_take = 0 the official indexing s[-0] = s[0] applies, which drops only the points at the minimum
distance. Frames with fewer than 2 points are kept whole (no neighbour to measure).

"closest-pairs" (the paper's description: "remove the top 25 % of the closest pairs"): in each frame,
every point is paired with its nearest neighbour; the unordered pairs are de-duplicated (a mutual pair
counts once) and sorted by distance (ties by indices). The closest int(fraction · number of pairs)
pairs are selected and visited in ascending order; each visit drops one member, the one with the larger
index in the input, unless that would leave some selected pair with no member: a point is dropped only
if none of its selected partners is dropped, and the partners of a dropped point are protected from
later drops. So no selected pair ever loses both points, and at most one point per selected pair goes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal, cast, get_args

import numpy as np
from scipy.spatial import cKDTree

from .points import PointCloud

PreprocessMode = Literal["none", "stg-isolated", "closest-pairs"]
MODES = get_args(PreprocessMode)


@dataclass
class PreprocessReport:
    mode: str
    fraction: float
    per_frame: list[dict[str, Any]] = field(default_factory=list)  # {"time", "before", "after"}

    @property
    def before(self) -> int:
        return sum(r["before"] for r in self.per_frame)

    @property
    def after(self) -> int:
        return sum(r["after"] for r in self.per_frame)

    def as_dict(self) -> dict[str, Any]:
        return {"mode": self.mode, "fraction": self.fraction, "before": self.before, "after": self.after,
                "per_frame": self.per_frame}


def preprocess_points(cloud: PointCloud, mode: str = "none", fraction: float = 0.25) -> tuple[PointCloud, PreprocessReport]:
    """Apply `mode` frame by frame (frames = distinct `time` values); returns the kept cloud (original order)
    and per-frame counts before and after."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, not {mode!r}")
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"fraction must be in [0, 1], not {fraction}")
    report = PreprocessReport(mode, fraction)
    keep = np.ones(len(cloud), dtype=bool)
    times = np.unique(cloud.time)
    for k, t in enumerate(times):
        idx = np.flatnonzero(cloud.time == t)
        if mode == "stg-isolated" and k > 0:
            keep[idx] = _stg_isolated(cloud.xyz[idx], fraction)
        elif mode == "closest-pairs":
            keep[idx] = _closest_pairs(cloud.xyz[idx], fraction)
        report.per_frame.append({"time": float(t), "before": len(idx), "after": int(keep[idx].sum())})
    return cloud.select(keep), report


def nearest_neighbours(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distance, index) of each point's nearest other point (float64 distances)."""
    tree = cKDTree(np.asarray(xyz, dtype=np.float64))
    dist, index = tree.query(xyz, k=2)
    # A duplicate point may come back as its own first neighbour; the second column is then the
    # duplicate, distance 0, which is what we want either way.
    self_first = index[:, 0] == np.arange(len(xyz))
    nn_index = np.where(self_first, index[:, 1], index[:, 0])
    nn_dist = np.where(self_first, dist[:, 1], dist[:, 0])
    return nn_dist, nn_index


def _stg_isolated(xyz: np.ndarray, fraction: float) -> np.ndarray:
    m = len(xyz)
    if m < 2:
        return np.ones(m, dtype=bool)
    d, _ = nearest_neighbours(xyz)
    num_take = int(fraction * m)
    threshold = np.sort(d)[-num_take]  # num_take == 0 -> s[0], as the official indexing does
    return cast(np.ndarray, d > threshold)


def _closest_pairs(xyz: np.ndarray, fraction: float) -> np.ndarray:
    m = len(xyz)
    keep = np.ones(m, dtype=bool)
    if m < 2:
        return keep
    d, nn = nearest_neighbours(xyz)
    a = np.minimum(np.arange(m), nn)
    b = np.maximum(np.arange(m), nn)
    pairs = np.unique(np.stack([a, b], axis=1), axis=0)
    dist = np.linalg.norm(xyz[pairs[:, 0]].astype(np.float64) - xyz[pairs[:, 1]], axis=1)
    order = np.lexsort((pairs[:, 1], pairs[:, 0], dist))
    selected = pairs[order[: int(fraction * len(pairs))]]
    partners: dict[int, list[int]] = {}
    for p, q in selected:
        partners.setdefault(int(p), []).append(int(q))
        partners.setdefault(int(q), []).append(int(p))
    protected = np.zeros(m, dtype=bool)
    for p, q in selected:
        for victim in (int(q), int(p)):  # larger index first
            if not keep[p] or not keep[q]:
                break  # this pair already lost a member: its survivor is protected
            if protected[victim] or any(not keep[o] for o in partners[victim]):
                continue
            keep[victim] = False
            protected[partners[victim]] = True
            break
    return keep
