"""Where one training iteration's time goes: a split of `Trainer.train_step` into its parts.

    .venv/bin/python benchmarks/iteration_profile.py --data ../shared/data/panoptic_basketball --model runs/RUN
    .venv/bin/python benchmarks/iteration_profile.py --data ../shared/data/panoptic_basketball_640 --model runs/RUN

Builds the trainer `stgc train DATA --preset cpu` would build (a trained model from --model instead of the initial
points, so the Gaussian count is a trained one's), runs --warmup iterations, then profiles --iterations with
torch.profiler. Forward parts are timed through record_function scopes put around the functions that do them;
backward parts are autograd's own nodes (the rasterizer's and SSIM's hand-written backwards, and the rest of the
graph). Prints ms per iteration and share per part; `--json` adds one JSON row.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
import tempfile
import time
from collections import defaultdict

import torch
from torch.profiler import ProfilerActivity, profile, record_function

import stgc.render.numba_backend as numba_backend
from stgc import machine
from stgc.config import apply_overrides, parse_set_arguments
from stgc.errors import StgcError
from stgc.model import STGModel
from stgc.model.decoder import SandwichDecoder
from stgc.options import resolve_configs
from stgc.train import Trainer

# (scope label, owner, attribute): functions whose forward time becomes a labelled part.
SCOPES = [
    ("render (per-Gaussian formulas, culling)", STGModel, "render_views"),  # render() calls it too
    ("projection", numba_backend, "project_numba"),  # what the numba backend calls (api.project_gaussians is torch's)
    ("depth sort", numba_backend, "depth_order"),
    ("tile binning", numba_backend.kernels, "bin_tiles"),
    ("compositing forward", numba_backend.kernels, "composite_forward"),
    ("decoder forward", SandwichDecoder, "forward"),
    ("loss forward (L1 + SSIM)", Trainer, "view_loss"),
    ("backward", torch.Tensor, "backward"),
    ("optimizer step", torch.optim.Adam, "step"),
]
# The parent of each nested scope, so that every part is reported exclusive of the parts inside it.
PARENT = {"projection": "render (per-Gaussian formulas, culling)",
          "depth sort": "render (per-Gaussian formulas, culling)",
          "tile binning": "render (per-Gaussian formulas, culling)",
          "compositing forward": "render (per-Gaussian formulas, culling)",
          "decoder forward": "render (per-Gaussian formulas, culling)"}
BACKWARD_NODES = {"_NumbaCompositeBackward": "rasterizer backward", "_NumbaProjectionBackward": "projection backward",
                  "_SeparableBlurBackward": "SSIM backward",
                  "_SSIMMeanBackward": "SSIM backward"}


def _scoped(label, fn):
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with record_function(label):
            return fn(*args, **kwargs)

    return wrapper


def install_scopes() -> None:
    for label, owner, name in SCOPES:
        setattr(owner, name, _scoped(label, getattr(owner, name)))


def split(prof, iterations: int) -> tuple[dict[str, float], dict[str, float]]:
    """(ms per iteration of each part, exclusive; ms per iteration of the largest other backward nodes)."""
    inclusive: dict[str, float] = defaultdict(float)
    other_nodes: dict[str, float] = defaultdict(float)
    for event in prof.key_averages():
        name = event.key
        ms = event.cpu_time_total / 1000.0 / iterations
        if name in {label for label, _, _ in SCOPES}:
            inclusive[name] += ms
        elif name.startswith("autograd::engine::evaluate_function: "):
            node = name.split(": ", 1)[1]
            part = BACKWARD_NODES.get(node)
            if part:
                inclusive[part] += ms
            else:
                other_nodes[node] += ms
    parts = dict(inclusive)
    for child, parent in PARENT.items():
        parts[parent] = parts.get(parent, 0.0) - inclusive.get(child, 0.0)
    backward_known = sum(inclusive.get(p, 0.0) for p in BACKWARD_NODES.values())
    parts["backward"] = inclusive.get("backward", 0.0) - backward_known
    parts["autograd rest of the graph (backward)"] = parts.pop("backward")
    return parts, dict(sorted(other_nodes.items(), key=lambda kv: -kv[1])[:8])


def steady_state_trainer(data: str, model_path: str, configs: dict, out: str) -> tuple[Trainer, int]:
    """(the trainer `stgc train DATA --preset cpu` builds, on the trained model at `model_path` instead of the
    initial points, writing to `out`; the iteration to start at). configs: `resolve_configs("cpu", ...)`, as `stgc
    train --preset cpu --set ...` resolves them (an unknown section or key refused, not ignored). The start is half-way
    through the schedule, past densification's rounds: the steady state."""
    dataset = configs["data"].open(data)
    model = STGModel.load(model_path, scene_extent=dataset.scene_extent())
    train_cfg = apply_overrides(configs["train"], {"progress": "false", "tensorboard": "false"})
    trainer = Trainer(dataset, configs["data"], configs["model"], train_cfg, None, out, model=model)
    return trainer, trainer.schedule.iterations // 2


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True)
    ap.add_argument("--model", required=True, help="a trained run (its latest PLY) or a PLY: the Gaussians profiled")
    ap.add_argument("--set", action="append", default=[],
                    help="config override section.key=value, as `stgc train --set` (repeatable)")
    ap.add_argument("--warmup", type=int, default=10)
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)

    machine.use_threads(args.threads)  # torch's and numba's (numba alone kept every core)
    try:
        configs = resolve_configs("cpu", {}, {}, parse_set_arguments(args.set))
    except StgcError as exc:
        ap.error(str(exc))
    install_scopes()
    with tempfile.TemporaryDirectory() as out:
        trainer, start = steady_state_trainer(args.data, args.model, configs, out)
        dataset, model, train_cfg = trainer.dataset, trainer.model, trainer.cfg
        for i in range(start, start + args.warmup):
            trainer.train_step(i)
        t0 = time.perf_counter()
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            for i in range(start + args.warmup, start + args.warmup + args.iterations):
                trainer.train_step(i)
        wall_ms = (time.perf_counter() - t0) * 1000.0 / args.iterations
    parts, other_nodes = split(prof, args.iterations)
    parts["everything else (python, loop, bookkeeping)"] = wall_ms - sum(parts.values())
    view = dataset.train[0]
    print(f"machine: {machine.one_line()}")
    print(f"{dataset.name} {view.width}x{view.height}, {model.num_gaussians} Gaussians, batch {train_cfg.batch}, "
          f"{args.threads} threads, load {os.getloadavg()[0]:.2f}: {wall_ms:.1f} ms per iteration (profiled)")
    print("| part | ms per iteration | share |\n|---|---:|---:|")
    for name, ms in sorted(parts.items(), key=lambda kv: -kv[1]):
        print(f"| {name} | {ms:.1f} | {100 * ms / wall_ms:.0f} % |")
    print("largest other backward nodes (ms per iteration): "
          + ", ".join(f"{k} {v:.1f}" for k, v in other_nodes.items()))
    if args.json:
        print(json.dumps({"dataset": dataset.name, "resolution": f"{view.width}x{view.height}",
                          "gaussians": model.num_gaussians, "wall_ms": wall_ms, "parts_ms": parts,
                          "other_backward_nodes_ms": other_nodes}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
