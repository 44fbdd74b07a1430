"""Which Gaussians a pruning step removes (paper section III.2).

The matched pairs are sorted by distance (ascending; equal distances in reference order) and the closest
`ratio` fraction of them is selected (rounded to the nearest count); `compaction.pair_order` may sort them by
another key (`size_relative_distances`, `loser_weights`). From each selected pair one member, the *loser*
chosen by the criterion, is removed and the other, the *keeper*, must survive:

- `timestamp` (paper): the loser has the later most-visible time mu_t;
- `scale`: the loser is the smaller one by volume, the product of its three activated scales (compared as the sum
  of log-scales, which is the same order and cannot overflow);
- `importance`: the loser has less blending weight accumulated over the training views
(the registry of criteria: `compaction.criteria`).
Equal scores: the larger index loses (the older Gaussian of the array survives). A score that is not finite loses.

Pairs can share Gaussians (chains i->j, j->k, or one Gaussian nearest to several). Selected pairs are resolved
greedily in the order they are taken (closest first, or `pair_order`'s key), so the pairs taken first decide.
When a loser is removed, *every* selected pair it belongs to has lost a member, so all its partners in selected
pairs are marked kept. Hence, for each selected pair in order:
- the loser is still free: it is removed and its selected partners are marked kept;
- the loser is kept (a partner of a removed Gaussian): the pair is skipped; removing the keeper instead would go
  against the criterion (and the keeper may itself be kept). When the keeper is removed too (by a pair taken
  before, or by one taken later) the pair has lost a member anyway; when not, it keeps both: a *conflict*;
- the loser is already removed: nothing to do.
So no selected pair loses both members and no kept Gaussian is removed; the removed set is exactly reproducible.
Each removed Gaussian has one keeper, its partner in the pair that removed it (`merge_keeper_opacity` hands it the
loser's opacity when `compaction.merge_opacity` asks for it).
Mutual pairs were merged into one earlier (`matching.match_from_neighbors`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
import torch

from .criteria import CRITERIA, ImportanceFn
from .matching import PairMatches

_FREE, _KEPT, _REMOVED = 0, 1, 2


@dataclass(frozen=True)
class PruneSelection:
    remove: np.ndarray  # [R] int64, sorted indices of the Gaussians to remove
    keepers: np.ndarray  # [R] int64, the keeper of the pair that removed remove[k] (never itself removed)
    selected_pairs: int  # pairs taken by the ratio
    conflicts: int  # selected pairs that keep both: their loser is kept by a pair taken before, their keeper stays
    max_selected_distance: float  # the distance of the farthest selected pair (nan when none)


def removal_scores(
    params: Mapping[str, torch.Tensor], criterion: str, importance: ImportanceFn | None = None
) -> np.ndarray:
    """Per-Gaussian score of the registered `criterion` (`compaction.criteria`); in a selected pair the member with
    the higher score is removed."""
    if criterion not in CRITERIA:
        raise ValueError(f"unknown compaction criterion {criterion!r}; registered: {', '.join(CRITERIA)}")
    with torch.no_grad():
        return CRITERIA[criterion].score(params, importance)


def reference_loses(a: np.ndarray, b: np.ndarray, scores: np.ndarray) -> np.ndarray:
    """For pairs (a[k], b[k]): whether a[k] is the criterion's loser (rules in the module docstring)."""
    score_a, score_b = scores[a], scores[b]
    finite_a, finite_b = np.isfinite(score_a), np.isfinite(score_b)
    # A member whose score is not finite (a diverged scale) loses; comparisons with NaN would keep it by row order.
    return np.where(finite_a & finite_b, (score_a > score_b) | ((score_a == score_b) & (a > b)),
                    np.where(finite_a == finite_b, a > b, ~finite_a))


_LOG_INVISIBLE = float(np.log(1.0 / 255.0))


