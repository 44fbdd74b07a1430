"""Removal criteria: in a selected pair of near-duplicate Gaussians, which member the pruning removes.

Each criterion gives every Gaussian a score; in a pair the member with the higher score is removed (ties: the
larger index). A criterion registers itself here, and `compaction.criterion`, the CLI's `--criterion` choices and
the experiment plans follow from the registry. Adding one is a decorated function in this module plus its test:

    @register_criterion("opacity", "lower opacity")
    def _more_transparent(params, importance):
        return -params["opacity"].detach().reshape(-1).to("cpu", torch.float64).numpy()
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
import torch

# The accumulated blending weight of every Gaussian over the training views (only the `importance` criterion calls
# it: it renders every training camera).
ImportanceFn = Callable[[], torch.Tensor | np.ndarray]
ScoreFn = Callable[[Mapping[str, torch.Tensor], ImportanceFn | None], np.ndarray]


@dataclass(frozen=True)
class Criterion:
    name: str
    removes: str  # which member is removed, for the option's help
    score: ScoreFn


CRITERIA: dict[str, Criterion] = {}


def register_criterion(name: str, removes: str) -> Callable[[ScoreFn], ScoreFn]:
    def decorator(score: ScoreFn) -> ScoreFn:
        if name in CRITERIA:
            raise ValueError(f"compaction criterion {name!r} is already registered")
        CRITERIA[name] = Criterion(name, removes, score)
        return score

    return decorator


def criteria_help() -> str:
    return "; ".join(f"{c.name} = {c.removes}" for c in CRITERIA.values())


@register_criterion("timestamp", "the later most-visible time mu_t (paper)")
def _later_time(params: Mapping[str, torch.Tensor], importance: ImportanceFn | None) -> np.ndarray:
    n = params["xyz"].shape[0]
    return params["trbf_center"].detach().reshape(n).to("cpu", torch.float64).numpy()


@register_criterion("scale", "the smaller volume (product of the activated scales)")
def _smaller_volume(params: Mapping[str, torch.Tensor], importance: ImportanceFn | None) -> np.ndarray:
    # The sum of log-scales orders like the volume and cannot overflow.
    return (-params["scaling"].detach().to("cpu", torch.float64).sum(dim=1)).numpy()


@register_criterion("importance", "less blending weight accumulated over the training views")
def _less_weight(params: Mapping[str, torch.Tensor], importance: ImportanceFn | None) -> np.ndarray:
    n = params["xyz"].shape[0]
    if importance is None:
        raise ValueError("compaction criterion 'importance' needs importance_fn (blending weight per Gaussian)")
    weight = importance()
    values = weight.detach().to("cpu", torch.float64).numpy() if torch.is_tensor(weight) else np.asarray(weight, np.float64)
    values = values.reshape(-1)
    if values.size != n:
        raise ValueError(f"importance_fn returned {values.size} values for {n} Gaussians")
    return -values
