"""Rate-distortion optimised bit allocation: the cheapest bit depth per attribute group that keeps the rendered
training views within a PSNR budget of the unquantized model.

The fixed ladder (format.GROUPS) is one table for every scene, but how much quantization noise a model tolerates
depends on how well the model itself fits: noise far below the model's own error does not move its PSNR. If the
model's squared error on a view is m0 and quantization adds an independent error e, the view's PSNR drops by
10 log10(1 + e / m0). So a budget of L dB is a bound on the *relative* added error, sum over groups of
mean_view(e_g / m0) <= 10^(L/10) - 1, with e_g measured by rendering the model with only group g quantized
(errors of different attribute groups are close to independent, so they add). The encoder

1. renders a few training views of the float model (reference) and reads their ground truth (m0 per view);
2. shapes the steps inside each group whose components play different roles (motion's three powers of time,
   albedo against the decoder's features, ...): each component is measured alone at the ladder's q3 depth, and
   since at fine quantization a component's error grows with the square of its step, the group's error for a
   given number of bits is smallest when every component adds the same error. The less visible components get
   steps coarser by sqrt(largest error / their error) (in quarter bits, at most 4 bits). The probes render 4 of
   the table's views: they only rank a group's components against each other;
3. for each group and integer bit depth, encodes/decodes the model with only that group coarse, renders,
   and records the section's bytes and its relative added error. The depths are swept from the middle of the
   group's range outwards and a direction stops at the first depth that decides nothing: finer than one whose
   error is negligible against the budget, coarser than one whose error is many budgets. Quarter-bit depths in
   between (a step 2^(1/4) coarser per quarter, codes in the next integer depth's container) are interpolated:
   bytes linearly, log error linearly (both are, at fine quantization);
4. picks one depth per group minimising total bytes under the budget (a multiple-choice knapsack, solved exactly
   on a fine grid of the error axis);
5. renders the model with all groups at the chosen depths and measures the mean PSNR drop over the views plus one
   standard error. The per-group errors do not add up exactly (in practice their sum over-estimates the joint
   error) and interpolated options are estimates, so the knapsack's budget is searched (geometric bisection,
   steps 4-5 repeated) for the cheapest allocation whose measured bound is within the budget.

Only training views are used, never test views. The decoder needs nothing of this: every component's step is in
the section table, as for the ladder. docs/stgc-format.md section 7 ("Rate-distortion optimised allocation").
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from stgc.metrics import psnr_of_mse

from .format import (
    DEFAULT_QUALITY,
    GROUP_BY_TAG,
    QUALITY_LEVELS,
    QUAT_SMALLEST3,
    QuantizationMemo,
    bits_for,
    groups_for,
    section_payload_bytes,
    simulate_decoder_state,
    simulate_quantization,
)
from .quantize import MAX_BITS, MIN_BITS

# PSNR budget on the training views per quality level: each level is ~3x (in added squared error) stricter than
# the one before; q3 = 0.1 dB, the loss a user would not see in any table.
LOSS_BUDGET_DB: Mapping[int, float] = {1: 1.0, 2: 0.3, 3: 0.1, 4: 0.03, 5: 0.01}
# Depths tried per group: from two below the ladder's q1 to the ladder's q5 (beyond q5 nothing measurable is left).
_BELOW_LADDER = 2
_NEAR_LOSSLESS_BITS = 20  # the other groups while one group is measured: far below any visible error
_PROBE_ZSTD_LEVEL = 3  # section sizes are measured at a fast level; the ranking of depths does not depend on it
_GRID = 2000  # error-axis resolution of the knapsack (errors are rounded up: the solution never exceeds the budget)
_MAX_ROUNDS = 8
_BRACKET = 1.05  # rate control stops once the feasible and infeasible knapsack budgets are within 5 %
_STEPS_PER_BIT = 4  # depths and step shapes are searched in quarter bits (step factors are powers of 2**(1/4))
_PROBE_FINER_BITS = 8  # while one component is measured, the rest of its group is this much finer (error / 4**8)
_MAX_COARSER_BITS = 4.0  # a component's step is at most 16x its group's finest
# The depth sweep of a group stops going finer at an error below this fraction of the budget, and coarser at an
# error above this many budgets (an error roughly quadruples per bit removed; rate control starts from one budget
# and widens it at most 4x a round while the measured loss stays far below it). Finer: at the knapsack's optimum a
# group's error is about its share of the budget, in proportion to its components (one of some 30 for a
# one-component group), so a depth adding under 1/100 of the budget is finer than any optimum uses; 1/1000 until
# session 15 gave files within 2.2 % on four trained models (benchmarks/RESULTS.md).
_NEGLIGIBLE = 1e-2
_HOPELESS = 16.0
# Views the table's trials render (of the sampled ones). Measured against all 16 on two trained blender_toys models
# at q3: files within 1.3 % (one smaller, one larger), test PSNR -0.003 and -0.007 dB (benchmarks/RESULTS.md).
_TABLE_VIEWS = 8
# Views the step-shape probes render (of the table's): a probe only ranks a group's components against each other,
# in quarter bits.
_PROBE_VIEWS = 4


def spread_views(count: int, wanted: int) -> list[int]:
    """`wanted` of `count` view indices (all when fewer), spread evenly over them."""
    spread = np.linspace(0, count - 1, min(wanted, count))
    return sorted({int(round(x)) for x in spread})


def budget_db(quality: int) -> float:
    if quality not in QUALITY_LEVELS:
        raise ValueError(f"quality must be one of {QUALITY_LEVELS}, got {quality!r}")
    return LOSS_BUDGET_DB[quality]


def candidate_bits(tag: str) -> list[int]:
    """The integer depths measured for a group."""
    group = GROUP_BY_TAG[tag.encode("latin-1")]
    lo = max(MIN_BITS, bits_for(group, 1) - _BELOW_LADDER)
    hi = min(MAX_BITS, bits_for(group, 5))
    return list(range(lo, hi + 1))


def shapeable_groups(variant: str) -> list[str]:
    """Groups whose components play different roles, so that each may deserve its own step."""
    return [g.tag.decode("latin-1") for g in groups_for(variant) if len(g.fields(variant)) > 1 and not g.exchangeable]


def coarser_bits(errors: Sequence[float]) -> list[float]:
    """Per component, how many bits coarser than the most visible one its step should be (multiples of 1/4, at
    most _MAX_COARSER_BITS) so that all components add about the same error, given the error each added alone
    at a common depth. A component that added no measurable error gets the maximum."""
    largest = max(errors)
    if not largest > 0:
        return [0.0] * len(errors)
    shifts = []
    for error in errors:
        bits = 0.5 * math.log2(largest / error) if error > 0 else _MAX_COARSER_BITS
        shifts.append(min(_MAX_COARSER_BITS, math.floor(bits * _STEPS_PER_BIT) / _STEPS_PER_BIT))
    return shifts


def encoder_settings(variant: str, depths: Mapping[str, float], shapes: Mapping[str, Sequence[float]] | None = None,
                     ) -> tuple[dict[str, int], dict[str, list[float]]]:
    """(group_bits, step_scales) for format.encode: a fractional depth d is coded in ceil(d) bits with every step
    2**(ceil(d) - d) coarser; a shaped group's components are coarser still by 2**shape."""
    group_bits, step_scales = {}, {}
    for tag, depth in depths.items():
        bits = math.ceil(depth)
        shape = list((shapes or {}).get(tag, ()))
        if bits != depth or any(shape):
            group = GROUP_BY_TAG[tag.encode("latin-1")]
            shape = shape or [0.0] * (3 if group.domain == QUAT_SMALLEST3 else len(group.fields(variant)))
            step_scales[tag] = [2.0 ** (bits - depth + b) for b in shape]
        group_bits[tag] = bits
    return group_bits, step_scales