def keeper_time_coverage(
    pairs: PairMatches, scores: np.ndarray, trbf_center: np.ndarray, trbf_scale: np.ndarray
) -> np.ndarray:
    """Per pair: how present the keeper is while the loser was, in [0, 1].

    STG's temporal opacity factor of a Gaussian is f(t) = exp(-((t - mu_t) / exp(s_t))^2), a bell of standard
    deviation sigma = exp(s_t) / sqrt(2). The coverage is the smallest ratio f_keeper / f_loser (capped at 1) over
    the loser's mu_t and mu_t +- sigma, each clipped to the clip's times [0, 1]: 1 when the two share a lifetime
    or the keeper lives throughout the loser's, near 0 when their lifetimes are disjoint, so that removing the loser
    would leave its frames without either. Times where the loser's factor is below 1/255 (it draws nothing there
    even at full opacity) count as covered. A loser whose temporal parameters are not finite (diverged) has nothing
    to cover: 1; a keeper's that are not: 0."""
    a, b = pairs.reference, pairs.partner
    a_loses = reference_loses(a, b, scores)
    loser, keeper = np.where(a_loses, a, b), np.where(a_loses, b, a)
    centre = np.asarray(trbf_center, dtype=np.float64).reshape(-1)
    log_width = np.asarray(trbf_scale, dtype=np.float64).reshape(-1)
    # Widths beyond e^+-50 behave as a constant or a spike over [0, 1]; bounding them keeps every product finite.
    width = np.exp(np.clip(log_width, -50.0, 50.0))
    spread = width[loser] / np.sqrt(2.0)
    with np.errstate(over="ignore", invalid="ignore"):
        times = np.clip(centre[loser][:, None] + np.array([-1.0, 0.0, 1.0]) * spread[:, None], 0.0, 1.0)
        log_keeper = -np.square((times - centre[keeper][:, None]) / width[keeper][:, None])
        log_loser = -np.square((times - centre[loser][:, None]) / width[loser][:, None])
        # Where the loser's own factor is below 1/255 it draws nothing even at full opacity: nothing to cover there
        # (a loser whose mu_t lies outside the clip has all three times clipped to its edge).
        shortfall = np.where(log_loser < _LOG_INVISIBLE, 0.0, np.minimum(log_keeper - log_loser, 0.0))
        coverage = np.exp(shortfall.min(axis=1))
    finite = np.isfinite(centre) & np.isfinite(log_width)
    return np.where(finite[loser] & finite[keeper], coverage, np.where(finite[loser], 0.0, 1.0))


def select_removals(
    pairs: PairMatches, ratio: float, scores: np.ndarray, max_removals: int | None = None,
    ratio_of: int | None = None, order_by: np.ndarray | Callable[[], np.ndarray] | None = None,
) -> PruneSelection:
    """Gaussians to remove for the first `ratio` fraction of `pairs`, closest first or by `order_by` (rules in the
    module docstring).

    `ratio_of`: the pair count the ratio is a fraction of, when `pairs` is a filtered subset of the matched pairs
    (`keeper_time_coverage`): the step then selects as many pairs as it would unfiltered (at most all of `pairs`),
    so that a filter changes which pairs go, not how fast the model is pruned.
    `order_by`: [P] the key the pairs are taken by, smallest first, instead of their distance (`pair_order`; NaN
    last); equal keys closest first (many losers share the weight 0: unseen from every training view), then in
    reference order. A callable is asked only when the step selects a pair (the weight key costs renders)."""
    n_pairs = len(pairs)
    n_selected = min(n_pairs, int(np.floor(ratio * (n_pairs if ratio_of is None else ratio_of) + 0.5)))
    if n_selected == 0 or (max_removals is not None and max_removals <= 0):
        return PruneSelection(np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), n_selected, 0, float("nan"))
    if callable(order_by):
        order_by = order_by()
    if order_by is None:
        order = np.lexsort((pairs.reference, pairs.distance))[:n_selected]
    else:
        key = np.asarray(order_by, dtype=np.float64)
        if key.shape != (n_pairs,):
            raise ValueError(f"order_by has shape {key.shape}; expected one key per pair ({n_pairs},)")
        order = np.lexsort((pairs.reference, pairs.distance, key))[:n_selected]
    a, b = pairs.reference[order], pairs.partner[order]
    a_loses = reference_loses(a, b, scores)
    losers = np.where(a_loses, a, b).tolist()
    keepers = np.where(a_loses, b, a).tolist()

    # Selected partners of every Gaussian (CSR): a removal marks all of them kept.
    ends = np.concatenate([a, b])
    others = np.concatenate([b, a])
    by_end = np.argsort(ends, kind="stable")
    partners = others[by_end].tolist()
    offsets = np.searchsorted(ends[by_end], np.arange(scores.shape[0] + 1)).tolist()

    state = bytearray(scores.shape[0])
    removed: list[int] = []
    removed_for: list[int] = []  # the keeper of each removal's pair
    limit = n_selected if max_removals is None else max_removals
    skipped: list[int] = []  # keepers of the pairs whose loser was kept
    for loser, keeper in zip(losers, keepers):
        if state[loser] == _KEPT:
            skipped.append(keeper)
        elif state[loser] == _FREE:
            if len(removed) >= limit:
                break
            state[loser] = _REMOVED
            removed.append(loser)
            removed_for.append(keeper)
            for partner in partners[offsets[loser] : offsets[loser + 1]]:
                state[partner] = _KEPT
    conflicts = sum(state[keeper] != _REMOVED for keeper in skipped)  # a later pair may still remove a keeper
    by_index = np.argsort(np.asarray(removed, dtype=np.int64))
    return PruneSelection(
        remove=np.asarray(removed, dtype=np.int64)[by_index],
        keepers=np.asarray(removed_for, dtype=np.int64)[by_index],
        selected_pairs=n_selected,
        conflicts=conflicts,
        max_selected_distance=float(np.max(pairs.distance[order])),
    )


