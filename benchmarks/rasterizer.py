"""Rasterizer benchmark: forward and forward+backward time and peak extra memory of every backend.

Backends: numba and torch (stgc.render) and the gsplat 1.5.3 pure-PyTorch reference made to run on CPU (the test
oracle in tests/render/gsplat_oracle.py). Every timing covers the whole pipeline from 3D parameters (projection,
binning, compositing); "fwd" runs under no_grad, "fwd+bwd" backpropagates (image * R).sum() to means, quats, scales,
opacities and features. Times are medians over repeats after one warm-up call (also reported: the minimum, and the
median process CPU time summed over threads, which is far less sensitive to other jobs on a shared machine);
extra_mb is the peak resident memory during one further call above the resident memory just before it (sampled every
millisecond by a thread; the numba kernels release the GIL).

Scene (as in the reference measurements): N Gaussians at depth U[3, 7] spread over the frustum (+10%), per-axis pixel
sigma log-uniform in [1.7, 10], random rotations, opacity U[0.05, 0.95], features U[0, 1]; pinhole with the focal
length equal to the image width.

    .venv/bin/python benchmarks/rasterizer.py            # everything: N 10k/50k/200k x 256x256, 320x180 x C 3/9
    .venv/bin/python benchmarks/rasterizer.py --quick    # 10k/50k, 256x256, C 9, numba + torch + reference
    .venv/bin/python benchmarks/rasterizer.py --n 50000 --size 256x256 --channels 9 --backends numba --json
    .venv/bin/python benchmarks/rasterizer.py --n 50000 --size 256x256 --channels 9 --backends numba --stages

--stages splits the numba fwd+bwd into its kernel calls (each entry point of stgc.render._numba_kernels and
_numba_projection wrapped with a wall-clock timer; "glue" is the rest of the call: packing, torch's autograd, the
input checks), medians per stage over the timed repeats.
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import json
import os
import statistics
import sys
import threading
import time
from pathlib import Path

# torch (its bundled libgomp) and numba's OpenMP layer each keep a pool of threads that busy-wait between parallel
# regions by default. On 2 shared cores those spinning threads steal the cores from the ones doing work: measured
# here, one numba render at 50k Gaussians took 5 s with the default policy and 0.28 s with PASSIVE under the same
# machine load. Must be set before torch is imported; export OMP_WAIT_POLICY=ACTIVE to measure the default.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))
sys.path.insert(0, str(REPO / "tests"))

from stgc import machine
from stgc.render import rasterize

# The gsplat reference's tile intersection is a Python loop (~85 us per Gaussian): above this many Gaussians a single
# call takes longer than the whole rest of the benchmark, so it is skipped (reported as such in the table).
REFERENCE_MAX_N = 50_000


def make_scene(n: int, width: int, height: int, channels: int, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    focal = float(width)
    cx, cy = width / 2, height / 2
    z = 3 + 4 * torch.rand(n, generator=g)
    u = (torch.rand(n, generator=g) * 1.2 - 0.1) * width
    v = (torch.rand(n, generator=g) * 1.2 - 0.1) * height
    means = torch.stack([(u - cx) / focal * z, (v - cy) / focal * z, z], -1)
    sigma_px = torch.exp(torch.log(torch.tensor(1.7)) + torch.log(torch.tensor(10 / 1.7)) * torch.rand(n, 3, generator=g))
    return {
        "means": means,
        "quats": torch.randn(n, 4, generator=g),
        "scales": sigma_px * z[:, None] / focal,
        "opacities": 0.05 + 0.9 * torch.rand(n, generator=g),
        "features": torch.rand(n, channels, generator=g),
        "K": torch.tensor([[focal, 0, cx], [0, focal, cy], [0, 0, 1.0]]),
        "viewmat": torch.eye(4),
    }


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _release_free_heap() -> None:
    """Return freed heap pages to the OS (glibc keeps them otherwise), so that RSS growth shows a call's real peak."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


class PeakRSS:
    """Peak RSS above the starting RSS, sampled by a thread (numba kernels release the GIL, torch ops too)."""

    def __enter__(self):
        gc.collect()
        _release_free_heap()
        self.base = _rss_mb()
        self.peak = self.base
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def _run(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, _rss_mb())
            time.sleep(0.001)

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, _rss_mb())

    @property
    def extra_mb(self) -> float:
        return self.peak - self.base


def _render_fn(backend: str, width: int, height: int):
    if backend == "reference":
        from render.gsplat_oracle import gsplat_reference

        return lambda p: gsplat_reference(p["means"], p["quats"], p["scales"], p["opacities"], p["features"], p["K"],
                                          p["viewmat"], width, height)["image"]  # fmt: skip
    alpha_max = 0.99
    return lambda p: rasterize(p["means"], p["quats"], p["scales"], p["opacities"], p["features"], p["K"],
                               p["viewmat"], width, height, backend=backend, alpha_max=alpha_max).image  # fmt: skip


