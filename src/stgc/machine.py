"""What a timing was measured on: the CPU as numba compiles for it, its widest vector instructions, the cores.

Two hosts of the project's one machine kind differed by 2x in the rasterizer's kernels (session 22: an AVX2-only
Zen 3 against an unrecorded earlier host). Numba compiles for the host CPU, so its model, LLVM target and vector
width belong with every timing. A wall time or an it/s without the machine it came from cannot be compared with
another, so training summaries and the benchmarks record this.
"""

from __future__ import annotations

import os
import platform
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import llvmlite.binding as llvm
import numba
import torch

# The OpenMP settings as torch's libgomp read them when it loaded (at the latest, during the import above; numba's
# loads at its first parallel call): what `openmp_wait` records, whatever the environment says later.
_OPENMP_AT_IMPORT = {key: os.environ[key] for key in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT") if key in os.environ}

# Widest first: the first feature the host has names its vector width.
_VECTOR_ISAS = (("avx512f", "avx512"), ("avx2", "avx2"), ("avx", "avx"), ("sse4.2", "sse4.2"),
                ("sve", "sve"), ("neon", "neon"))  # fmt: skip


def vector_isa(features: Mapping[str, bool]) -> str:
    """The widest vector instruction set among LLVM's host features ({"avx2": True, ...}); "scalar" if none."""
    for feature, name in _VECTOR_ISAS:
        if features.get(feature):
            return name
    return "scalar"


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def openmp_wait(environ: Mapping[str, str] | None = None) -> str:
    """How idle OpenMP threads wait between parallel regions: OMP_WAIT_POLICY (stgc sets "PASSIVE" on import) and
    GOMP_SPINCOUNT when the user set it, e.g. "PASSIVE" or "PASSIVE+GOMP_SPINCOUNT=3000". By default as they stood
    when this module imported torch, i.e. as libgomp read them. With a passive wait each parallel region wakes its
    sleeping threads (70-81 us a region on session 45's 2-CPU virtual machine); a spin count keeps them awake for
    a while instead (docs/rasterizer.md, "OpenMP wait policy"). Timings depend on it."""
    env = _OPENMP_AT_IMPORT if environ is None else environ
    policy = env.get("OMP_WAIT_POLICY", "unset")
    spin = env.get("GOMP_SPINCOUNT")
    return policy if spin is None else f"{policy}+GOMP_SPINCOUNT={spin}"


def describe() -> dict[str, Any]:
    """{cpu_model, cpu_target (LLVM's name for the host, what numba compiles for), vector_isa, cpus, openmp_wait}."""
    features = llvm.get_host_cpu_features()
    return {
        "cpu_model": _cpu_model(),
        "cpu_target": str(llvm.get_host_cpu_name()),
        "vector_isa": vector_isa({name: bool(features[name]) for name in features}),
        "cpus": os.cpu_count(),
        "openmp_wait": openmp_wait(),
    }


def one_line(machine: Mapping[str, Any] | None = None) -> str:
    """'AMD EPYC (znver3, avx2), 2 CPUs, OpenMP PASSIVE, load 1.23': the header line of a benchmark's output
    (a description from before openmp_wait was recorded has no OpenMP part)."""
    m = describe() if machine is None else machine
    wait = f", OpenMP {m['openmp_wait']}" if "openmp_wait" in m else ""
    return (f"{m['cpu_model']} ({m['cpu_target']}, {m['vector_isa']}), {m['cpus']} CPUs{wait}, "
            f"load {os.getloadavg()[0]:.2f}")


def use_threads(count: int) -> None:
    """torch's and the numba rasterizer's threads (count > 0; 0 leaves them as they are): a run's `train.threads`."""
    if count > 0:
        torch.set_num_threads(count)
        numba.set_num_threads(min(count, numba.config.NUMBA_NUM_THREADS))  # type: ignore[attr-defined]


@contextmanager
def threads(count: int) -> Iterator[None]:
    """`use_threads(count)` for a block, then the earlier counts again."""
    before = torch.get_num_threads(), numba.get_num_threads()
    use_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(before[0])
        numba.set_num_threads(before[1])
