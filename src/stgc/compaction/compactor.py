"""The trainer-facing compactor: schedule + loss smoothing + adaptive ratio + matching + pruning."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping, Sequence
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from stgc.config import validate_config
from stgc.errors import DataError
from stgc.fileio import read_json_object
from stgc.metrics import psnr_of_mse

from .config import (
    PROBE_SIGNALS,
    CompactionConfig,
    PruningSchedule,
    idle_compaction_options,
    resolve_schedule,
    settling_after_reset,
)
from .controller import AdaptiveRatio, LossSmoother, budget_for_psnr_drop
from .matching import SpacetimeModel, match_spatiotemporal_pairs, to_float64_numpy
from .plot import LOG_NAME, read_compaction_log
from .pruning import (
    PruneSelection,
    keeper_time_coverage,
    loser_weights,
    merge_keeper_opacity,
    removal_scores,
    select_removals,
    size_relative_distances,
)


class PrunableModel(SpacetimeModel, Protocol):
    def prune(self, keep: torch.Tensor) -> None: ...

    def params_replaced(self, params: Mapping[str, torch.Tensor] | None) -> AbstractContextManager[None]: ...


@dataclasses.dataclass(frozen=True)
class ProbeResult:
    """The model on the fixed probe views: the training loss, and the mean squared error as the geometric mean over
    the views (10^(-PSNR/10) of their mean PSNR, so that its ratio between two models is their PSNR difference)."""

    loss: float
    mse: float

    def signal(self, loss_signal: str) -> float:
        return self.mse if loss_signal == "probe_psnr" else self.loss


# Where a probe signal's value sits in a reference run's record (the loss was its only one before 2026-11-28).
_REFERENCE_FIELD = {"probe": "smoothed_loss", "probe_psnr": "probe_mse"}


class STKNNCompactor:
    """Spatiotemporal KNN compaction, stepped by the trainer once per iteration after the optimizer step.

    >>> config = replace(CompactionConfig(case=1), **PAPER_RULE)   # the defaults also need probe_fn, importance_fn
    >>> compactor = STKNNCompactor(config, total_iterations=4500)
    >>> event = compactor.step(iteration, t, model, loss)   # None, or a dict for RUN/compaction.jsonl
    """

    def __init__(self, config: CompactionConfig, total_iterations: int, opacity_resets: Sequence[int] = ()):
        """`opacity_resets`: the iterations at which training resets every opacity (reset_settle_steps waits after
        them)."""
        validate_config(config, "compaction")  # its fixed choices too (pair_order "Size" was taken for distance)
        self.config = config
        self.total_iterations = int(total_iterations)
        self.opacity_resets = tuple(sorted(int(i) for i in opacity_resets))
        self.schedule: PruningSchedule = resolve_schedule(config, self.total_iterations)
        self.smoother = LossSmoother(config.loss_smoothing, self.schedule.interval, config.ema_decay)
        # prune_damage holds its budget in dB as an allowance (AdaptiveRatio.hold), not as a relative rise.
        relative_budget = config.loss_budget_db > 0 and config.loss_signal != "prune_damage"
        self.controller = AdaptiveRatio(
            config.ratio_init, config.ratio_step, config.ratio_min, config.ratio_max, config.loss_tolerance,
            budget_for_psnr_drop(config.loss_budget_db, squared_error=config.loss_signal == "probe_psnr")
            if relative_budget else 0.0,
            slow_start=config.loss_budget_db > 0 and config.ratio_increase == "slow_start",
        )
        self.steps_done = 0
        self.total_removed = 0
        self.prune_damage_db = 0.0  # the probe PSNR the prunes cost so far (loss_signal prune_damage)
        self.damage_unmeasured = False  # the last prune's damage could not be measured (a non-finite probe render)
        self.reference = (load_reference_losses(config.loss_reference, self.schedule, config.probe_views,
                                                config.loss_signal) if config.loss_reference else None)

    @property
    def enabled(self) -> bool:
        return self.config.method != "none" and self.schedule.num_steps > 0

    @property
    def ratio(self) -> float:
        return self.controller.ratio

    def step(
        self,
        iteration: int,
        t: float,
        model: PrunableModel,
        loss: float,
        importance_fn: Callable[[], torch.Tensor | np.ndarray] | None = None,
        on_prune: Callable[[torch.Tensor], Any] | None = None,
        probe_fn: Callable[..., ProbeResult] | None = None,
    ) -> dict[str, Any] | None:
        """Record this iteration's training loss; at a pruning iteration adjust the ratio and prune the model.

        `on_prune(keep)` is called with the boolean keep mask right after `model.prune(keep)`, so a caller
        holding per-Gaussian state of its own (the trainer's densification statistics) can drop the same rows.
        `probe_fn()`: the model on a fixed probe set, the controller's signal when loss_signal is a probe's;
        `probe_fn(keep)` (prune_trials): the same as if only the rows where the bool mask `keep` is True were kept.
        Returns the pruning step's log record, or None on other iterations (and always with method 'none')."""
        if not self.enabled:
            return None
        self.smoother.add(loss)
        if not self.schedule.is_pruning_iteration(iteration):
            return None
        if self.config.method != "reference" and self._settling(iteration):
            n = int(model.params["xyz"].shape[0])
            self.steps_done += 1
            return {"iteration": int(iteration), "t": float(t), "step": self.steps_done, "ratio": self.controller.ratio,
                    "loss_signal": self.config.loss_signal, "settling": True, "removed": 0, "gaussians_before": n,
                    "gaussians_left": n, "total_removed": self.total_removed, "criterion": self.config.criterion}

        smoothed: float | None
        probe: ProbeResult | None = None
        if self.config.loss_signal in PROBE_SIGNALS or self.config.method == "reference":
            if probe_fn is None:
                raise ValueError("compaction: the probe loss needs probe_fn (the loss on the fixed probe views)")
            probe = probe_fn()
            smoothed = float(probe.signal(self.config.loss_signal))
        else:
            smoothed = self.smoother.value()
        n_before = int(model.params["xyz"].shape[0])
        if self.config.method == "reference":
            assert probe is not None
            self.steps_done += 1
            # Both probe signals, whichever a budgeted run will hold against this run.
            return {"iteration": int(iteration), "t": float(t), "step": self.steps_done, "ratio": 0.0,
                    "smoothed_loss": float(probe.loss), "probe_mse": float(probe.mse), "loss_signal": "probe",
                    "removed": 0, "gaussians_before": n_before, "gaussians_left": n_before, "total_removed": 0}
        reference = None if self.reference is None else self.reference[int(iteration)]
        previous, best = self.controller.previous_loss, self.controller.best_loss
        allowed_db: float | None = None
        backed_off = False  # the ratio halved because the last prune's damage was not measured
        if self.config.loss_signal == "prune_damage":
            # The budget spread evenly over the window: the steps so far may have cost their share of it.
            allowed_db = self.config.loss_budget_db * self.steps_done / self.schedule.num_steps
            smoothed = self.prune_damage_db
            backed_off = self.damage_unmeasured
            if backed_off:
                direction = self.controller.back_off()
                self.damage_unmeasured = False
            else:
                direction = self.controller.hold(self.prune_damage_db, allowed_db)
        else:
            direction = self.controller.update(smoothed, reference)
        ratio = self.controller.ratio

        started = time.perf_counter()
        pairs = match_spatiotemporal_pairs(model, t, self.config.rotation_weight, self.config.sample_times)
        matched_at = time.perf_counter()
        max_removals = max(0, n_before - self.config.min_gaussians)
        matched_pairs = len(pairs)
        rate_capped = False
        if self.config.removal_rate_max > 0:
            # At least one a step, or a small model with a short interval would never be pruned at all.
            cap = max(1, int(self.config.removal_rate_max * self.schedule.interval * n_before))
            max_removals = min(max_removals, cap)
            if matched_pairs and ratio * matched_pairs > cap:
                # The step uses only the cap's share of the pairs: the controller goes on from the ratio used (as
                # TCP does not grow a window it cannot fill), so that a halving halves what is removed.
                ratio = cap / matched_pairs
                self.controller.limit(ratio)
                rate_capped = True
        weights: np.ndarray | None = None

        def blending_weights() -> np.ndarray:  # rendered once per step, whether the criterion or the order asks
            nonlocal weights
            if importance_fn is None:
                raise ValueError("compaction: the importance criterion and pair_order 'weight' need importance_fn "
                                 "(the blending weight of every Gaussian over the training views)")
            if weights is None:
                raw = importance_fn()
                weights = (to_float64_numpy(raw) if torch.is_tensor(raw) else np.asarray(raw, np.float64)).reshape(-1)
            return weights

        scores = removal_scores(model.params, self.config.criterion, blending_weights) if len(pairs) else np.zeros(n_before)
        if self.config.keeper_time_coverage > 0 and len(pairs):
            coverage = keeper_time_coverage(pairs, scores, to_float64_numpy(model.params["trbf_center"]),
                                            to_float64_numpy(model.params["trbf_scale"]))
            pairs = pairs.subset(coverage >= self.config.keeper_time_coverage)
        order_by: Callable[[], np.ndarray] | None = None
        if self.config.pair_order == "size":
            order_by = lambda: size_relative_distances(pairs, to_float64_numpy(model.params["scaling"]),
                                                       model.scene_extent)
        elif self.config.pair_order == "weight":
            order_by = lambda: loser_weights(pairs, scores, blending_weights())
        selection = select_removals(pairs, ratio, scores, max_removals, ratio_of=matched_pairs, order_by=order_by)
        step_damage_db: float | None = None
        trials = rejected = 0
        # A probe that is not finite before the prune measures nothing: the prune is applied and found unmeasured
        # after it, as without trials (the next step backs off), rather than tried N times in vain.
        if self.config.prune_trials > 0 and self.config.loss_signal == "prune_damage" and selection.remove.size \
                and probe is not None and _psnr_of_mse(probe.mse) is not None:
            assert probe_fn is not None
            # What the prune may cost: the allowance once this step is done, less what the prunes so far spent.
            affordable_db = self.config.loss_budget_db * (self.steps_done + 1) / self.schedule.num_steps \
                - self.prune_damage_db
            while True:
                trials += 1
                damage_db = self._trial_damage(model, selection, probe, probe_fn)
                if damage_db is not None and damage_db <= affordable_db:  # a non-finite render never fits
                    step_damage_db = damage_db
                    break
                rejected += 1
                rate_capped = False  # what is tried next is below the cap's share
                tried = self.controller.ratio
                direction = self.controller.back_off()
                ratio = self.controller.ratio
                smaller = ratio < tried and trials < self.config.prune_trials  # none below ratio_min
                tried_removals = selection.remove
                selection = select_removals(pairs, ratio if smaller else 0.0, scores, max_removals,
                                            ratio_of=matched_pairs, order_by=order_by)
                if np.array_equal(selection.remove, tried_removals):  # max_removals bound both: the same trial again
                    selection = select_removals(pairs, 0.0, scores, max_removals, ratio_of=matched_pairs)
                if not selection.remove.size:
                    step_damage_db = 0.0
                    break
        if selection.remove.size:
            keep = _keep_mask(model, selection)
            if self.config.merge_opacity:
                merge_keeper_opacity(model.params["opacity"], selection.remove, selection.keepers)
            model.prune(keep)
            if on_prune is not None:
                on_prune(keep)
        finished = time.perf_counter()

        removed = int(selection.remove.size)
        if self.config.loss_signal == "prune_damage":
            assert probe is not None and probe_fn is not None
            if step_damage_db is None:  # no trial: measured now
                # Nothing trained since `probe`: the difference is the prune's alone (the keepers' merged opacity too).
                step_damage_db = _psnr_drop(probe.mse, probe_fn().mse) if removed else 0.0
            if step_damage_db is None:  # a non-finite render is no measure: the next step backs off
                self.damage_unmeasured = True
            else:
                self.prune_damage_db += step_damage_db
        self.steps_done += 1
        self.total_removed += removed
        return {
            "iteration": int(iteration),
            "t": float(t),
            "step": self.steps_done,
            "ratio": ratio,
            "ratio_direction": direction,
            "smoothed_loss": smoothed,
            "loss_signal": self.config.loss_signal,
            "probe_psnr": None if probe is None else _psnr_of_mse(probe.mse),
            "previous_smoothed_loss": previous,
            "best_smoothed_loss": best,
            "reference_loss": reference,
            "rate_capped": rate_capped,
            "loss_budget": self.controller.budget,
            "prune_damage_db": step_damage_db,
            "damage_allowed_db": allowed_db,
            "backed_off_unmeasured": backed_off,
            "prune_trials": trials,
            "trials_rejected": rejected,
            "matched_references": pairs.matched_references,
            "matched_pairs": matched_pairs,
            "time_covered_pairs": len(pairs),
            "selected_pairs": selection.selected_pairs,
            "conflicts": selection.conflicts,
            "removed": removed,
            "gaussians_before": n_before,
            "gaussians_left": n_before - removed,
            "total_removed": self.total_removed,
            "max_selected_distance": None if np.isnan(selection.max_selected_distance) else selection.max_selected_distance,
            "criterion": self.config.criterion,
            "match_seconds": round(matched_at - started, 4),
            "prune_seconds": round(finished - matched_at, 4),
        }

    def _trial_damage(self, model: PrunableModel, selection: PruneSelection, probe: ProbeResult,
                      probe_fn: Callable[..., ProbeResult]) -> float | None:
        """The probe PSNR that pruning `selection` would cost, rendered without applying it (None: not finite)."""
        keep = _keep_mask(model, selection)
        replaced: dict[str, torch.Tensor] | None = None
        if self.config.merge_opacity:
            opacity = model.params["opacity"].detach().clone()
            merge_keeper_opacity(opacity, selection.remove, selection.keepers)
            replaced = {**model.params, "opacity": opacity}
        with model.params_replaced(replaced):
            return _psnr_drop(probe.mse, probe_fn(keep).mse)

    def _settling(self, iteration: int) -> bool:
        """Whether the pruning step at `iteration` is one of the reset_settle_steps after an opacity reset (at or
        before it): the opacities are still growing back."""
        return settling_after_reset(iteration, self.opacity_resets,
                                    self.config.reset_settle_steps * self.schedule.interval)

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume (plain Python values: JSON- and torch.save-friendly)."""
        return {
            "config": dataclasses.asdict(self.config),
            "total_iterations": self.total_iterations,
            "steps_done": self.steps_done,
            "total_removed": self.total_removed,
            "prune_damage_db": self.prune_damage_db,
            "damage_unmeasured": self.damage_unmeasured,
            "controller": self.controller.state_dict(),
            "smoother": self.smoother.state_dict(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a `state_dict()`; the config and schedule must be the ones this compactor was built with."""
        saved = state.get("config")
        # An option added since the state was saved is read as the saving code trained it (SAVED_BEFORE, else the
        # default of the day it was added, which is today's for options whose default never changed).
        defaults = {**dataclasses.asdict(CompactionConfig()), **CompactionConfig.SAVED_BEFORE}
        # Options that act on nothing here are no difference (ratio_increase without a budget, as in PAPER_RULE).
        idle = {key.removeprefix("compaction.") for key in idle_compaction_options(self.config)}
        if saved is not None and _without({**defaults, **saved}, idle) != _without(dataclasses.asdict(self.config), idle):
            raise ValueError("compaction state was saved with a different CompactionConfig; resume with the same config")
        if int(state.get("total_iterations", self.total_iterations)) != self.total_iterations:
            raise ValueError(
                f"compaction state was saved for {state['total_iterations']} total iterations, not {self.total_iterations}"
            )
        self.steps_done = int(state["steps_done"])
        self.total_removed = int(state["total_removed"])
        self.prune_damage_db = float(state.get("prune_damage_db", 0.0))  # saved before the signal existed: none
        self.damage_unmeasured = bool(state.get("damage_unmeasured", False))
        self.controller.load_state_dict(state["controller"])
        self.smoother.load_state_dict(state["smoother"])


def _keep_mask(model: PrunableModel, selection: PruneSelection) -> torch.Tensor:
    """The bool mask of the model's rows that `selection` keeps, on the model's device."""
    keep = torch.ones(int(model.params["xyz"].shape[0]), dtype=torch.bool)
    keep[torch.from_numpy(selection.remove)] = False
    return keep.to(model.params["xyz"].device)


def _without(options: dict[str, Any], names: set[str]) -> dict[str, Any]:
    return {key: value for key, value in options.items() if key not in names}


def _psnr_drop(mse_before: float, mse_after: float) -> float | None:
    """The PSNR lost from `mse_before` to `mse_after` (dB, negative for a gain); None unless both are finite, > 0."""
    if not (mse_before > 0 and mse_after > 0 and np.isfinite(mse_before) and np.isfinite(mse_after)):
        return None
    return float(10.0 * np.log10(mse_after / mse_before))


def _psnr_of_mse(mse: float) -> float | None:
    """The probe's PSNR for the log: None where it has none (no error, or a non-finite one)."""
    return psnr_of_mse(mse) if mse > 0 and np.isfinite(mse) else None


def load_reference_losses(run_dir: str, schedule: PruningSchedule, probe_views: int,
                          loss_signal: str = "probe") -> dict[int, float]:
    """The probe signal `loss_signal` (the loss, or the MSE for probe_psnr) of a compaction.method=reference run at
    every pruning iteration of `schedule`, by iteration. Raises DataError naming the file when the run is not such a
    reference, does not cover the schedule, did not log that signal, or (its config.json says) probed a different
    number of views."""
    key = _REFERENCE_FIELD[loss_signal]  # CompactionConfig.validate admits a reference only with a REFERENCE_SIGNALS one
    path = Path(run_dir) / LOG_NAME if Path(run_dir).is_dir() else Path(run_dir)
    config_path = path.parent / "config.json"
    if config_path.is_file():
        theirs = (read_json_object(config_path) or {}).get("compaction") or {}
        if theirs.get("method") != "reference":
            raise DataError(config_path, f"compaction.method is {theirs.get('method')!r}: a loss reference is a run "
                                         "trained with compaction.method=reference")
        if int(theirs.get("probe_views", probe_views)) != probe_views:
            raise DataError(config_path, f"the reference probed {theirs['probe_views']} views, this run probes "
                                         f"{probe_views}: the losses would not compare")
    records = read_compaction_log(path)
    losses: dict[int, float] = {}
    for record in records:
        if record.get("removed", 0) != 0 or record.get("loss_signal") != "probe":
            raise DataError(path, f"iteration {record['iteration']}: not a reference run's record (it pruned, or "
                                  "logged no probe loss); train the reference with compaction.method=reference")
        if record.get(key) is None:
            raise DataError(path, f"iteration {record['iteration']}: the reference logged no {key} (reference runs "
                                  f"log it since 2026-11-28, for loss_signal {loss_signal}); train the reference again")
        losses[int(record["iteration"])] = float(record[key])
    missing = [i for i in schedule.iterations() if i not in losses]
    if missing:
        raise DataError(path, f"no probe loss at iteration {missing[0]} ({len(missing)} of this run's "
                              f"{schedule.num_steps} pruning iterations missing): the reference must be trained to the "
                              "end with the same schedule and compaction case/interval")
    return losses
