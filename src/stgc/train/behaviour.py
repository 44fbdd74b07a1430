"""Changes to what training does with the same options. config.json records the ones its code had
(`behaviour`), so that a run trained before a change that acts on it is never taken for one trained today: the
experiment runner's reuse check names the change instead of reusing the run's numbers.

Add a change here whenever a fix moves the result of some runs without a new option. `acts` answers from the run's
own configs (as `stgc.options.configs_from_run` reads them back, schedule options resolved) whether the change can
move that run; runs it cannot move stay reusable."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from stgc.compaction.config import resolve_schedule as resolve_pruning_schedule
from stgc.train.config import TrainConfig, resolve_schedule

BEHAVIOUR_KEY = "behaviour"


@dataclass(frozen=True)
class BehaviourChange:
    name: str
    what: str  # one line, for the message that refuses to reuse a run
    acts: Callable[[Mapping[str, Any]], bool]


def _rounds_refill_compaction(configs: Mapping[str, Any]) -> bool:
    train, compaction = configs["train"], configs.get("compaction")
    if compaction is None or compaction.method != "st-knn" or not isinstance(train, TrainConfig):
        return False
    densify = train.densify
    if not densify.enabled:
        return False
    if densify.max_growth is None or densify.interval is None or densify.rounds is None:
        return False  # a training records them resolved: this config.json was written by something else
    if not densify.cap(1):
        return False  # no cap, nothing refilled to it
    schedule = resolve_schedule(train)
    pruning = resolve_pruning_schedule(compaction, schedule.iterations)
    return pruning.num_steps > 0 and pruning.iterations()[0] <= schedule.densify_end


def _importance_criterion(configs: Mapping[str, Any]) -> bool:
    compaction = configs.get("compaction")
    return compaction is not None and compaction.method == "st-knn" and compaction.criterion == "importance"


def _pruned_by_weight(configs: Mapping[str, Any]) -> bool:
    compaction = configs.get("compaction")
    return compaction is not None and compaction.method == "st-knn" and compaction.pair_order == "weight"


def _prune_damage_budget(configs: Mapping[str, Any]) -> bool:
    compaction = configs.get("compaction")
    return compaction is not None and compaction.method == "st-knn" and compaction.loss_signal == "prune_damage"


def _slow_start_budget(configs: Mapping[str, Any]) -> bool:
    compaction = configs.get("compaction")
    return (compaction is not None and compaction.method == "st-knn" and compaction.loss_budget_db > 0
            and compaction.ratio_increase == "slow_start")


def _learned_mask(configs: Mapping[str, Any]) -> bool:
    train = configs["train"]
    return isinstance(train, TrainConfig) and train.quantization_aware.iterations > 0 and train.quantization_aware.mask


def _two_view_tracks(configs: Mapping[str, Any]) -> bool:
    data = configs["data"]
    return data.min_track_length < 3 and data.init_source in ("auto", "triangulate")


def _error_guided_sampling(configs: Mapping[str, Any]) -> bool:
    train = configs["train"]
    return isinstance(train, TrainConfig) and train.ems.enabled


CHANGES: tuple[BehaviourChange, ...] = (
    BehaviourChange(
        "compaction-not-refilled",
        "since 2026-11-27 capped clone/split rounds inside the ST-KNN window no longer refill what compaction removed",
        _rounds_refill_compaction,
    ),
    BehaviourChange(
        "importance-every-frame",
        "since 2026-11-28 the importance criterion sums the blending weight over every training frame, not over one "
        "view per camera",
        _importance_criterion,
    ),
    BehaviourChange(
        "ems-candidates-kept",
        "since 2026-11-28 an error-guided sampling candidate stays one after its event (the official loop), so one "
        "camera may make both events",
        _error_guided_sampling,
    ),
    BehaviourChange(
        "pair-weight-ties-closest",
        "since session 35 (2026-11-28) pair_order=weight takes pairs of equal loser weight (many are 0) closest "
        "first, not in array order",
        _pruned_by_weight,
    ),
    BehaviourChange(
        "mask-prices-rotation-index",
        "since session 36 (2026-11-28) the learned mask's price of a Gaussian includes its quaternion's "
        "largest-component index (about 2 bits)",
        _learned_mask,
    ),
    BehaviourChange(
        "unmeasured-prune-damage-backs-off",
        "since session 39 (2026-11-29) a prune whose damage the probe could not measure (a non-finite render after "
        "it) halves the ratio at the next step instead of counting as free",
        _prune_damage_budget,
    ),
    BehaviourChange(
        "slow-start-threshold",
        "since session 40 (2026-11-29) slow start doubles the ratio again after a back-off, up to half the ratio the "
        "back-off started from (it rose one step at a time after the first halving)",
        _slow_start_budget,
    ),
    BehaviourChange(
        "two-view-tracks-kept",
        "since session 36 (2026-11-28) data.min_track_length 2 keeps COLMAP's two-view tracks (it dropped them: "
        "fewer triangulated points)",
        _two_view_tracks,
    ),
)


def recorded_behaviour() -> list[str]:
    """What config.json records: every change this code has."""
    return [change.name for change in CHANGES]


def missing_behaviour(saved: Mapping[str, Any], configs: Mapping[str, Any]) -> list[BehaviourChange]:
    """The changes that act on a run (its configs read back) and that its config.json (`saved`, as read) lacks."""
    have = saved.get(BEHAVIOUR_KEY)
    have = set(have) if isinstance(have, Iterable) and not isinstance(have, (str, bytes)) else set()
    return [change for change in CHANGES if change.name not in have and change.acts(configs)]