def measure(backend: str, n: int, width: int, height: int, channels: int, repeats: int) -> dict:
    scene = make_scene(n, width, height, channels)
    render = _render_fn(backend, width, height)
    weights = torch.rand(height, width, channels, generator=torch.Generator().manual_seed(1))
    grad_keys = ("means", "quats", "scales", "opacities", "features")

    def fwd():
        with torch.no_grad():
            render(scene)

    def fwdbwd():
        params = {k: (v.clone().requires_grad_(True) if k in grad_keys else v) for k, v in scene.items()}
        (render(params) * weights).sum().backward()

    row = {"backend": backend, "n": n, "channels": channels, "width": width, "height": height}
    for name, fn in (("fwd", fwd), ("fwdbwd", fwdbwd)):
        fn()  # warm-up: JIT/cache load, allocator
        times, cpu = [], []
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            times.append((time.perf_counter() - t0) * 1e3)
            cpu.append((time.process_time() - c0) * 1e3)
        with PeakRSS() as mem:  # a separate call, so the sampling thread does not perturb the timings
            fn()
        row[f"{name}_ms"] = round(statistics.median(times), 1)
        row[f"{name}_min_ms"] = round(min(times), 1)
        row[f"{name}_cpu_ms"] = round(statistics.median(cpu), 1)
        row[f"{name}_extra_mb"] = round(mem.extra_mb, 1)
    row["extra_mb"] = max(row["fwd_extra_mb"], row["fwdbwd_extra_mb"])
    row["repeats"] = repeats
    return row


# The numba backend's kernel entry points, as the stage names of --stages. numba_backend reaches them through their
# modules' attributes at call time, so wrapping the attributes times every call.
STAGES = {
    "projection fwd": ("_numba_projection", "project_forward"),
    "projection bwd": ("_numba_projection", "project_backward"),
    "depth order": ("_numba_kernels", "ids_with_a_tile", "radix_argsort"),
    "binning": ("_numba_kernels", "bin_tiles"),
    "compositing fwd": ("_numba_kernels", "composite_forward"),
    "compositing bwd": ("_numba_kernels", "composite_backward"),
    "sum rows": ("_numba_kernels", "sum_rows"),
}


