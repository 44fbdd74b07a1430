"""Configuration and pruning schedule of the spatiotemporal KNN compaction.

The paper (30k iterations, pruning every 100) defines four pruning windows that all start at 6k and end at 12k, 16k,
20k or 24k. They are stored here as fractions of the total so that a shorter CPU schedule scales them, and the
interval is scaled by the same factor (100/30000 of the total), so every case keeps the paper's number of pruning
steps (60, 100, 140, 180) and the adaptive ratio controller sees the same number of decisions. That is exact when
the total is a multiple of 300, as in both presets (9,000 and 30,000). Otherwise the interval is rounded to whole
iterations and the count moves by a few percent: 5,000 iterations give 59/99/138/177 steps, 1,000 give
67/111/156/200, and very short runs, whose interval cannot drop below 1, give fewer.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar, Literal, get_args

from .criteria import CRITERIA, criteria_help

PAPER_ITERATIONS = 30_000
PAPER_INTERVAL = 100

# case -> (window start, window end) as fractions of the total iterations (paper: 6k-12k/16k/20k/24k of 30k).
CASE_WINDOWS: dict[int, tuple[float, float]] = {
    1: (6_000 / PAPER_ITERATIONS, 12_000 / PAPER_ITERATIONS),
    2: (6_000 / PAPER_ITERATIONS, 16_000 / PAPER_ITERATIONS),
    3: (6_000 / PAPER_ITERATIONS, 20_000 / PAPER_ITERATIONS),
    4: (6_000 / PAPER_ITERATIONS, 24_000 / PAPER_ITERATIONS),
}

Method = Literal["none", "st-knn", "reference"]
METHODS = get_args(Method)
SMOOTHINGS = ("window_mean", "ema")
LossSignal = Literal["training", "probe", "probe_psnr", "prune_damage"]
# The signals rendered on the fixed probe set, and those of them a reference run's log can be held against.
PROBE_SIGNALS = ("probe", "probe_psnr", "prune_damage")
REFERENCE_SIGNALS = ("probe", "probe_psnr")
LOSS_SIGNALS = get_args(LossSignal)
RatioIncrease = Literal["additive", "slow_start"]
RATIO_INCREASES = get_args(RatioIncrease)


# The paper's rule as written (Sec. III.2): the closest pairs first, the smoothed training loss compared step to step,
# the ratio within 0.1-2 %. The defaults were these until session 37; `stgc train --set compaction.<key>=<value>` for
# each, or `replace(CompactionConfig(...), **PAPER_RULE)`, trains it.
PAPER_RULE: dict[str, Any] = {"pair_order": "distance", "loss_signal": "training", "loss_budget_db": 0.0,
                              "ratio_max": 0.02, "removal_rate_max": 0.0, "reset_settle_steps": 0}


@dataclass(frozen=True)
class CompactionConfig:
    """Spatiotemporal KNN pruning during training with a rendering-loss-adaptive pruning ratio."""

    method: Method = field(
        default="st-knn",
        metadata={
            "help": "'none' trains without compaction; 'st-knn' prunes matched pairs; 'reference' prunes nothing but "
            "records the probe loss at every pruning iteration of the schedule (the unpruned run that another run's "
            "loss_reference names)"
        },
    )
    case: int = field(
        default=2,
        metadata={
            "help": "pruning window preset (paper, of 30k): 1 = 6k-12k, 2 = 6k-16k, 3 = 6k-20k, 4 = 6k-24k, scaled "
            "to the run's total; 0 = use window_start/window_end"
        },
    )
    window_start: float = field(
        default=0.2, metadata={"help": "first pruning iteration as a fraction of the total (only with case 0)"}
    )
    window_end: float = field(
        default=0.4, metadata={"help": "pruning stops before this fraction of the total (only with case 0)"}
    )
    interval: int = field(
        default=0,
        metadata={"help": "iterations between pruning steps; 0 = total/300 (the paper's 100 of 30k), at least 1"},
    )
    criterion: str = field(
        default="timestamp",
        metadata={"help": "which member of a selected pair is removed: " + criteria_help()},
    )
    ratio_init: float = field(
        default=0.005, metadata={"help": "fraction of the matched pairs (in pair_order) pruned at the first step "
                                          "(the paper's rule; the prune_damage budget and a loss_reference raise it "
                                          "once before the first prune)"}
    )
    ratio_step: float = field(
        default=0.001, metadata={"help": "ratio change per step: minus when the smoothed loss rose, plus when it fell "
                                         "(with a damage budget: plus within it, or doubled with ratio_increase "
                                         "slow_start; over it the ratio halves)"}
    )
    ratio_min: float = field(default=0.001, metadata={"help": "lower bound of the pruning ratio"})
    ratio_max: float = field(default=0.5, metadata={"help": "upper bound of the pruning ratio (the paper's rule: "
                                                            "0.02; 0.05 until session 42, when removal_rate_max took "
                                                            "over pacing the prunes)"})
    ratio_increase: RatioIncrease = field(
        default="slow_start",
        metadata={
            "help": "how the damage budget (loss_budget_db > 0) raises the ratio while within it: 'additive' = one "
            "ratio_step per step; 'slow_start' = doubled (at least one step) until the budget first halves it; after "
            "each back-off it doubles again up to half the ratio the back-off started from, then rises one step at a "
            "time (TCP's slow start and threshold; since session 40: session 39's rule stepped after the first "
            "halving). The default since session 42 (additive before), paced by removal_rate_max and held by "
            "reset_settle_steps and prune_trials: benchmarks/RESULTS.md, sessions 39-42"
        },
    )
    removal_rate_max: float = field(
        default=0.002,
        metadata={
            "help": "the most a pruning step may remove, as a share of the model's Gaussians per training iteration "
            "since the previous step (times the interval: 0.001 is 3 in 100 per step at the cpu preset's interval of "
            "30, 1 in 200 at the demo's 5): what a prune takes, training must make good before the next one, so the cap "
            "counts iterations, not steps (at least one Gaussian a step); where it binds the ratio is lowered to the "
            "cap's share of the matched pairs (logged as the step's ratio, even below ratio_min; conflicts between "
            "pairs leave the removals at 65-90 percent of the cap). 0 = no cap (the paper; the default until session 42)"
        },
    )
    reset_settle_steps: int = field(
        default=10,
        metadata={
            "help": "pruning steps after an opacity reset (train.densify.opacity_reset_interval) that prune nothing, "
            "while the opacities grow back: right after a reset every opacity is at most opacity_reset_value, so the "
            "blending weights (pair_order weight, the importance criterion) rank the Gaussians by their size instead "
            "of by what they show, and the probe cannot see what a prune takes (the official schedule resets at 6k, "
            "the first iteration of every case's window). The steps count toward the damage budget's spread; the "
            "ratio waits. 0 = prune from the first step (paper; the default until session 42)"
        },
    )
    prune_trials: int = field(
        default=3,
        metadata={
            "help": "with loss_signal prune_damage: each step's prune is rendered on the probe views before it is "
            "applied (the pruned Gaussians' opacity masked to 0, a render equal to the pruned model's), and one that "
            "would take the summed damage over the allowance, this step's share included, is not applied: the ratio "
            "halves (a back-off, as an overshoot would have caused) and the step tries the smaller selection, up to "
            "this many renders, then prunes nothing. The steps' unspent allowance carries over as before. 0 = the "
            "prune is applied and measured after it, an overshoot paid back by the next steps' back-offs (how stgc "
            "pruned until session 42)"
        },
    )
    loss_tolerance: float = field(
        default=0.0,
        metadata={"help": "relative loss change treated as 'no change' (ratio kept); 0 = paper (any change counts)"},
    )
    loss_budget_db: float = field(
        default=0.3,
        metadata={
            "help": "damage budget of the ratio controller, as the PSNR drop it may see: > 0 compares the signal with "
            "the lowest value seen so far (ratio halved while it is worse by more than the loss increase this drop "
            "means, up one step otherwise) instead of with the previous step; 0 = paper (step to step). Best with "
            "loss_signal probe_psnr (the drop measured as PSNR) or probe. With loss_signal prune_damage: the PSNR "
            "the prunes may cost the probe views in all, spread evenly over the window's steps"
        },
    )
    loss_reference: str = field(
        default="",
        metadata={
            "help": "with loss_budget_db and loss_signal probe or probe_psnr: a run of the same configuration "
            "trained with compaction.method=reference; the budget then holds the probe signal against that "
            "unpruned run's at the same iteration instead of against the best seen so far (which stops falling "
            "once pruning takes the capacity, while the unpruned model's keeps falling). '' = the best seen so far"
        },
    )
    loss_smoothing: Literal["window_mean", "ema"] = field(
        default="window_mean",
        metadata={
            "help": "window_mean = mean training loss over the last interval iterations (i.e. since the previous "
            "pruning step); ema = exponential moving average updated every iteration"
        },
    )
    ema_decay: float = field(default=0.98, metadata={"help": "EMA decay per iteration (loss_smoothing = ema)"})
    loss_signal: LossSignal = field(
        default="prune_damage",
        metadata={
            "help": "the loss the ratio controller compares between pruning steps: 'training' = the smoothed training "
            "loss (paper; each from a random timestamp and views, so it varies with what was drawn; only with "
            "loss_budget_db=0, the paper's step-to-step comparison), 'probe' = the "
            "training loss of the current model on a fixed set of training views and times, rendered at every "
            "pruning step (it measures the model, not the sample), 'probe_psnr' = the same renders' mean squared error "
            "(geometric mean over the views, the mean PSNR's), so that loss_budget_db holds the PSNR it names; "
            "'prune_damage' = the PSNR the prunes themselves cost, without a reference run: the probe views' mean "
            "PSNR right before each prune minus right after it (nothing trains between; with prune_trials the 'after' "
            "is the trial's render of the model without the selection, taken before it is applied), summed over the "
            "steps and held against loss_budget_db spread evenly over the window's steps (needs loss_budget_db > 0)"
        },
    )
    probe_views: int = field(
        default=8, metadata={"help": "training views (camera x frame, spread over both) of the probe set"}
    )
    rotation_weight: float = field(
        default=0.01,
        metadata={
            "help": "weight of the sign-canonical unit quaternion against positions divided by the scene extent in "
            "the 7-D KNN distance; 0 = position only"
        },
    )
    sample_times: int = field(
        default=0,
        metadata={
            "help": "extra times (k evenly spaced, (j+0.5)/k) at which the nearest neighbour must also agree; "
            "0 = only the canonical time mu_t and the current time t (paper)"
        },
    )
    keeper_time_coverage: float = field(
        default=0.0,
        metadata={
            "help": "prune a matched pair only where its keeper is present while its loser is: the smallest ratio "
            "of their temporal opacity factors (keeper / loser, capped at 1) at the loser's mu_t and mu_t +- one "
            "temporal standard deviation must reach this, so pairs of disjoint lifetimes keep both; 0 = every pair "
            "(paper)"
        },
    )
    pair_order: Literal["distance", "size", "weight"] = field(
        default="weight",
        metadata={
            "help": "which matched pairs the ratio takes first: 'distance' = the closest (paper), 'size' = the closest "
            "in units of the pair's size (the distance over the sum of the two Gaussians' largest scales), so that "
            "Gaussians that overlap go before small neighbours that only lie close, such as fine detail; 'weight' = "
            "the pairs whose loser (by the criterion) shows least: its blending weight summed over the training views "
            "(one per camera and per frame, as the importance criterion's; rendered at each pruning step that selects "
            "a pair), equal "
            "weights closest first"
        },
    )
    merge_opacity: bool = field(
        default=False,
        metadata={
            "help": "the keeper of a pruned pair takes over its loser's opacity: its base opacity becomes the union "
            "1 - (1 - a_keeper)(1 - a_loser), so a pair of near duplicates keeps the coverage both gave at their "
            "centre; false = the loser's opacity goes with it (paper). Under the default damage budget with prune "
            "trials it removes less, not more (benchmarks/RESULTS.md, session 48)"
        },
    )
    min_gaussians: int = field(default=0, metadata={"help": "never prune below this many Gaussians"})

    @property
    def renders_model(self) -> bool:
        """Whether the controller or the pair order renders the model to decide (a probe-measured signal and its
        trials, the weight order's or the importance criterion's blending weights), rather than reading the
        training loss alone."""
        return self.loss_signal in PROBE_SIGNALS or self.pair_order == "weight" or self.criterion == "importance"

    # How a run saved before these options existed pruned (stgc.config.from_saved; the experiment runner's reuse
    # check compares a plan's value with them, so an older run is not taken for one that asks for another).
    SAVED_BEFORE: ClassVar[dict[str, Any]] = {"keeper_time_coverage": 0.0, "merge_opacity": False,
                                              "pair_order": "distance", "loss_signal": "training",
                                              "loss_budget_db": 0.0, "ratio_increase": "additive",
                                              "removal_rate_max": 0.0, "reset_settle_steps": 0,
                                              "prune_trials": 0}

    def validate(self, prefix: str = "") -> None:
        """Raise ValueError naming the field when a value cannot work."""
        if self.method not in METHODS:
            raise ValueError(f"compaction.method {self.method!r}: expected one of {METHODS}")
        if self.case not in (0, *CASE_WINDOWS):
            raise ValueError(f"compaction.case {self.case}: expected 0 (custom window) or 1-4")
        if self.case == 0 and not (0.0 <= self.window_start < self.window_end <= 1.0):
            raise ValueError(
                f"compaction.window_start/window_end ({self.window_start}, {self.window_end}): "
                "need 0 <= start < end <= 1"
            )
        if self.interval < 0:
            raise ValueError(f"compaction.interval {self.interval}: must be >= 0 (0 = automatic)")
        if self.criterion not in CRITERIA:
            raise ValueError(f"compaction.criterion {self.criterion!r}: expected one of {', '.join(CRITERIA)}")
        if not (0.0 <= self.ratio_min <= self.ratio_max <= 1.0):
            raise ValueError(
                f"compaction.ratio_min/ratio_max ({self.ratio_min}, {self.ratio_max}): need 0 <= min <= max <= 1"
            )
        if not (self.ratio_min <= self.ratio_init <= self.ratio_max):
            raise ValueError(
                f"compaction.ratio_init {self.ratio_init}: must lie in [ratio_min, ratio_max] = "
                f"[{self.ratio_min}, {self.ratio_max}]"
            )
        if not (0.0 <= self.removal_rate_max <= 1.0):  # also refuses NaN
            raise ValueError(f"compaction.removal_rate_max {self.removal_rate_max}: must be in [0, 1] (0 = no cap)")
        for name in ("ratio_step", "loss_tolerance", "rotation_weight"):  # NaN or inf would silently freeze the rule
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"compaction.{name} {value}: must be a finite number >= 0")
        if not (math.isfinite(self.loss_budget_db) and self.loss_budget_db >= 0):
            raise ValueError(f"compaction.loss_budget_db {self.loss_budget_db}: must be a finite number >= 0")
        if self.loss_budget_db > 0 and self.loss_tolerance > 0:
            raise ValueError("compaction.loss_tolerance applies to the paper's step-to-step comparison, which needs "
                             "compaction.loss_budget_db=0 (default 0.3) and compaction.loss_signal training, probe or "
                             "probe_psnr (default prune_damage); with a budget the budget is the tolerance")
        if self.loss_smoothing not in SMOOTHINGS:
            raise ValueError(f"compaction.loss_smoothing {self.loss_smoothing!r}: expected one of {SMOOTHINGS}")
        if self.ratio_increase not in RATIO_INCREASES:
            raise ValueError(f"compaction.ratio_increase {self.ratio_increase!r}: expected one of {RATIO_INCREASES}")
        if self.loss_signal not in LOSS_SIGNALS:
            raise ValueError(f"compaction.loss_signal {self.loss_signal!r}: expected one of {LOSS_SIGNALS}")
        # With method none every other option acts on nothing (a fine-tuning carries its source's section so).
        budgeted = self.method == "st-knn" and self.loss_budget_db > 0 and self.loss_signal in REFERENCE_SIGNALS
        if self.method == "st-knn" and self.loss_signal == "prune_damage" and self.loss_budget_db <= 0:
            raise ValueError("compaction.loss_signal prune_damage holds the prunes' PSNR cost against "
                             "compaction.loss_budget_db: set it > 0 (for example 0.3)")
        if self.loss_reference and self.method != "none" and not budgeted:
            raise ValueError(f"compaction.loss_reference {self.loss_reference!r}: a reference run is the damage "
                             "budget's, so it needs method st-knn, loss_budget_db > 0 and loss_signal probe or "
                             "probe_psnr")
        if self.probe_views < 1:
            raise ValueError(f"compaction.probe_views {self.probe_views}: must be >= 1")
        if not (0.0 <= self.ema_decay < 1.0):
            raise ValueError(f"compaction.ema_decay {self.ema_decay}: must be in [0, 1)")
        if self.sample_times < 0:
            raise ValueError(f"compaction.sample_times {self.sample_times}: must be >= 0")
        if not (0.0 <= self.keeper_time_coverage <= 1.0):  # also refuses NaN
            raise ValueError(f"compaction.keeper_time_coverage {self.keeper_time_coverage}: must be in [0, 1]")
        if self.min_gaussians < 0:
            raise ValueError(f"compaction.min_gaussians {self.min_gaussians}: must be >= 0")
        if self.reset_settle_steps < 0:
            raise ValueError(f"compaction.reset_settle_steps {self.reset_settle_steps}: must be >= 0")
        if self.prune_trials < 0:
            raise ValueError(f"compaction.prune_trials {self.prune_trials}: must be >= 0 (0 = measure after the prune)")


# Options that act only with another option's value, and that value in words (for the refusal).
_ACTS_ONLY_WITH: dict[str, tuple[Callable[[CompactionConfig], bool], str]] = {
    "window_start": (lambda c: c.case == 0, "compaction.case=0 (a case 1-4 has its window)"),
    "window_end": (lambda c: c.case == 0, "compaction.case=0 (a case 1-4 has its window)"),
    "loss_smoothing": (lambda c: c.loss_signal == "training",
                       "compaction.loss_signal=training (the probe loss is not smoothed)"),
    "ema_decay": (lambda c: c.loss_signal == "training" and c.loss_smoothing == "ema",
                  "compaction.loss_smoothing=ema and compaction.loss_signal=training"),
    "ratio_increase": (lambda c: c.loss_budget_db > 0,
                       "compaction.loss_budget_db > 0 (the paper's step-to-step rule raises the ratio by one step)"),
    "prune_trials": (lambda c: c.loss_signal == "prune_damage",
                     "compaction.loss_signal=prune_damage (the trials are held against its allowance)"),
    "probe_views": (lambda c: c.loss_signal in PROBE_SIGNALS or c.method == "reference",
                    "compaction.loss_signal=probe, probe_psnr or prune_damage, or compaction.method=reference"),
}
# What a reference run (method=reference) shares with the pruned run it is the reference of: the pruning schedule,
# at which it logs the probe loss, and the probe. It prunes nothing, so the matching, the criterion and the
# controller's options act on nothing there.
REFERENCE_RUN_OPTIONS = frozenset({"case", "window_start", "window_end", "interval", "probe_views"})
_REFERENCE_USES = REFERENCE_RUN_OPTIONS | {"method"}


def idle_compaction_options(compaction: CompactionConfig) -> set[str]:
    """The compaction options (dotted, with their section) that act on nothing in a run with `compaction`: all but
    the method where it is none, all but the schedule's and the probe's in a reference run, and those that act only
    with another option's value where that value is not set. Two runs that differ only there pruned alike; given
    for such a run they are refused (`stgc.options.refuse_unused_compaction_options`), and a plan's --set leaves
    them out of it."""
    names = [f.name for f in fields(compaction)]
    if compaction.method == "none":
        return {f"compaction.{name}" for name in names if name != "method"}
    idle = {f"compaction.{name}" for name, (acts, _) in _ACTS_ONLY_WITH.items() if not acts(compaction)}
    if compaction.method == "reference":
        idle |= {f"compaction.{name}" for name in names if name not in _REFERENCE_USES}
    return idle


def why_idle(compaction: CompactionConfig, key: str) -> str:
    """Why the compaction option `key` (dotted; one `idle_compaction_options` names) acts on nothing, in words."""
    name = key.removeprefix("compaction.")
    if compaction.method == "reference" and name not in _REFERENCE_USES:
        return f"{key} acts on nothing in a reference run (compaction.method=reference prunes nothing)"
    return f"{key} acts only with {_ACTS_ONLY_WITH[name][1]}"


@dataclass(frozen=True)
class PruningSchedule:
    """Pruning iterations of one run: start, start + interval, ... while < end."""

    start: int
    end: int
    interval: int

    def is_pruning_iteration(self, iteration: int) -> bool:
        return self.start <= iteration < self.end and (iteration - self.start) % self.interval == 0

    def iterations(self) -> range:
        """Every pruning iteration, in order."""
        return range(self.start, max(self.start, self.end), self.interval)

    @property
    def num_steps(self) -> int:
        if self.end <= self.start:
            return 0
        return (self.end - self.start - 1) // self.interval + 1


def settling_after_reset(iteration: int, opacity_resets: Sequence[int], settle_iterations: int) -> bool:
    """Whether a pruning step at `iteration` waits (compaction.reset_settle_steps): the latest opacity reset at or
    before it came less than `settle_iterations` (the steps times the pruning interval) before it."""
    latest = max((reset for reset in opacity_resets if reset <= iteration), default=None)
    return latest is not None and settle_iterations > 0 and iteration - latest < settle_iterations


def resolve_schedule(config: CompactionConfig, total_iterations: int) -> PruningSchedule:
    """Window and interval in real iterations for a run of `total_iterations`."""
    if total_iterations < 1:
        raise ValueError(f"total_iterations {total_iterations}: must be >= 1")
    start_fraction, end_fraction = (
        CASE_WINDOWS[config.case] if config.case else (config.window_start, config.window_end)
    )
    interval = config.interval or max(1, round(total_iterations * PAPER_INTERVAL / PAPER_ITERATIONS))
    # Iterations count from 1: a window opening at 0 prunes first at 1 (iteration 0 is never trained).
    return PruningSchedule(start=max(1, round(start_fraction * total_iterations)),
                           end=round(end_fraction * total_iterations), interval=interval)
