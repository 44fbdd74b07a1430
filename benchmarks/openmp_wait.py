"""What the OpenMP wait policy costs: a parallel region's wake-up, and a training iteration, per GOMP_SPINCOUNT.

torch and numba each run a libgomp thread pool. stgc sets OMP_WAIT_POLICY=PASSIVE on import (an idle pool that
busy-waits steals the cores the other one needs; docs/rasterizer.md), so every parallel region wakes its sleeping
threads. GOMP_SPINCOUNT=N, set before stgc is imported, makes idle threads spin about N pauses first. This script
runs each setting in fresh processes (libgomp reads both variables once, when it loads):

    .venv/bin/python benchmarks/openmp_wait.py --spins 0 1000 3000
    .venv/bin/python benchmarks/openmp_wait.py --spins 0 3000 --data ../shared/data/blender_toys --model runs/RUN \
        --side-by-side

Per setting: microseconds per parallel region at --threads (a numba prange over 64 elements, and a torch add on
70,000 floats, which takes about 7 us on one thread: both wake the pools' other threads and do little work), and
with --data/--model the wall-clock ms of a `cpu`-preset training iteration at --threads (the trainer
`benchmarks/iteration_profile.py` builds, no profiler, --iterations timed after 10 warm-up iterations);
--side-by-side also runs two such processes at once, their timed iterations started together (with 2 threads each
on a 2-CPU machine: what a spinning thread costs its neighbours). The header's machine line leaves the OpenMP
setting out: each row sets its own.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile

from stgc import machine

_REGIONS = r"""
import stgc  # first: its OMP_WAIT_POLICY must be set before torch loads libgomp
import sys, time, numpy as np, numba, torch
from numba import njit, prange
@njit(parallel=True)
def touch(a):
    for i in prange(a.shape[0]):
        a[i] += 1.0
threads = int(sys.argv[1])
a, x = np.zeros(64), torch.zeros(70_000)
numba.set_num_threads(threads); torch.set_num_threads(threads)
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
import stgc  # first: its OMP_WAIT_POLICY must be set before torch loads libgomp
from stgc import machine
from stgc.config import parse_set_arguments
from stgc.options import resolve_configs
data, model_path, iterations, threads, benchmarks = sys.argv[1:6]
sys.path.insert(0, benchmarks)
from iteration_profile import steady_state_trainer
machine.use_threads(int(threads))
with tempfile.TemporaryDirectory() as out:
    trainer, start = steady_state_trainer(data, model_path, resolve_configs("cpu", {}, {}, parse_set_arguments([])), out)
    for i in range(start, start + 10):
        trainer.train_step(i)
    print("ready", flush=True)
    sys.stdin.readline()  # the parent starts every copy's timed iterations together
    t0 = time.perf_counter()
    for i in range(start + 10, start + 10 + int(iterations)):
        trainer.train_step(i)
print(f"{(time.perf_counter() - t0) * 1e3 / int(iterations):.1f}")
"""


def _env(spin: int) -> dict[str, str]:
    env = {key: value for key, value in os.environ.items() if key not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    env["GOMP_SPINCOUNT"] = str(spin)  # stgc adds OMP_WAIT_POLICY=PASSIVE on import
    return env


def _run(code: str, args: list[str], spin: int, copies: int = 1, synchronised: bool = False) -> list[str]:
    """The last stdout line of each of `copies` processes run at once. synchronised: each prints "ready" and waits
    for a line on stdin; all get it once all are ready."""
    with tempfile.TemporaryDirectory() as logs:
        errors = [open(os.path.join(logs, f"{i}.err"), "w+") for i in range(copies)]
        procs = [subprocess.Popen([sys.executable, "-c", code, *args], env=_env(spin), stdin=subprocess.PIPE,
                                  stdout=subprocess.PIPE, stderr=err, text=True) for err in errors]  # fmt: skip
        try:
            if synchronised:
                for proc in procs:
                    assert proc.stdout is not None
                    if proc.stdout.readline().strip() != "ready":
                        raise RuntimeError("a measuring process stopped before its timed iterations")
                for proc in procs:
                    assert proc.stdin is not None
                    proc.stdin.write("go\n")
                    proc.stdin.flush()
            outputs = [proc.communicate()[0].strip().splitlines() for proc in procs]
            if any(proc.returncode != 0 or not out for proc, out in zip(procs, outputs)):
                raise RuntimeError("a measuring process failed")
        except RuntimeError as exc:
            for proc in procs:
                proc.kill()
                proc.wait()
            messages = []
            for err in errors:
                err.seek(0)
                messages.append(err.read()[-2000:])
            raise SystemExit(f"{exc}:\n" + "\n".join(m for m in messages if m)) from None
        finally:
            for err in errors:
                err.close()
    return [out[-1] for out in outputs]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--spins", type=int, nargs="+", default=[0, 1000, 3000], help="GOMP_SPINCOUNT values (0: passive)")
    ap.add_argument("--data", help="a dataset, to time training iterations too (with --model)")
    ap.add_argument("--model", help="a trained run or PLY: the Gaussians the iterations train")
    ap.add_argument("--iterations", type=int, default=60)
    ap.add_argument("--side-by-side", action="store_true", help="also time two training processes at once")
    ap.add_argument("--threads", type=int, default=2, help="threads of torch and numba in every process")
    args = ap.parse_args(argv)
    if (args.data is None) != (args.model is None):
        ap.error("--data and --model go together")
    if args.threads < 1:
        ap.error("--threads must be >= 1")

    host = {key: value for key, value in machine.describe().items() if key != "openmp_wait"}
    print(f"machine: {machine.one_line(host)}, {args.threads} threads per process")
    header = "| GOMP_SPINCOUNT | numba region us | torch region us |"
    if args.data:
        header += " iteration ms |" + (" iteration ms, two side by side |" if args.side_by_side else "")
    print(header + "\n|" + "---:|" * (header.count("|") - 1))
    for spin in args.spins:
        numba_us, torch_us = _run(_REGIONS, [str(args.threads)], spin)[0].split()
        row = f"| {spin} | {numba_us} | {torch_us} |"
        if args.data:
            iteration = [args.data, args.model, str(args.iterations), str(args.threads),
                         os.path.dirname(os.path.abspath(__file__))]
            row += f" {_run(_ITERATION, iteration, spin, synchronised=True)[0]} |"
            if args.side_by_side:
                row += " " + " / ".join(_run(_ITERATION, iteration, spin, copies=2, synchronised=True)) + " |"
        print(row, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
