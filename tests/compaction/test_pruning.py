"""Pruning rules: the criteria remove the right member, pair conflicts resolve deterministically, counts follow ratio."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from stgc.compaction import PairMatches, removal_scores, select_removals
from stgc.compaction.pruning import keeper_time_coverage
from stgc.compaction.matching import match_from_neighbors
from stgc.model import STGModel

from .compaction_helpers import make_model, paper_rule, static_params


def _pairs(ref, part, dist) -> PairMatches:
    return PairMatches(np.asarray(ref, np.int64), np.asarray(part, np.int64), np.asarray(dist, float), len(ref))


def test_timestamp_criterion_removes_the_later_mu_t():
    params = static_params(np.zeros((4, 3)), trbf_center=np.array([0.7, 0.2, 0.1, 0.9]))
    scores = removal_scores(params, "timestamp")
    sel = select_removals(_pairs([0, 2], [1, 3], [0.1, 0.2]), 1.0, scores)
    assert sel.remove.tolist() == [0, 3]


def test_scale_criterion_removes_the_smaller_volume_not_the_smaller_max_axis():
    params = static_params(np.zeros((2, 3)))
    # Gaussian 0: a needle (max axis 1.0, volume 1e-4); Gaussian 1: a ball (max axis 0.1, volume 1e-3).
    params["scaling"] = torch.log(torch.tensor([[1.0, 0.01, 0.01], [0.1, 0.1, 0.1]]))
    sel = select_removals(_pairs([0], [1], [0.1]), 1.0, removal_scores(params, "scale"))
    assert sel.remove.tolist() == [0]


def test_importance_criterion_removes_the_less_important_and_needs_the_function():
    params = static_params(np.zeros((4, 3)))
    weights = torch.tensor([5.0, 1.0, 0.5, 2.0])
    sel = select_removals(_pairs([0, 2], [1, 3], [0.1, 0.2]), 1.0, removal_scores(params, "importance", lambda: weights))
    assert sel.remove.tolist() == [1, 2]
    with pytest.raises(ValueError, match="importance_fn"):
        removal_scores(params, "importance", None)
    with pytest.raises(ValueError, match="3 values for 4"):
        removal_scores(params, "importance", lambda: weights[:3])


def test_equal_scores_remove_the_larger_index():
    sel = select_removals(_pairs([5, 1], [2, 9], [0.1, 0.2]), 1.0, np.zeros(10))
    assert sel.remove.tolist() == [5, 9]


def test_ratio_selects_the_closest_pairs():
    # 10 disjoint pairs (2k, 2k+1) with shuffled distances; the loser is always the odd member.
    rng = np.random.default_rng(0)
    dist = rng.permutation(10) / 10.0
    pairs = _pairs(np.arange(0, 20, 2), np.arange(1, 20, 2), dist)
    scores = np.tile([0.0, 1.0], 10)
    sel = select_removals(pairs, 0.3, scores)
    closest = np.argsort(dist)[:3]
    assert sel.selected_pairs == 3
    assert sel.remove.tolist() == sorted((2 * closest + 1).tolist())
    assert sel.max_selected_distance == pytest.approx(np.sort(dist)[2])
    assert select_removals(pairs, 0.04, scores).selected_pairs == 0  # 0.4 pairs rounds to none
    assert select_removals(pairs, 0.05, scores).selected_pairs == 1  # 0.5 rounds up
    assert select_removals(pairs, 1.0, scores, max_removals=4).remove.size == 4


def test_chain_resolution_closest_pair_decides():
    # Chain 0-1 (d .1), 1-2 (d .2), 2-3 (d .3), 3-4 (d .4); later timestamps lose: mu_t = index.
    scores = np.arange(6, dtype=float)
    sel = select_removals(_pairs([0, 1, 2, 3], [1, 2, 3, 4], [0.1, 0.2, 0.3, 0.4]), 1.0, scores)
    # 0-1: remove 1; its partners 0 and 2 are kept. 1-2: loser 2 is kept, skipped (else both would go); the pair
    # has lost 1 already. 2-3: remove 3; 2 and 4 kept. 3-4: loser 4 is kept, skipped; the pair has lost 3.
    assert sel.remove.tolist() == [1, 3]
    assert sel.conflicts == 0  # every selected pair lost a member
    # A kept Gaussian is never removed by a farther pair.
    scores = np.array([1.0, 0.0, 2.0])  # 0 loses to 1, 2 loses to 0
    sel = select_removals(_pairs([1, 0], [0, 2], [0.1, 0.2]), 1.0, scores)
    assert sel.remove.tolist() == [0]  # (1,0) removes 0, so 1 and 2 are kept; (0,2) cannot remove 2
    scores = np.array([0.0, 1.0, 2.0])  # 0 wins against both 1 and 2
    sel = select_removals(_pairs([0, 0], [1, 2], [0.1, 0.2]), 1.0, scores)
    assert sel.remove.tolist() == [1, 2]  # one Gaussian may absorb several neighbours
    scores = np.array([1.0, 0.0, 0.5])
    sel = select_removals(_pairs([1, 0], [2, 2], [0.1, 0.2]), 1.0, scores)
    # (1,2) d .1: 2 loses (0.5 > 0.0); its partners 1 and 0 are kept. (0,2) d .2: loser 0 is kept, skipped; the
    # pair has lost 2.
    assert sel.remove.tolist() == [2] and sel.conflicts == 0
    scores = np.array([1.0, 2.0, 0.0])
    sel = select_removals(_pairs([0, 0], [1, 2], [0.1, 0.2]), 1.0, scores)
    # (0,1): 1 loses, 0 is kept. (0,2): loser 0 is kept and keeper 2 stays: the pair keeps both, a conflict.
    assert sel.remove.tolist() == [1] and sel.conflicts == 1


@pytest.mark.parametrize("seed", range(4))
def test_random_pair_sets_never_lose_both_members_or_a_keeper(seed):
    rng = np.random.default_rng(seed)
    n = 300
    nn = rng.integers(0, n, size=n)
    nn[nn == np.arange(n)] = (nn[nn == np.arange(n)] + 1) % n
    dist = rng.random(n)
    pairs = match_from_neighbors([nn, nn], [dist, dist])
    scores = rng.random(n)
    sel = select_removals(pairs, 0.6, scores)
    removed = np.zeros(n, bool)
    removed[sel.remove] = True
    order = np.lexsort((pairs.reference, pairs.distance))[: sel.selected_pairs]
    a, b = pairs.reference[order], pairs.partner[order]
    assert not np.any(removed[a] & removed[b])
    assert sel.conflicts == int(np.sum(~removed[a] & ~removed[b]))  # the selected pairs that kept both members
    assert sel.remove.size + sel.conflicts <= sel.selected_pairs
    assert sel.remove.size > 0 and sel.conflicts > 0
    # Every removal was the loser of some selected pair whose other member survived.
    loser = np.where((scores[a] > scores[b]) | ((scores[a] == scores[b]) & (a > b)), a, b)
    keeper = np.where(loser == a, b, a)
    for r in sel.remove:
        assert np.any((loser == r) & ~removed[keeper])
    # Deterministic.
    np.testing.assert_array_equal(sel.remove, select_removals(pairs, 0.6, scores).remove)


def test_mutual_pairs_are_merged_once():
    nn = np.array([1, 0, 3, 1])
    dist = np.array([0.5, 0.5, 0.2, 0.3])
    pairs = match_from_neighbors([nn, nn], [dist, dist])
    assert list(zip(pairs.reference.tolist(), pairs.partner.tolist())) == [(0, 1), (2, 3), (3, 1)]
    # A reference whose searches disagree is dropped.
    pairs = match_from_neighbors([nn, np.array([1, 0, 0, 1])], [dist, dist])
    assert list(zip(pairs.reference.tolist(), pairs.partner.tolist())) == [(0, 1), (3, 1)]


def test_a_registered_criterion_reaches_the_config_and_the_scores():
    from stgc.compaction.criteria import CRITERIA, register_criterion

    @register_criterion("first-index", "the member with the smaller index (a test criterion)")
    def _first(params, importance):
        return -np.arange(params["xyz"].shape[0], dtype=np.float64)

    try:
        paper_rule(criterion="first-index").validate()
        params = {"xyz": torch.zeros(4, 3)}
        sel = select_removals(_pairs([0, 2], [1, 3], [0.1, 0.2]), 1.0, removal_scores(params, "first-index"))
        assert sel.remove.tolist() == [0, 2]
        with pytest.raises(ValueError, match="already registered"):
            register_criterion("first-index", "again")(_first)
    finally:
        CRITERIA.pop("first-index")
    with pytest.raises(ValueError, match="first-index"):
        paper_rule(criterion="first-index").validate()


def test_a_member_whose_score_is_not_finite_is_the_one_removed():
    # Under `scale` a diverged (NaN) scale compared False both ways, so row order decided: the finite row could go.
    scores = np.array([np.nan, 1.0, 2.0, np.inf, np.nan, np.nan])
    sel = select_removals(_pairs([0, 2, 4], [1, 3, 5], [0.1, 0.2, 0.3]), 1.0, scores)
    assert sel.remove.tolist() == [0, 3, 5]  # NaN loses, inf loses, two NaN: the larger index, as equal scores


def _lifetimes(centres, widths) -> tuple[np.ndarray, np.ndarray]:
    """trbf_center and trbf_scale (log of STG's temporal width) for the given centres and widths."""
    return np.asarray(centres, float)[:, None], np.log(np.asarray(widths, float))[:, None]


def test_keeper_time_coverage_is_the_keepers_presence_over_the_losers_lifetime():
    # Pairs (0, 1) .. (8, 9); the timestamp criterion removes the later centre, here always the odd member.
    centre, scale = _lifetimes(
        [0.5, 0.5, 0.4, 0.5, 0.9, 0.95, 0.1, 0.9, 0.5, 0.6],
        [0.1, 0.1, 0.1, 0.1 * np.sqrt(2), 0.1, 0.1 * np.sqrt(2), 0.05, 0.05, 50.0, 0.02],
    )
    scores = centre[:, 0]
    pairs = _pairs([0, 2, 4, 6, 8], [1, 3, 5, 7, 9], [0.1] * 5)
    coverage = keeper_time_coverage(pairs, scores, centre, scale)
    # The keeper's bell over the loser's at the loser's mu_t and mu_t +- sigma (sigma = width / sqrt 2; there the
    # loser's own factor is exp(-1/2)), capped at 1. One lifetime: 1. Loser 0.5 +- 0.1, keeper at 0.4 of width 0.1:
    # at 0.6, exp(-4) / exp(-1/2). Loser 0.95 +- 0.1 is clipped at the clip's end 1.0: exp(-1) / exp(-1/8), not
    # the exp(-2.25) / exp(-1/2) of 1.05. Disjoint lifetimes: ~0. A keeper that lives throughout: ~1.
    sigma_last = 0.05 / np.sqrt(2)
    expected = [1.0, np.exp(-3.5), np.exp(-0.875), np.exp(-((0.8 + sigma_last) / 0.05) ** 2 + 0.5),
                np.exp(-((0.6 - 0.5) / 50.0) ** 2)]
    np.testing.assert_allclose(coverage, expected, rtol=1e-12, atol=1e-300)
    # The loser decides whose lifetime counts: with the criterion reversed, the narrow member 9 keeps and its
    # bell does not cover the wide member 8's lifetime.
    reversed_coverage = keeper_time_coverage(pairs, -scores, centre, scale)
    assert reversed_coverage[4] < 1e-100 and reversed_coverage[0] == 1.0
    # A diverged loser has nothing to cover (its pair is pruned); a diverged keeper covers nothing.
    scale[3, 0], scale[4, 0] = np.nan, np.inf
    assert keeper_time_coverage(pairs, scores, centre, scale)[1:3].tolist() == [1.0, 0.0]
    # Extreme but finite widths: a loser present throughout [0, 1] against a narrow keeper, and the reverse.
    centre, scale = np.full((4, 1), 0.5), np.array([[np.log(1e-3)], [800.0], [800.0], [np.log(1e-3)]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        extreme = keeper_time_coverage(_pairs([0, 2], [1, 3], [0.1, 0.1]), np.array([0.0, 1.0, 0.0, 1.0]), centre,
                                       scale)
    assert extreme[0] == 0.0 and extreme[1] == 1.0
    # A loser centred outside the clip is invisible within it (a factor of e^-100 at the clip's end, its three times
    # clipped there): nothing to cover, whatever the keeper; a just-visible one is still judged.
    centre, scale = _lifetimes([0.2, 1.5, 0.2, 1.1], [0.05, 0.05, 0.05, 0.05])
    outside = keeper_time_coverage(_pairs([0, 2], [1, 3], [0.1, 0.1]), centre[:, 0], centre, scale)
    assert outside[0] == 1.0 and outside[1] < 1e-100


def test_pairs_whose_keeper_does_not_cover_the_losers_lifetime_are_not_pruned():
    from stgc.compaction import STKNNCompactor

    from .compaction_helpers import make_model

    # Four pairs, each much closer than any other Gaussian: two of disjoint lifetimes (the closest two, at 1e-4)
    # and two that share one (1e-3).
    corners = np.array([[0.0, 0.0, 0.0], [0.5, 0.5, 0.5], [0.0, 0.5, 0.0], [0.5, 0.0, 0.5]])
    xyz = np.repeat(corners, 2, axis=0) + np.array([[0.0, 0.0, 0.0], [1e-4, 0.0, 0.0]] * 2 + [[0.0, 0.0, 0.0], [1e-3, 0.0, 0.0]] * 2)
    centres = np.array([0.2, 0.8, 0.25, 0.75, 0.5, 0.5, 0.4, 0.4])
    params = static_params(xyz, trbf_center=centres)
    params["trbf_scale"][:] = float(np.log(0.05))
    kept = {}
    for ratio, coverage in ((1.0, 0.0), (1.0, 0.5), (0.5, 0.0), (0.5, 0.5)):
        config = paper_rule(case=0, window_start=0.0, window_end=1.0, interval=1, ratio_init=ratio,
                                  ratio_min=ratio, ratio_max=ratio, keeper_time_coverage=coverage)
        model = make_model({k: v.clone() for k, v in params.items()})
        event = STKNNCompactor(config, 10).step(1, 0.5, model, 1.0)
        assert event["matched_pairs"] == 4 and event["time_covered_pairs"] == (4 if coverage == 0 else 2)
        # The ratio is a fraction of every matched pair, filtered or not: the filter changes which pairs go.
        assert event["selected_pairs"] == (4 if (ratio, coverage) == (1.0, 0.0) else 2)
        kept[ratio, coverage] = sorted(model.params["trbf_center"][:, 0].tolist())
    assert kept[1.0, 0.0] == pytest.approx([0.2, 0.25, 0.4, 0.5])  # the paper: the later member of each pair goes
    assert kept[0.5, 0.0] == pytest.approx([0.2, 0.25, 0.4, 0.4, 0.5, 0.5])  # the closest half: the disjoint pairs
    # With the filter the disjoint pairs keep both members, and half of all pairs is still two pairs: the two
    # that share a lifetime.
    assert kept[1.0, 0.5] == kept[0.5, 0.5] == pytest.approx([0.2, 0.25, 0.4, 0.5, 0.75, 0.8])
    with pytest.raises(ValueError, match="keeper_time_coverage"):
        paper_rule(keeper_time_coverage=float("nan")).validate()


def test_each_removal_names_the_keeper_of_the_pair_that_removed_it():
    # The chain of test_chain_resolution_closest_pair_decides: 1 goes for 0, 3 for 2.
    sel = select_removals(_pairs([0, 1, 2, 3], [1, 2, 3, 4], [0.1, 0.2, 0.3, 0.4]), 1.0, np.arange(6, dtype=float))
    assert sel.remove.tolist() == [1, 3] and sel.keepers.tolist() == [0, 2]
    # One keeper absorbing two neighbours, listed in removal-index order whatever the pair order.
    sel = select_removals(_pairs([4, 4], [0, 2], [0.1, 0.2]), 1.0, np.array([3.0, 0.0, 2.0, 0.0, 1.0]))
    assert sel.remove.tolist() == [0, 2] and sel.keepers.tolist() == [4, 4]
    assert select_removals(_pairs([0], [1], [0.1]), 0.0, np.zeros(2)).keepers.size == 0


def test_merged_opacity_is_the_union_of_the_keeper_and_its_losers():
    from stgc.compaction.pruning import merge_keeper_opacity

    alphas = torch.tensor([0.5, 0.5, 0.5, 0.2, 0.9, 0.3], dtype=torch.float64)
    logits = torch.logit(alphas).float().reshape(-1, 1)
    logits[4] = 40.0  # sigmoid(40) rounds to 1 in float32: the union must stay opaque and finite
    merge_keeper_opacity(logits, np.array([1, 2, 5]), np.array([0, 0, 4]))
    merged = torch.sigmoid(logits[:, 0].double())
    assert merged[0].item() == pytest.approx(1 - 0.5 ** 3, rel=1e-6)  # 0.875: the keeper and its two losers
    assert merged[3].item() == pytest.approx(0.2, rel=1e-6)  # not a keeper: untouched
    assert torch.isfinite(logits).all() and logits[4, 0].item() == 40.0  # held, not lowered to the bound's 13.8
    unchanged = logits.clone()
    merge_keeper_opacity(logits, np.zeros(0, np.int64), np.zeros(0, np.int64))
    assert torch.equal(logits, unchanged)


def test_merged_opacity_keeps_what_a_pair_of_duplicates_rendered():
    """A model of exact duplicate pairs loses one of each: with merge_opacity the keeper's union opacity draws
    the pair's coverage again (exactly at its centre, nearly around it); without, half-opaque splats thin out."""
    from model.helpers import look_at_camera, point_cloud

    from stgc.compaction import STKNNCompactor

    single = STGModel.from_points(point_cloud(40, seed=3), variant="lite")
    with torch.no_grad():
        single.params["opacity"].fill_(0.0)  # a = 0.5: a pair composites to 0.75 at its centre
        single.params["scaling"].add_(1.0)
    doubled = make_model({k: torch.cat([v.detach(), v.detach()]) for k, v in single.params.items()},
                         single.scene_extent)
    camera = look_at_camera(width=48, height=32, time=0.5)
    with torch.no_grad():
        target = doubled.render(camera).rgb
    errors = {}
    for merge in (False, True):
        config = paper_rule(case=0, window_start=0.0, window_end=1.0, interval=1, ratio_init=1.0,
                                  ratio_min=1.0, ratio_max=1.0, merge_opacity=merge)
        model = make_model({k: v.clone() for k, v in doubled.params.items()}, doubled.scene_extent)
        event = STKNNCompactor(config, 10).step(1, 0.5, model, 1.0)
        assert event["removed"] == 40 and model.num_gaussians == 40
        with torch.no_grad():
            errors[merge] = float((model.render(camera).rgb - target).square().mean())
    assert errors[True] < 0.2 * errors[False]


def test_size_order_takes_overlapping_gaussians_before_small_close_neighbours():
    """Two pairs: small Gaussians 0.01 apart (fine detail) and large ones 0.02 apart (one inside the other). The
    paper's order takes the closer small pair first; the size order the overlapping large pair."""
    from stgc.compaction import STKNNCompactor
    from stgc.compaction.pruning import size_relative_distances

    xyz = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.5, 0.5, 0.5], [0.52, 0.5, 0.5]])
    params = static_params(xyz, trbf_center=np.array([0.4, 0.6, 0.4, 0.6]))
    params["scaling"][:2] = float(np.log(0.002))  # radius 0.002: 0.01 apart is 2.5 sizes
    params["scaling"][2:] = float(np.log(0.1))  # radius 0.1: 0.02 apart is 0.1 size
    params["scaling"][2, 1] = float(np.log(0.2))  # the largest axis counts
    relative = size_relative_distances(_pairs([0, 2], [1, 3], [0.01, 0.02]), params["scaling"].numpy(), 1.0)
    np.testing.assert_allclose(relative, [0.01 / 0.004, 0.02 / 0.3])
    np.testing.assert_allclose(size_relative_distances(_pairs([0], [1], [0.01]), params["scaling"].numpy(), 2.0),
                               [0.01 / 0.002])  # sizes over the scene extent, as positions are
    kept = {}
    for order in ("distance", "size"):
        config = paper_rule(case=0, window_start=0.0, window_end=1.0, interval=1, ratio_init=0.5,
                                  ratio_min=0.5, ratio_max=0.5, pair_order=order)
        model = make_model({k: v.clone() for k, v in params.items()})
        event = STKNNCompactor(config, 10).step(1, 0.5, model, 1.0)
        assert event["matched_pairs"] == 2 and event["removed"] == 1
        kept[order] = model.params["xyz"][:, 0].tolist()
        # The log names the selected pair's distance, whatever order took it.
        assert event["max_selected_distance"] == pytest.approx(0.01 if order == "distance" else 0.02, rel=1e-3)
    assert kept["distance"] == pytest.approx([0.0, 0.5, 0.52])  # the small pair lost its later member
    assert kept["size"] == pytest.approx([0.0, 0.01, 0.5])  # the overlapping pair did
    scaling = params["scaling"].numpy().copy()
    scaling[3] = np.nan
    assert np.isnan(size_relative_distances(_pairs([0, 2], [1, 3], [0.01, 0.02]), scaling, 1.0)[1])