def merge_keeper_opacity(opacity_logit: torch.Tensor, remove: np.ndarray, keepers: np.ndarray) -> None:
    """In place: each keeper's base opacity sigmoid(o) becomes the union 1 - (1 - a_keeper) * prod(1 - a_loser) over
    the losers it keeps (`PruneSelection.keepers`), what the pair composites to where both are drawn at full
    strength (their centre, for near duplicates). The result is held below 1 so that its logit stays finite, and
    never below the keeper's own (a keeper more opaque than that bound keeps its logit)."""
    if remove.size == 0:
        return
    with torch.no_grad():
        flat = opacity_logit.view(-1)
        # log(1 - sigmoid(o)) = -softplus(o): exact for opaque Gaussians, where 1 - sigmoid(o) underflows.
        log_clear = -torch.nn.functional.softplus(flat.double())
        keeper_rows = torch.from_numpy(keepers).to(flat.device)
        merged = log_clear.index_add(0, keeper_rows, log_clear[torch.from_numpy(remove).to(flat.device)])
        touched = torch.unique(keeper_rows)
        clear = merged[touched].exp().clamp_min(1e-6)
        union = torch.log1p(-clear).sub(torch.log(clear)).to(flat.dtype)
        flat[touched] = torch.maximum(flat[touched], union)


def size_relative_distances(pairs: PairMatches, log_scaling: np.ndarray, scene_extent: float) -> np.ndarray:
    """[P] each pair's distance over its size (`pair_order = size`): the sum of its two Gaussians' largest activated
    scale exp(s), over the scene extent as the distance's positions are. For the positions alone 1 is two spheres of
    those radii touching and a Gaussian inside its neighbour is below it; the rotation term is divided too (for small
    Gaussians it dominates). A non-finite scale makes the pair's value NaN, which sorts last."""
    largest = np.exp(np.max(np.asarray(log_scaling, dtype=np.float64).reshape(len(log_scaling), -1), axis=1))
    with np.errstate(over="ignore", invalid="ignore"):
        size = (largest[pairs.reference] + largest[pairs.partner]) / float(scene_extent)
        return np.where(np.isfinite(size) & (size > 0), pairs.distance / size, np.nan)


def loser_weights(pairs: PairMatches, scores: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """[P] the blending weight of each pair's loser (the member `scores` removes; `weights` [N] per Gaussian, summed
    over the training views), for `pair_order = weight`: the pairs whose removal takes least of what the views show
    go first. A non-finite weight is NaN, which sorts last."""
    losers = np.where(reference_loses(pairs.reference, pairs.partner, scores), pairs.reference, pairs.partner)
    values = np.asarray(weights, dtype=np.float64).reshape(-1)
    if values.size != scores.shape[0]:
        raise ValueError(f"{values.size} blending weights for {scores.shape[0]} Gaussians")
    picked = values[losers]
    return np.where(np.isfinite(picked), picked, np.nan)