@dataclass(frozen=True)
class Option:
    """One bit depth of one group: the section's bytes and the relative squared error it adds."""

    depth: float
    bytes: float
    error: float


def with_fractional_depths(measured: Sequence[Option]) -> list[Option]:
    """`measured` (consecutive integer depths, ascending) plus quarter-bit depths in between: bytes interpolated
    linearly, error geometrically (linearly where either end is 0)."""
    options = [measured[0]]
    for lo, hi in itertools.pairwise(measured):
        for k in range(1, _STEPS_PER_BIT):
            w = k / _STEPS_PER_BIT
            if lo.error > 0 and hi.error > 0:
                error = math.exp((1 - w) * math.log(lo.error) + w * math.log(hi.error))
            else:
                error = (1 - w) * lo.error + w * hi.error
            options.append(Option(lo.depth + w, (1 - w) * lo.bytes + w * hi.bytes, error))
        options.append(hi)
    return options


def _units(error: float, unit: float) -> int:
    return math.ceil(error / unit) if error > 0 else 0


def solve(options: Mapping[str, Sequence[Option]], budget: float) -> dict[str, float] | None:
    """Depth per group with the fewest total bytes such that the sum of errors stays <= budget.

    Exact multiple-choice knapsack on the error axis discretised into _GRID steps of budget/_GRID, each error
    rounded *up* (so the true sum never exceeds the budget). None when even the most precise options do not fit."""
    tags = list(options)
    if budget <= 0:  # only error-free options fit
        exact = {t: [o for o in options[t] if o.error <= 0] for t in tags}
        if not all(exact.values()):
            return None
        return {t: min(exact[t], key=lambda o: o.bytes).depth for t in tags}
    unit = budget / _GRID
    inf = math.inf
    # best[k] = fewest bytes of the groups so far using at most k error units; picks[g][k] = the option taken.
    best = np.zeros(_GRID + 1)
    picks: list[np.ndarray] = []
    for tag in tags:
        new = np.full(_GRID + 1, inf)
        pick = np.full(_GRID + 1, -1, dtype=np.int64)
        for index, option in enumerate(options[tag]):
            units = _units(option.error, unit)
            if units > _GRID:
                continue
            shifted = np.full(_GRID + 1, inf)
            shifted[units:] = best[: _GRID + 1 - units] + option.bytes
            better = shifted < new
            new[better] = shifted[better]
            pick[better] = index
        best = new
        picks.append(pick)
    if not np.isfinite(best[_GRID]):
        return None
    chosen: dict[str, float] = {}
    k = _GRID
    for tag, pick in zip(reversed(tags), reversed(picks)):
        option = options[tag][int(pick[k])]
        chosen[tag] = option.depth
        k -= _units(option.error, unit)
    return dict(reversed(list(chosen.items())))


