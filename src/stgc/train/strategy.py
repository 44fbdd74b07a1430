"""Strategies around the training step, in the manner of gsplat's `Strategy`: what changes the model's rows
(density control, error-guided sampling, ST-KNN compaction) is one object each, stepped by the trainer after the
optimizer step in a fixed order. Each keeps its own state in the training checkpoint under the keys it names, so
`Trainer.run` reads as the loop it is, and a new strategy is one class here plus a line in `Trainer.__init__`."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import torch

from stgc.compaction import ProbeResult, STKNNCompactor
from stgc.data import Camera
from stgc.model import STGModel
from stgc.train.densify import DensityControl
from stgc.train.ems import ErrorGuidedSampler
from stgc.train.quantization import QuantizationSimulation


@dataclass
class StepContext:
    """What a strategy sees after the optimizer step of `iteration`."""

    iteration: int
    t: float  # the timestamp the step trained
    loss: float  # the step's training loss (mean over its views)
    model: STGModel
    generator: torch.Generator  # this iteration's random stream for row changes
    ems_view: tuple[Camera, torch.Tensor, torch.Tensor] | None = None  # a view that asked for error-guided points


class Strategy(Protocol):
    def after_step(self, ctx: StepContext) -> dict[str, Any]:
        """Act on the model after the optimizer step; returns numbers for the metrics log."""
        ...

    def state_dict(self) -> dict[str, Any]:
        """Checkpoint entries (top-level keys of the training checkpoint)."""
        ...

    def load_state_dict(self, checkpoint: dict[str, Any]) -> None:
        """Restore from a whole training checkpoint (read only the keys `state_dict` writes)."""
        ...


class DensityStrategy:
    """The official clone/split, prune and opacity-reset schedule (`DensityControl`)."""

    def __init__(self, density: DensityControl):
        self.density = density

    def after_step(self, ctx: StepContext) -> dict[str, Any]:
        return dict(self.density.step(ctx.iteration, ctx.model, ctx.generator))

    def state_dict(self) -> dict[str, Any]:
        return self.density.state_dict()

    def load_state_dict(self, checkpoint: dict[str, Any]) -> None:
        self.density.load_state_dict(checkpoint)


class ErrorGuidedStrategy:
    """Error-guided sampling: new Gaussians along the rays of a badly reconstructed view the step flagged."""

    def __init__(self, sampler: ErrorGuidedSampler, density: DensityControl):
        self.sampler, self.density = sampler, density

    def after_step(self, ctx: StepContext) -> dict[str, Any]:
        if ctx.ems_view is None:
            return {}
        camera, render, gt = ctx.ems_view
        added = self.sampler.insert(ctx.iteration, ctx.model, camera, render, gt, ctx.generator)
        # As the official addgaussians (its densification_postfix): the gradient statistics start again, for every row.
        self.density.restart_statistics(ctx.model.num_gaussians)
        return {"ems_added": added}

    def state_dict(self) -> dict[str, Any]:
        return {"ems": self.sampler.state}

    def load_state_dict(self, checkpoint: dict[str, Any]) -> None:
        if checkpoint.get("ems"):
            self.sampler.state = checkpoint["ems"]


class CompactionStrategy:
    """ST-KNN compaction with its adaptive ratio; every pruning step is a line of RUN/compaction.jsonl."""

    def __init__(self, compactor: STKNNCompactor, record: Callable[[dict[str, Any]], None], density: DensityControl,
                 importance: Callable[[], torch.Tensor | np.ndarray], probe: Callable[..., ProbeResult] | None = None):
        self.compactor, self.record, self.density, self.importance = compactor, record, density, importance
        self.probe = probe

    def after_step(self, ctx: StepContext) -> dict[str, Any]:
        event = self.compactor.step(ctx.iteration, ctx.t, ctx.model, ctx.loss, importance_fn=self.importance,
                                    on_prune=self.density.rows_kept, probe_fn=self.probe)  # fmt: skip
        if event:
            self.record(event)  # the event carries its iteration
        return {}

    def state_dict(self) -> dict[str, Any]:
        return {"compactor": self.compactor.state_dict()}

    def load_state_dict(self, checkpoint: dict[str, Any]) -> None:
        if checkpoint.get("compactor") is not None:
            self.compactor.load_state_dict(checkpoint["compactor"])


class MaskStrategy:
    """Settles the rate-aware window's learned mask (stgc.train.quantization.GaussianMask) at `settle_iteration`:
    the Gaussians it faded out are removed, the others keep it baked into their opacity."""

    def __init__(self, quantization: QuantizationSimulation, density: DensityControl, settle_iteration: int):
        self.quantization, self.density, self.settle_iteration = quantization, density, settle_iteration

    def after_step(self, ctx: StepContext) -> dict[str, Any]:
        if ctx.iteration < self.settle_iteration:
            return {}
        keep = self.quantization.settle_mask(ctx.model)
        if keep is None:
            return {}
        dropped = int((~keep).sum())
        if dropped:
            ctx.model.prune(keep)
            self.density.rows_kept(keep)
        return {"mask_dropped": dropped}

    def state_dict(self) -> dict[str, Any]:
        return {}  # the mask itself is in the quantization simulation's checkpoint entry

    def load_state_dict(self, checkpoint: dict[str, Any]) -> None:
        pass
