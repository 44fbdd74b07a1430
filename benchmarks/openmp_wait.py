"""What the OpenMP wait policy costs: a parallel region's wake-up, and a training iteration, per GOMP_SPINCOUNT.

torch and numba each run a libgomp thread pool. stgc sets OMP_WAIT_POLICY=PASSIVE on import (an idle pool that
busy-waits steals the cores the other one needs; docs/rasterizer.md), so every parallel region wakes its sleeping
threads. GOMP_SPINCOUNT=N, set before stgc is imported, makes idle threads spin about N pauses first. This script
runs each setting in fresh processes (libgomp reads both variables once, when it loads):

    .venv/bin/python benchmarks/openmp_wait.py --spins 0 1000 3000
    .venv/bin/python benchmarks/openmp_wait.py --spins 0 3000 --data ../shared/data/blender_toys --model runs/RUN \
        --side-by-side

Per setting: microseconds per parallel region at 2 threads (a numba prange over 64 elements, and a torch add on
70,000 floats: both wake the pool's second thread and do almost no work), and with --data/--model the wall-clock ms
of a `cpu`-preset training iteration at 2 threads (the trainer `benchmarks/iteration_profile.py` builds, no
profiler, --iterations timed after 10 warm-up iterations); --side-by-side also runs two such processes at once, each
with 2 threads (more threads than CPUs on a 2-CPU machine: what a spinning thread costs its neighbours).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys

from stgc import machine

_REGIONS = r"""
import stgc  # first: its OMP_WAIT_POLICY must be set before torch loads libgomp
import time, numpy as np, numba, torch
from numba import njit, prange
@njit(parallel=True)
def touch(a):
    for i in prange(a.shape[0]):
        a[i] += 1.0
a, x = np.zeros(64), torch.zeros(70_000)
numba.set_num_threads(2); torch.set_num_threads(2)
touch(a); x.add_(1.0)
n = 2000
t0 = time.perf_counter()
for _ in range(n): touch(a)
t1 = time.perf_counter()
for _ in range(n): x.add_(1.0)
t2 = time.perf_counter()
print(f"{1e6 * (t1 - t0) / n:.1f} {1e6 * (t2 - t1) / n:.1f}")
"""

_ITERATION = r"""
import sys, tempfile, time
import stgc
from stgc import machine
from stgc.config import apply_overrides, parse_set_arguments
from stgc.model import STGModel
from stgc.options import resolve_configs
from stgc.train import Trainer
data, model_path, iterations = sys.argv[1], sys.argv[2], int(sys.argv[3])
machine.use_threads(2)
configs = resolve_configs("cpu", {}, {}, parse_set_arguments([]))
dataset = configs["data"].open(data)
model = STGModel.load(model_path, scene_extent=dataset.scene_extent())
with tempfile.TemporaryDirectory() as out:
    train_cfg = apply_overrides(configs["train"], {"progress": "false", "tensorboard": "false"})
    trainer = Trainer(dataset, configs["data"], configs["model"], train_cfg, None, out, model=model)
    start = trainer.schedule.iterations // 2  # past densification: the steady state
    for i in range(start, start + 10):
        trainer.train_step(i)
    t0 = time.perf_counter()
    for i in range(start + 10, start + 10 + iterations):
        trainer.train_step(i)
print(f"{(time.perf_counter() - t0) * 1e3 / iterations:.1f}")
"""


def _env(spin: int) -> dict[str, str]:
    env = {key: value for key, value in os.environ.items() if key not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    env["GOMP_SPINCOUNT"] = str(spin)  # stgc adds OMP_WAIT_POLICY=PASSIVE on import
    return env


def _run(code: str, args: list[str], spin: int, copies: int = 1) -> list[str]:
    procs = [subprocess.Popen([sys.executable, "-c", code, *args], env=_env(spin), stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for _ in range(copies)]  # fmt: skip
    outputs = []
    for proc in procs:
        out, err = proc.communicate()
        if proc.returncode != 0:
            raise SystemExit(f"a measuring process failed:\n{err[-2000:]}")
        outputs.append(out.strip().splitlines()[-1])
    return outputs


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--spins", type=int, nargs="+", default=[0, 1000, 3000], help="GOMP_SPINCOUNT values (0: passive)")
    ap.add_argument("--data", help="a dataset, to time training iterations too (with --model)")
    ap.add_argument("--model", help="a trained run or PLY: the Gaussians the iterations train")
    ap.add_argument("--iterations", type=int, default=60)
    ap.add_argument("--side-by-side", action="store_true", help="also time two training processes at once")
    args = ap.parse_args(argv)
    if (args.data is None) != (args.model is None):
        ap.error("--data and --model go together")

    print(f"machine: {machine.one_line()}")
    header = "| GOMP_SPINCOUNT | numba region us | torch region us |"
    if args.data:
        header += " iteration ms |" + (" iteration ms, two side by side |" if args.side_by_side else "")
    print(header + "\n|" + "---:|" * (header.count("|") - 1))
    for spin in args.spins:
        numba_us, torch_us = _run(_REGIONS, [], spin)[0].split()
        row = f"| {spin} | {numba_us} | {torch_us} |"
        if args.data:
            iteration = [args.data, args.model, str(args.iterations)]
            row += f" {_run(_ITERATION, iteration, spin)[0]} |"
            if args.side_by_side:
                row += " " + " / ".join(_run(_ITERATION, iteration, spin, copies=2)) + " |"
        print(row, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