@dataclass
class Allocation:
    """What the optimiser chose and measured (stored in the file's metadata as `allocation`)."""

    variant: str
    depths: dict[str, float]  # per group, in quarter bits (encoder_settings turns them into depths and steps)
    shapes: dict[str, list[float]]  # per shaped group, how many bits coarser each component is than the finest
    budget_db: float
    measured_loss_db: float  # mean PSNR drop on the sampled training views with every group at `depths`
    loss_bound_db: float  # measured + one standard error over the views: what is held to the budget
    predicted_loss_db: float
    views: int
    rounds: int
    within_budget: bool
    table: dict[str, list[Option]] = field(default_factory=dict, repr=False)

    def encoder_settings(self) -> tuple[dict[str, int], dict[str, list[float]]]:
        return encoder_settings(self.variant, self.depths, self.shapes)

    def summary(self) -> dict[str, Any]:
        return {"mode": "rd-optimised", "depths": dict(self.depths),
                "coarser_bits": {t: list(v) for t, v in self.shapes.items()}, "budget_db": self.budget_db,
                "train_view_loss_db": round(self.measured_loss_db, 5),
                "train_view_loss_bound_db": round(self.loss_bound_db, 5),
                "predicted_loss_db": round(self.predicted_loss_db, 5), "views": self.views,
                "rounds": self.rounds, "within_budget": self.within_budget}


RenderFn = Callable[[Mapping[str, np.ndarray], Mapping[str, np.ndarray] | None, Sequence[int]], Sequence[np.ndarray]]


def _mse(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))


def _psnr(mse: float) -> float:
    return psnr_of_mse(max(mse, 1e-12))


