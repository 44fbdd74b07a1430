"""Count the OpenMP parallel regions of a training iteration, and which torch ops open them.

With stgc's passive OpenMP wait every parallel region wakes a sleeping thread (about 75 us at 2 threads on the
machines measured, benchmarks/RESULTS.md session 45), so the number of regions an iteration opens is a cost of its
own, beside the arithmetic. This script counts them: it compiles a small shim (needs a C compiler: `cc`) that
stands in for libgomp's `GOMP_parallel` (the entry of every `#pragma omp parallel` that torch and numba's OpenMP layer
compile to; the older GOMP_parallel_start/_loop_* entries are not counted) through LD_PRELOAD, counts each call by its caller (torch, or numba's OpenMP
layer) and hands it to the libgomp the caller would have used (torch's bundled one: numba's layer binds to it too
once torch is loaded). A child process then runs the trainer `iteration_profile.py` builds (the `cpu` preset at its
steady state on a trained model) at 2 threads and reports the regions per iteration, and, under a
TorchDispatchMode, which torch op at which line of stgc opened them.

    .venv/bin/python benchmarks/openmp_regions.py --data ../shared/data/blender_toys --model runs/s39/bl-stg

Linux with glibc only. Counting changes no result; the timings of a counted run are not meaningful. The counters
are plain integers, incremented by the calling thread: regions opened from several threads at once (none in a
training iteration) could be miscounted.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import torch  # only to find its libgomp: the child process counts

_SHIM = r"""
#define _GNU_SOURCE
#include <dlfcn.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
typedef void (*gomp_parallel_t)(void (*)(void *), void *, unsigned, unsigned);
static gomp_parallel_t real;
static long torch_regions, numba_regions, other_regions;
long counted_torch(void) { return torch_regions; }
long counted_numba(void) { return numba_regions; }
long counted_other(void) { return other_regions; }
void GOMP_parallel(void (*fn)(void *), void *data, unsigned threads, unsigned flags) {
  Dl_info info;
  const char *caller = "";
  if (dladdr(__builtin_return_address(0), &info) && info.dli_fname) caller = info.dli_fname;
  if (strstr(caller, "omppool")) numba_regions++;
  else if (strstr(caller, "torch")) torch_regions++;
  else other_regions++;
  if (!real) {
    void *lib = dlopen(getenv("STGC_COUNTED_LIBGOMP"), RTLD_NOW | RTLD_NOLOAD);
    if (lib) real = (gomp_parallel_t)dlvsym(lib, "GOMP_parallel", "GOMP_4.0");
    if (!real) {  /* a NULL handle would find this function again */
      fprintf(stderr, "openmp_regions shim: GOMP_parallel not found in %s\n", getenv("STGC_COUNTED_LIBGOMP"));
      abort();
    }
  }
  real(fn, data, threads, flags);
}
"""

_CHILD = r"""
import collections, ctypes, sys, tempfile, traceback
import stgc  # first: its OMP_WAIT_POLICY must be set before torch loads libgomp
import torch
from torch.utils._python_dispatch import TorchDispatchMode
from stgc import machine
from stgc.config import parse_set_arguments
from stgc.options import resolve_configs
data, model_path, iterations, threads, benchmarks, top = sys.argv[1:7]
iterations, top = int(iterations), int(top)
sys.path.insert(0, benchmarks)
from iteration_profile import steady_state_trainer
shim = ctypes.CDLL(None)
for name in ("counted_torch", "counted_numba", "counted_other"):
    getattr(shim, name).restype = ctypes.c_long
machine.use_threads(int(threads))
per_line = collections.Counter()

class Attribute(TorchDispatchMode):
    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        before = shim.counted_torch()
        out = func(*args, **(kwargs or {}))
        opened = shim.counted_torch() - before
        if opened:
            frames = [f for f in traceback.extract_stack() if "/stgc/" in f.filename]
            where = (f"{frames[-1].filename.split('/stgc/')[-1]}:{frames[-1].lineno} {frames[-1].name}"
                     if frames else "(outside stgc)")
            per_line[f"{where} | {func.__name__}"] += opened
        return out

with tempfile.TemporaryDirectory() as out:
    trainer, start = steady_state_trainer(data, model_path, resolve_configs("cpu", {}, {}, parse_set_arguments([])), out)
    for i in range(start, start + 5):
        trainer.train_step(i)
    counts = [shim.counted_torch(), shim.counted_numba(), shim.counted_other()]
    for i in range(start + 5, start + 5 + iterations):
        trainer.train_step(i)
    counts = [(now - then) / iterations for now, then in
              zip((shim.counted_torch(), shim.counted_numba(), shim.counted_other()), counts)]
    with Attribute():
        for i in range(start + 5 + iterations, start + 5 + 2 * iterations):
            trainer.train_step(i)
view = trainer.dataset.train[0]
import numba
print(f"machine: {machine.one_line()}, numba threading layer {numba.threading_layer()} (only 'omp' regions are counted)")
print(f"{trainer.dataset.name} {view.width}x{view.height}, {trainer.model.num_gaussians} Gaussians, batch "
      f"{trainer.cfg.batch}, {threads} threads: regions per iteration: torch {counts[0]:.1f}, numba {counts[1]:.1f}, "
      f"other {counts[2]:.1f}")
print("| torch regions per iteration | where (stgc line, or the backward pass's line) | op |\n|---:|---|---|")
for key, count in per_line.most_common(top):
    where, op = key.split(" | ")
    print(f"| {count / iterations:.1f} | {where} | {op} |")
"""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True)
    ap.add_argument("--model", required=True, help="a trained run (its latest PLY) or a PLY: the Gaussians trained")
    ap.add_argument("--iterations", type=int, default=6)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--top", type=int, default=25, help="how many (line, op) rows to list")
    args = ap.parse_args(argv)
    if args.threads < 2:
        ap.error("--threads must be at least 2: at 1 thread torch and numba open no regions")
    compiler = shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        raise SystemExit("openmp_regions.py needs a C compiler (cc or gcc) to build its libgomp shim")
    libgomp = Path(torch.__file__).parent / "lib" / "libgomp.so.1"
    if not libgomp.exists():
        raise SystemExit(f"{libgomp}: torch's bundled libgomp not found (a torch build without OpenMP?)")
    with tempfile.TemporaryDirectory() as work:
        source, shim = Path(work) / "shim.c", Path(work) / "libcounted_gomp.so"
        source.write_text(_SHIM)
        subprocess.run([compiler, "-O2", "-shared", "-fPIC", str(source), "-o", str(shim), "-ldl"], check=True)
        env = dict(os.environ, LD_PRELOAD=str(shim), STGC_COUNTED_LIBGOMP=str(libgomp))
        benchmarks = str(Path(__file__).resolve().parent)
        done = subprocess.run([sys.executable, "-c", _CHILD, args.data, args.model, str(args.iterations),
                               str(args.threads), benchmarks, str(args.top)], env=env)  # fmt: skip
    return done.returncode


if __name__ == "__main__":
    sys.exit(main())
