"""The rd-optimised bit allocation measured on a model's own training views (what `compress_run` and rate-aware
training both use): renders for `stgc.codec.allocation.optimise_allocation`."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from stgc.data.cameras import Camera
from stgc.data.dataset import Dataset
from stgc.model import STGModel, ply_columns

from .allocation import Allocation, budget_db, optimise_allocation

# {training camera name: (gain [3], offset [3])}: the colour correction the model was trained with.
Corrections = Mapping[str, tuple[Any, Any]]


def optimise_on_views(model: STGModel, dataset: Dataset, quality: int, *, views: int = 16, position_bits: int = 0,
                      outlier_guard: bool = True, corrections: Corrections | None = None,
                      show_progress: bool = True) -> Allocation:
    """The rd-optimised allocation of `model` at `quality`'s PSNR budget, measured on
    `views` training views (camera x frame, fixed seed), each rendered as training saw it: with its camera's colour
    correction (on a real rig a raw render of a training camera is off by that camera's tint, which would hide part
    of the quantization error and loosen the budget)."""
    corrections = corrections or {}
    train = list(dataset.train)
    picked = np.random.default_rng(0).choice(len(train), size=min(views, len(train)), replace=False)
    chosen = [train[i] for i in sorted(picked)]

    def ground_truth(cam: Camera) -> np.ndarray:  # as stgc.eval reads it: uint8 -> [0, 1], colour channels only
        image = np.asarray(dataset.load_image(cam))[..., :3]
        return image.astype(np.float32) / 255.0 if image.dtype == np.uint8 else image.astype(np.float32)

    truth = [ground_truth(cam) for cam in chosen]
    background = torch.tensor(dataset.background, dtype=torch.float32)
    columns = ply_columns(model.variant)
    trial: STGModel | None = None  # one model whose parameters each trial overwrites (its camera cache stays)

    @torch.no_grad()
    def render(candidate: Mapping[str, np.ndarray], decoder_state: Any, views: Sequence[int]) -> list:
        nonlocal trial
        if trial is None or trial.num_gaussians != len(candidate["x"]):
            trial = STGModel.from_ply_arrays(dict(candidate), model.variant, decoder_state,
                                             decoder_activation=model.decoder_activation or "sigmoid")
        else:
            for key, names in columns.items():
                trial.params[key].copy_(torch.from_numpy(np.stack([candidate[n] for n in names], axis=1)))
            if decoder_state is not None and trial.decoder is not None:
                trial.decoder.load_state_dict({k: torch.from_numpy(np.asarray(v)) for k, v in decoder_state.items()})
        out = []
        for cam in (chosen[v] for v in views):
            rgb = trial.render(cam, t=float(cam.time), background=background).rgb.numpy()
            gain, offset = corrections.get(str(cam.name), (1.0, 0.0))
            out.append(np.clip(rgb * gain + offset, 0.0, 1.0))
        return out

    fixed = {"POSI": position_bits} if position_bits else None
    with tqdm(total=1, desc="allocating bits", unit="trial", leave=False, disable=not show_progress) as bar:
        def progress(done: int, total: int) -> None:
            bar.total = total
            bar.n = done
            bar.refresh()

        return optimise_allocation(model.to_ply_arrays(), model.variant, model.decoder_state(), render, truth, budget_db(quality),
                                   fixed_bits=fixed, outlier_guard=outlier_guard, progress=progress)
