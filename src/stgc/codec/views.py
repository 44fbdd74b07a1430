"""The rd-optimised bit allocation measured on a model's own training views (what `compress_run` and rate-aware
training both use): renders for `stgc.codec.allocation.optimise_allocation`."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numba
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
                      outlier_guard: bool = True, adaptive_delta: bool = True, corrections: Corrections | None = None,
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

    @torch.no_grad()  # (per thread: the pool's workers need their own)
    def render_view(cam: Camera) -> np.ndarray:
        assert trial is not None
        rgb = trial.render(cam, t=float(cam.time), background=background).rgb.numpy()
        gain, offset = corrections.get(str(cam.name), (1.0, 0.0))
        return np.clip(rgb * gain + offset, 0.0, 1.0)

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
        cams = [chosen[v] for v in views]
        if not pools:  # the first call (the reference) renders in turn: numba has picked its threading layer after it
            images = [render_view(cam) for cam in cams]
            pools.append(stack.enter_context(_view_pool()))
            return images
        if pools[0] is None:
            return [render_view(cam) for cam in cams]
        return list(pools[0].map(render_view, cams))

    fixed = {"POSI": position_bits} if position_bits else None
    pools: list[ThreadPoolExecutor | None] = []
    with tqdm(total=1, desc="allocating bits", unit="trial", leave=False, disable=not show_progress) as bar, \
            contextlib.ExitStack() as stack:
        def progress(done: int, total: int) -> None:
            bar.total = total
            bar.n = done
            bar.refresh()

        return optimise_allocation(model.to_ply_arrays(), model.variant, model.decoder_state(), render, truth, budget_db(quality),
                                   fixed_bits=fixed, outlier_guard=outlier_guard, adaptive_delta=adaptive_delta,
                                   progress=progress)


@contextlib.contextmanager
def _view_pool() -> Iterator[ThreadPoolExecutor | None]:
    """Threads that render one view each, one thread per core torch may use, each single-threaded inside (torch
    and numba) for the block; None (render in turn) with one thread, or where numba's threading layer cannot run
    parallel kernels from several threads at once (its workqueue layer; omp and tbb can).

    At the allocation's sizes (a few hundred pixels square, tens of thousands of Gaussians) much of a render is
    per-Gaussian torch work on tensors too small for torch's own threads, so views side by side keep the cores
    busier than one view at a time with both (benchmarks/RESULTS.md, the codec's allocation trials). A pixel's
    colour does not depend on the number of threads: the images are the same either way."""
    workers = torch.get_num_threads()
    if workers < 2 or not _concurrent_kernels_safe():
        yield None
        return
    torch.set_num_threads(1)  # process-wide: restored below
    try:
        with ThreadPoolExecutor(workers, initializer=numba.set_num_threads, initargs=(1,)) as pool:  # per thread
            yield pool
    finally:
        torch.set_num_threads(workers)


def _concurrent_kernels_safe() -> bool:
    try:
        return numba.threading_layer() in ("omp", "tbb")
    except ValueError:  # no parallel kernel has run in this process, so none was chosen: do not guess
        return False