def optimise_allocation(
    arrays: Mapping[str, np.ndarray],
    variant: str,
    decoder_state: Mapping[str, Any] | None,
    render: RenderFn,
    ground_truth: Sequence[np.ndarray],
    loss_budget_db: float,
    *,
    fixed_bits: Mapping[str, int] | None = None,
    outlier_guard: bool = True,
    adaptive_delta: bool = True,
    progress: Callable[[int, int], None] | None = None,
) -> Allocation:
    """Choose the depth and step shape of every attribute group (see the module docstring).

    `render(arrays, decoder_state, views)` renders the sampled training views listed in `views` (indices into
    `ground_truth`, in that order) of the model given as official PLY arrays (float images in [0, 1]).
    `fixed_bits` pins groups to an integer depth with unshaped steps (e.g. a user's position_bits); the other
    groups are optimised."""
    if not ground_truth:
        raise ValueError("optimise_allocation needs at least one training view")
    if not loss_budget_db > 0:
        raise ValueError(f"loss budget must be > 0 dB, got {loss_budget_db}")
    tags = [g.tag.decode("latin-1") for g in groups_for(variant)]
    fixed = dict(fixed_bits or {})
    candidates = {t: ([fixed[t]] if t in fixed else candidate_bits(t)) for t in tags}
    shaped = [t for t in shapeable_groups(variant) if t not in fixed]
    shapes: dict[str, list[float]] = {}
    # Progress counts encode/decode/render trials: probes and table (an upper bound: the sweep stops early; the
    # total is corrected once the table is done), then one per rate-control round (grows it).
    width = {t: len(GROUP_BY_TAG[t.encode("latin-1")].fields(variant)) for t in tags}
    planned = 1 + sum(width[t] for t in shaped) + sum(len(c) for c in candidates.values()) + 1
    done = 0

    decoded_decoder = simulate_decoder_state(decoder_state)
    memo = QuantizationMemo(arrays)  # a trial redoes only the groups whose settings differ from earlier trials'

    every_view = list(range(len(ground_truth)))
    # The table's trials (one group at a time) compare with the reference on a subset of the views, spread over
    # them, and the step-shape probes on a smaller one; rate control, which decides what is held to the budget,
    # renders every view.
    table_views = spread_views(len(ground_truth), _TABLE_VIEWS)
    probe_views = [table_views[i] for i in spread_views(len(table_views), _PROBE_VIEWS)]

    def trial(depths: Mapping[str, float], shape: Mapping[str, Sequence[float]] | None = None,
              size_of: str | None = None, views: Sequence[int] = table_views) -> tuple[list[np.ndarray], int | None]:
        """Render `views` of the model as the codec would store it at `depths` (simulate_quantization:
        decode(encode()) without the entropy coding, which only the measured section's size needs), and that
        section's bytes."""
        nonlocal done
        group_bits, step_scales = encoder_settings(variant, depths, shapes if shape is None else shape)
        stored = simulate_quantization(arrays, variant, group_bits=group_bits, step_scales=step_scales,
                                       outlier_guard=outlier_guard, memo=memo)
        images = list(render(stored, decoded_decoder, views))
        size = None if size_of is None else section_payload_bytes(
            arrays, variant, size_of, zstd_level=_PROBE_ZSTD_LEVEL, group_bits=group_bits, step_scales=step_scales,
            outlier_guard=outlier_guard, adaptive_delta=adaptive_delta, memo=memo)  # the bytes encode would write
        done += 1
        if progress:
            progress(done, max(planned, done))
        return images, size

    reference = list(render(arrays, decoder_state, every_view))
    if len(reference) != len(ground_truth):
        raise ValueError(f"render gave {len(reference)} views for {len(ground_truth)} ground-truth images")
    base_mse = [max(_mse(r, g), 1e-10) for r, g in zip(reference, ground_truth)]
    base_psnr = np.array([_psnr(m) for m in base_mse])

    def loss(images: Sequence[np.ndarray]) -> tuple[float, float]:
        """Mean PSNR drop over the views, and that plus one standard error (the views are a sample: a bound
        keeps the budget on views not drawn too, test views included)."""
        drop = base_psnr - np.array([_psnr(_mse(i, g)) for i, g in zip(images, ground_truth)])
        se = float(np.std(drop, ddof=1) / math.sqrt(len(drop))) if len(drop) > 1 else 0.0
        return float(np.mean(drop)), float(np.mean(drop)) + se

    def relative_error(images: Sequence[np.ndarray], views: Sequence[int] = table_views) -> float:
        """Mean added squared error relative to the model's own, over `views` (rendered as `images`)."""
        return float(np.mean([_mse(i, reference[v]) / base_mse[v] for i, v in zip(images, views)]))

    near_lossless = {t: float(fixed.get(t, _NEAR_LOSSLESS_BITS)) for t in tags}
    images, _ = trial(near_lossless)
    floor = relative_error(images)  # fp16 decoder weights, float32 casts: common to every option
    probe_floor = relative_error([images[table_views.index(v)] for v in probe_views], probe_views)
    for tag in shaped:  # each component alone at the ladder's q3 depth, the rest of its group much finer
        probe_depth = bits_for(GROUP_BY_TAG[tag.encode("latin-1")], DEFAULT_QUALITY) + _PROBE_FINER_BITS
        errors = []
        for component in range(width[tag]):
            probe = [float(_PROBE_FINER_BITS) if c == component else 0.0 for c in range(width[tag])]
            images, _ = trial({**near_lossless, tag: probe_depth}, {tag: probe}, views=probe_views)
            errors.append(relative_error(images, probe_views) - probe_floor)
        shapes[tag] = coarser_bits(errors)
    target = 10.0 ** (loss_budget_db / 10.0) - 1.0

    def measure(tag: str, bits: int) -> Option:
        images, size = trial({**near_lossless, tag: float(bits)}, size_of=tag)
        assert size is not None
        return Option(float(bits), size, max(0.0, relative_error(images) - floor))

    table: dict[str, list[Option]] = {}
    for tag in tags:
        # From the middle of the group's depths outwards, each way until a depth decides nothing: finer ones once
        # the error is negligible (the knapsack would pay bytes to remove less than _NEGLIGIBLE of the budget),
        # coarser ones once the error is hopeless (_HOPELESS budgets: more than rate control's search widens to).
        depths = candidates[tag]
        middle = len(depths) // 2
        trials = [measure(tag, depths[middle])]
        for bits in depths[middle + 1:]:
            if trials[-1].error <= _NEGLIGIBLE * target:
                break
            trials.append(measure(tag, bits))
        for bits in reversed(depths[:middle]):
            if trials[0].error >= _HOPELESS * target:
                break
            trials.insert(0, measure(tag, bits))
        # Fewer bits never remove error; where measurement noise says otherwise, a depth is charged the largest
        # error measured at it or any finer depth (the conservative envelope).
        monotone, largest = [], 0.0
        for option in reversed(trials):
            largest = max(largest, option.error)
            monotone.append(Option(option.depth, option.bytes, largest))
        monotone.reverse()
        table[tag] = monotone if tag in fixed else with_fractional_depths(monotone)

    planned = done + 1  # the table is done: what is left is rate control, at least one round
    # Rate control: the sum of per-group errors only approximates the joint error (in practice it over-estimates
    # it), so the knapsack budget is searched (geometric bisection) for the cheapest allocation whose *measured*
    # loss on the views stays within the budget.
    most_precise = {t: table[t][-1].depth for t in tags}

    def option_of(tag: str, depth: float) -> Option:
        return next(o for o in table[tag] if o.depth == depth)

    def estimated_bytes(depths: Mapping[str, float]) -> float:
        return sum(option_of(t, depths[t]).bytes for t in tags)

    measured_at: dict[tuple[float, ...], tuple[float, float]] = {}
    best: Allocation | None = None
    fallback: Allocation | None = None
    # Positive even when the fixed floor alone uses the budget up (then only the most precise depths can pass).
    internal, feasible, infeasible = max(target - floor, 1e-3 * target), None, None
    for round_index in range(1, _MAX_ROUNDS + 1):
        chosen = solve(table, internal) or most_precise
        key = tuple(chosen[t] for t in tags)
        if key not in measured_at:
            images, _ = trial(chosen, views=every_view)
            measured_at[key] = loss(images)
        measured, bound = measured_at[key]
        predicted = floor + sum(option_of(t, chosen[t]).error for t in tags)
        candidate = Allocation(variant, chosen, shapes, loss_budget_db, measured, bound,
                               10.0 * math.log10(1.0 + predicted), len(reference), round_index,
                               bound <= loss_budget_db, table)
        if candidate.within_budget:
            if best is None or estimated_bytes(chosen) < estimated_bytes(best.depths):
                best = candidate
            feasible = internal if feasible is None else max(feasible, internal)
        else:
            fallback = candidate if chosen == most_precise else fallback
            infeasible = internal if infeasible is None else min(infeasible, internal)
            if chosen == most_precise:
                break
        if feasible is not None and infeasible is not None:
            if infeasible / feasible < _BRACKET:
                break
            internal = math.sqrt(feasible * infeasible)
        else:
            ratio = target / max(10.0 ** (bound / 10.0) - 1.0, 1e-12)
            internal *= min(4.0, max(1.25, ratio)) if feasible is not None else min(0.8, max(0.25, ratio))
    result = best or fallback
    if result is None:  # every round overshot without reaching the most precise depths: measure those
        images, _ = trial(most_precise, views=every_view)
        measured, bound = loss(images)
        predicted = floor + sum(table[t][-1].error for t in tags)
        result = Allocation(variant, most_precise, shapes, loss_budget_db, measured, bound,
                            10.0 * math.log10(1.0 + predicted), len(reference), _MAX_ROUNDS, bound <= loss_budget_db,
                            table)
    return result