def test_weight_order_takes_the_pair_whose_loser_shows_least():
    """Two pairs: the closer one's loser (the later mu_t) carries much blending weight, the farther one's little. The
    paper's order removes the closer pair's loser; the weight order the farther pair's. Both the importance criterion
    and the weight order in one step render the weights once."""
    from stgc.compaction import STKNNCompactor
    from stgc.compaction.pruning import loser_weights

    xyz = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.5, 0.5, 0.5], [0.52, 0.5, 0.5]])
    params = static_params(xyz, trbf_center=np.array([0.4, 0.6, 0.4, 0.6]))
    weights = np.array([1.0, 5.0, 1.0, 0.5])
    scores = params["trbf_center"].numpy().reshape(-1)
    np.testing.assert_allclose(loser_weights(_pairs([0, 2], [1, 3], [0.01, 0.02]), scores, weights), [5.0, 0.5])
    np.testing.assert_allclose(loser_weights(_pairs([1, 3], [0, 2], [0.01, 0.02]), scores, weights), [5.0, 0.5])
    assert np.isnan(loser_weights(_pairs([0], [1], [0.01]), scores, np.array([1.0, np.inf, 1.0, 1.0]))[0])
    with pytest.raises(ValueError, match="3 blending weights for 4"):
        loser_weights(_pairs([0], [1], [0.01]), scores, weights[:3])
    kept = {}
    for order, criterion in (("distance", "timestamp"), ("weight", "timestamp"), ("weight", "importance")):
        config = paper_rule(case=0, window_start=0.0, window_end=1.0, interval=1, ratio_init=0.5,
                                  ratio_min=0.5, ratio_max=0.5, pair_order=order, criterion=criterion)
        model = make_model({k: v.clone() for k, v in params.items()})
        calls = []

        def importance() -> torch.Tensor:
            calls.append(1)
            return torch.from_numpy(weights.copy())

        event = STKNNCompactor(config, 10).step(1, 0.5, model, 1.0, importance_fn=importance)
        assert event["removed"] == 1
        assert len(calls) == (0 if order == "distance" else 1)
        kept[order, criterion] = model.params["xyz"][:, 0].tolist()
    assert kept["distance", "timestamp"] == pytest.approx([0.0, 0.5, 0.52])
    assert kept["weight", "timestamp"] == pytest.approx([0.0, 0.01, 0.5])  # the farther pair's faint loser went
    assert kept["weight", "importance"] == pytest.approx([0.0, 0.01, 0.5])  # (there it is the criterion's loser too)
    # Equal weights (losers no training view shows): the closest pair first, not the first in the array.
    unseen = np.array([1.0, 0.0, 1.0, 0.0])
    selection = select_removals(_pairs([0, 2], [1, 3], [0.5, 0.001]), 0.5, scores,
                                order_by=loser_weights(_pairs([0, 2], [1, 3], [0.5, 0.001]), scores, unseen))
    assert selection.remove.tolist() == [3] and selection.max_selected_distance == pytest.approx(0.001)
    # A step that selects nothing renders nothing.
    config = paper_rule(case=0, window_start=0.0, window_end=1.0, interval=1, ratio_init=0.001,
                              ratio_min=0.001, ratio_max=0.001, pair_order="weight")
    calls.clear()
    event = STKNNCompactor(config, 10).step(1, 0.5, make_model({k: v.clone() for k, v in params.items()}), 1.0,
                                            importance_fn=importance)
    assert event["selected_pairs"] == 0 and event["removed"] == 0 and calls == []
    config = paper_rule(case=0, window_start=0.0, window_end=1.0, interval=1, ratio_init=0.5, ratio_min=0.5,
                              ratio_max=0.5, pair_order="weight")
    with pytest.raises(ValueError, match="need importance_fn"):
        STKNNCompactor(config, 10).step(1, 0.5, make_model({k: v.clone() for k, v in params.items()}), 1.0)