def measure_stages(n: int, width: int, height: int, channels: int, repeats: int) -> dict:
    """Per-stage wall time of the numba fwd+bwd (medians over `repeats` calls after a warm-up)."""
    import importlib

    spent: dict[str, float] = {}
    originals = []

    def timed(stage, fn):
        def wrapper(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                spent[stage] = spent.get(stage, 0.0) + (time.perf_counter() - t0) * 1e3

        return wrapper

    for stage, (module_name, *names) in STAGES.items():
        module = importlib.import_module(f"stgc.render.{module_name}")
        for name in names:
            originals.append((module, name, getattr(module, name)))
            setattr(module, name, timed(stage, getattr(module, name)))
    try:
        scene = make_scene(n, width, height, channels)
        render = _render_fn("numba", width, height)
        weights = torch.rand(height, width, channels, generator=torch.Generator().manual_seed(1))
        grad_keys = ("means", "quats", "scales", "opacities", "features")
        per_call: list[dict[str, float]] = []
        for i in range(repeats + 1):
            params = {k: (v.clone().requires_grad_(True) if k in grad_keys else v) for k, v in scene.items()}
            spent.clear()
            t0 = time.perf_counter()
            (render(params) * weights).sum().backward()
            total = (time.perf_counter() - t0) * 1e3
            if i:  # the first call is the warm-up
                per_call.append({**spent, "glue": total - sum(spent.values()), "total": total})
    finally:
        for module, name, fn in originals:
            setattr(module, name, fn)
    stages = [*STAGES, "glue", "total"]
    return {s: round(statistics.median(c.get(s, 0.0) for c in per_call), 1) for s in stages}


def _fmt_ratio(ref: float | None, x: float) -> str:
    return "-" if ref is None else f"{ref / x:.1f}x"


def print_table(rows: list[dict], skipped: list[str]) -> None:
    ref = {(r["n"], r["channels"], r["width"], r["height"]): r for r in rows if r["backend"] == "reference"}
    header = ("| backend | N | C | size | fwd ms med (min) | fwd+bwd ms med (min) | fwd+bwd CPU ms | extra MB "
              "| fwd vs ref | fwd+bwd vs ref | repeats |")  # fmt: skip
    print(header)
    print("|" + "---|" * (header.count("|") - 1))
    for r in rows:
        rr = ref.get((r["n"], r["channels"], r["width"], r["height"]))
        print(
            f"| {r['backend']} | {r['n'] // 1000}k | {r['channels']} | {r['width']}x{r['height']} "
            f"| {r['fwd_ms']:.0f} ({r['fwd_min_ms']:.0f}) | {r['fwdbwd_ms']:.0f} ({r['fwdbwd_min_ms']:.0f}) "
            f"| {r['fwdbwd_cpu_ms']:.0f} | {r['extra_mb']:.0f} | {_fmt_ratio(rr and rr['fwd_ms'], r['fwd_ms'])} "
            f"| {_fmt_ratio(rr and rr['fwdbwd_ms'], r['fwdbwd_ms'])} | {r['repeats']} |"
        )
    for line in skipped:
        print(f"note: {line}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="10k and 50k Gaussians, 256x256, C=9 only")
    parser.add_argument("--n", type=int, nargs="+", default=[10_000, 50_000, 200_000], help="Gaussian counts")
    parser.add_argument("--size", nargs="+", default=["256x256", "320x180"], help="image sizes WxH")
    parser.add_argument("--channels", type=int, nargs="+", default=[3, 9], help="feature channels")
    parser.add_argument("--backends", nargs="+", default=["numba", "torch", "reference"],
                        choices=["numba", "torch", "reference"], help="what to run")  # fmt: skip
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats (the reference uses fewer, see --ref-repeats)")
    parser.add_argument("--ref-repeats", type=int, default=2, help="timed repeats of the slow gsplat reference")
    parser.add_argument("--torch-repeats", type=int, default=None, help="timed repeats of the torch backend "
                        "(default: --repeats; it takes seconds per call at 200k)")  # fmt: skip
    parser.add_argument("--ref-max-n", type=int, default=REFERENCE_MAX_N,
                        help="skip the reference above this many Gaussians")  # fmt: skip
    parser.add_argument("--threads", type=int, default=2, help="torch and numba threads")
    parser.add_argument("--tile-size", type=int, default=None, help="numba tile edge in pixels (default: the library's)")
    parser.add_argument("--json", action="store_true", help="also print one JSON object per measurement")
    parser.add_argument("--stages", action="store_true", help="numba only: per-stage split of fwd+bwd (see above)")
    args = parser.parse_args(argv)
    if args.quick:
        args.n, args.size, args.channels = [10_000, 50_000], ["256x256"], [9]

    torch.set_num_threads(args.threads)
    import numba

    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))  # (NUMBA_NUM_THREADS caps it)
    if args.tile_size is not None:
        from stgc.render import numba_backend

        numba_backend.TILE_SIZE = args.tile_size
    print(f"# machine: {machine.one_line()}")
    print(f"# load average before: {os.getloadavg()}, threads: {args.threads}, torch {torch.__version__}, "
          f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}, numba tile {args.tile_size or 'default'}")
    if args.stages:
        print("| N | C | size | threads | " + " | ".join(f"{s} ms" for s in [*STAGES, "glue", "total"]) + " |")
        print("|" + "---|" * (len(STAGES) + 6))
        for size in args.size:
            width, height = (int(v) for v in size.lower().split("x"))
            for channels in args.channels:
                for n in args.n:
                    split = measure_stages(n, width, height, channels, args.repeats)
                    if args.json:
                        print(json.dumps({"n": n, "channels": channels, "size": size, **split}), flush=True)
                    print(f"| {n // 1000}k | {channels} | {size} | {args.threads} | "
                          + " | ".join(f"{v:.1f}" for v in split.values()) + " |", flush=True)  # fmt: skip
        print(f"# load average after: {os.getloadavg()}")
        return 0
    rows, skipped = [], []
    for size in args.size:
        width, height = (int(v) for v in size.lower().split("x"))
        for channels in args.channels:
            for n in args.n:
                for backend in args.backends:
                    if backend == "reference" and n > args.ref_max_n:
                        skipped.append(f"reference skipped at N={n} {size} C={channels}: its Python tile "
                                       f"intersection loop alone takes ~{n * 85e-6:.0f} s per call")  # fmt: skip
                        continue
                    repeats = {"reference": args.ref_repeats, "torch": args.torch_repeats or args.repeats}.get(
                        backend, args.repeats
                    )
                    row = measure(backend, n, width, height, channels, repeats)
                    rows.append(row)
                    if args.json:
                        print(json.dumps(row), flush=True)
                    else:
                        print(f"# {row}", file=sys.stderr, flush=True)
    print(f"# load average after: {os.getloadavg()}")
    print_table(rows, skipped)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
