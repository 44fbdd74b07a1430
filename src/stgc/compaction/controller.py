"""Rendering-loss-adaptive pruning ratio (paper Fig. 5) and the loss smoothing it compares.

Smoothing. The default is the mean of the training losses of the last `interval` iterations, which, because pruning
steps are exactly `interval` apart, is the mean since the previous pruning step: it measures the loss the model had
after the last prune, and averaging ~interval losses (each from a random frame and random views) divides the
sampling noise of single losses by about sqrt(interval). An EMA updated every iteration is offered as an
alternative; it reacts with a lag of ~1/(1-decay) iterations and mixes in losses from before the last prune.

Control. At each pruning step the smoothed loss is compared with the one of the previous step: higher (by more than
`tolerance` relative) -> ratio - step, lower -> ratio + step, otherwise unchanged; then clamped to [min, max]. The
first step has nothing to compare with and prunes at the initial ratio. The ratio is updated *before* the step's
prune, so each step's ratio reflects the effect of the previous prunes.

Damage budget (an alternative to the paper's comparison, `budget` > 0). While training lowers the loss faster than
pruning raises it, a comparison with the previous step raises the ratio whatever the pruning costs, until the damage
outruns the training's gain; then it steps down too slowly to undo it (benchmarks/RESULTS.md, issue #17). With a
budget the signal is compared with the lowest value seen so far instead: the ratio halves while the signal exceeds
that best by more than `budget` (relative), and rises one step otherwise (additive increase, multiplicative decrease:
the damage shows some steps after the prunes that caused it). So the accumulated damage, not its change, is held.
With `slow_start` the ratio doubles instead of rising one step until the budget first halves it (TCP's slow start):
an additive climb from 0.5 % by 0.1 % per step took 45 of a window's 100 steps to reach 5 % while the prunes cost
nothing measurable (issue #17, session 38), and so left a third of the window's pruning unspent. Each back-off
(a run of halvings) sets a threshold at half the ratio it started from, and the ratio doubles again up to it before
stepping (TCP's threshold; session 40: stepping from the bottom of a back-off left half the allowance unspent).
`budget_for_psnr_drop` turns a PSNR drop into it. The best seen so far understates the damage: once pruning takes
the model's capacity its loss stops falling, while an unpruned model's keeps falling to the end (issue #17 measured
1.8 dB lost on a test view with the probe held within 0.3 dB's worth of its own best). Given a `reference` loss at
each step, the unpruned model's at the same iteration (compaction.loss_reference), the budget is held against it;
then the first step has something to compare with too (the reference's loss), and an undamaged model raises the
ratio there already: the first prune is at the initial ratio plus one increase (one step, or doubled in slow
start), as with `hold`, whose first allowance is 0 and so is never exceeded.

Without a reference run the damage can still be read apart from training's progress: the probe rendered right
before and right after a prune (nothing trained between) differs only by what the prune did. `hold` compares the
sum of those drops so far with the budget spread evenly over the window's steps (compaction.loss_signal
prune_damage), with the same additive increase and multiplicative decrease.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any


class LossSmoother:
    """Smoothed training loss: window mean of the last `window` values, or an EMA. Non-finite losses are ignored."""

    def __init__(self, mode: str, window: int, ema_decay: float = 0.98):
        if mode not in ("window_mean", "ema"):
            raise ValueError(f"unknown loss smoothing {mode!r}")
        self.mode = mode
        self.window = max(1, int(window))
        self.ema_decay = float(ema_decay)
        self._recent: deque[float] = deque(maxlen=self.window)
        self._ema: float | None = None
        self.ignored = 0  # non-finite losses seen (a diverging run); they must not steer the ratio

    def add(self, loss: float) -> None:
        loss = float(loss)
        if not math.isfinite(loss):
            self.ignored += 1
            return
        self._recent.append(loss)
        self._ema = loss if self._ema is None else self.ema_decay * self._ema + (1.0 - self.ema_decay) * loss

    def value(self) -> float | None:
        if self.mode == "ema":
            return self._ema
        return sum(self._recent) / len(self._recent) if self._recent else None

    def state_dict(self) -> dict[str, Any]:
        return {"recent": list(self._recent), "ema": self._ema, "ignored": self.ignored}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self._recent = deque((float(x) for x in state["recent"]), maxlen=self.window)
        self._ema = None if state["ema"] is None else float(state["ema"])
        self.ignored = int(state.get("ignored", 0))


def budget_for_psnr_drop(drop_db: float, squared_error: bool = False) -> float:
    """The relative loss increase that a PSNR drop of `drop_db` corresponds to. For an L1-like loss PSNR follows the
    RMS error, 20 log10, and L1 scales with it, so 10^(drop/20) - 1 (0.3 dB -> 3.5 %): an approximation (a loss
    with a D-SSIM term, or errors that change shape, move otherwise). For a mean squared error (`squared_error`,
    geometric mean over views, whose ratio is exactly the mean PSNR's change) 10^(drop/10) - 1 (0.3 dB -> 7.2 %)."""
    return 10.0 ** (float(drop_db) / (10.0 if squared_error else 20.0)) - 1.0


class AdaptiveRatio:
    """The pruning ratio: down one step when the smoothed loss rose, up one step when it fell, clamped; or, with a
    damage `budget` (or `hold`), halved while over it and increased otherwise: up one step, or with `slow_start`
    doubled below the threshold (none until the first back-off, then half the ratio each back-off started from)."""

    def __init__(self, initial: float, step: float, minimum: float, maximum: float, tolerance: float = 0.0,
                 budget: float = 0.0, slow_start: bool = False):
        if not (minimum <= initial <= maximum):
            raise ValueError(f"initial ratio {initial} outside [{minimum}, {maximum}]")
        if budget < 0:
            raise ValueError(f"damage budget {budget} must be >= 0")
        self.ratio = float(initial)
        self.step = float(step)
        self.minimum = float(minimum)
        self.maximum = float(maximum)
        self.tolerance = float(tolerance)
        self.budget = float(budget)
        # With a budget: double the ratio below `threshold`, one step at a time above it (TCP's slow start and
        # congestion avoidance). The threshold is unknown (None: no limit) until the budget first halves the ratio;
        # each back-off then sets it to half the ratio it started from, so that after the halvings the ratio doubles
        # back to the level that last cost too little, not one step at a time from the bottom.
        self.slow_start = bool(slow_start)
        self.threshold: float | None = None
        self._backing_off = False
        self.previous_loss: float | None = None
        self.best_loss: float | None = None

    def update(self, loss: float | None, reference: float | None = None) -> int:
        """Feed this step's smoothed loss; returns the direction taken (-1, 0, +1). `self.ratio` is the new ratio.
        `reference` (budget only): the unpruned model's loss at this step, held against instead of the best so far.
        A non-finite loss or reference is no signal (a diverged probe render must not read as 'no damage'): the
        ratio stays and nothing is remembered."""
        if (loss is not None and not math.isfinite(loss)) or (reference is not None and not math.isfinite(reference)):
            return 0
        direction = 0
        proposed = self.ratio
        if loss is not None and self.budget > 0:
            against = self.best_loss if reference is None else reference
            if against is not None:
                direction = -1 if loss > against * (1.0 + self.budget) else 1
                proposed = self._aimd_step(direction)
        elif loss is not None and self.previous_loss is not None:
            change = loss - self.previous_loss
            if abs(change) > self.tolerance * abs(self.previous_loss):
                direction = -1 if change > 0 else 1
                proposed = self.ratio + direction * self.step
        self._set(proposed)
        if loss is not None:
            self.previous_loss = loss
            self.best_loss = loss if self.best_loss is None else min(self.best_loss, loss)
        return direction

    def hold(self, spent: float, allowed: float) -> int:
        """The budget as an allowance (compaction.loss_signal prune_damage): halve the ratio while the damage `spent`
        so far exceeds what is `allowed` by now, up one step otherwise; returns the direction. Non-finite values are
        no signal (the ratio stays)."""
        if not (math.isfinite(spent) and math.isfinite(allowed)):
            return 0
        direction = -1 if spent > allowed else 1
        self._set(self._aimd_step(direction))
        return direction

    def back_off(self) -> int:
        """Halve the ratio as when over budget: a prune whose damage could not be measured (a non-finite render
        after it) is taken as one that cost too much, never as one that cost nothing. Returns -1."""
        self._set(self._aimd_step(-1))
        return -1

    def limit(self, used: float) -> None:
        """The step could use only the ratio `used` (a cap on removals bound it): go on from there, not from a ratio
        that was never applied (kept within [minimum, maximum])."""
        if math.isfinite(used):
            self._set(min(self.ratio, used))

    def _aimd_step(self, direction: int) -> float:
        # Additive increase, multiplicative decrease: the damage shows some steps after the prunes that caused it,
        # so a ratio that only stepped down would keep pruning at nearly the rate that overshot.
        if direction < 0:
            if not self._backing_off:  # a run of halvings is one back-off (as one loss event in TCP)
                self.threshold = self.ratio / 2.0
            self._backing_off = True
            return self.ratio / 2.0
        self._backing_off = False
        additive = self.ratio + self.step
        if not self.slow_start or (self.threshold is not None and self.ratio >= self.threshold):
            return additive
        doubled = max(2.0 * self.ratio, additive)
        return doubled if self.threshold is None else max(min(doubled, self.threshold), additive)

    def _set(self, proposed: float) -> None:
        # Round away float drift (0.02 + 0.005 - 0.005 != 0.02) so that ratios are reproducible (and on the step grid
        # in the paper's rule; halving leaves it).
        self.ratio = round(min(self.maximum, max(self.minimum, proposed)), 12)

    def state_dict(self) -> dict[str, Any]:
        return {"ratio": self.ratio, "previous_loss": self.previous_loss, "best_loss": self.best_loss,
                "slow_start": self.slow_start, "threshold": self.threshold, "backing_off": self._backing_off}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.ratio = float(state["ratio"])
        self.previous_loss = None if state["previous_loss"] is None else float(state["previous_loss"])
        # Checkpoints written before the damage budget existed: the best so far is unknown, the last loss stands in.
        best = state.get("best_loss", state["previous_loss"])
        self.best_loss = None if best is None else float(best)
        # Saved before slow start existed: the ratio rose one step at a time.
        self.slow_start = bool(state.get("slow_start", False))
        if "threshold" in state:
            self.threshold = None if state["threshold"] is None else float(state["threshold"])
            self._backing_off = bool(state["backing_off"])
        else:
            # Saved before the threshold existed (session 39): a state whose slow start had ended (the first halving)
            # steps on as it did; one still doubling takes up the threshold at its first back-off (a behaviour
            # change, `slow-start-threshold`).
            self.threshold = None
            self._backing_off = False
