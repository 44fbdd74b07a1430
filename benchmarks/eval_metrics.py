"""SSIM cost in the training loss: stgc's SSIM vs the 3DGS formulation and a separable variant, fwd and bwd.

Images are random float32 [H, W, 3] pairs at the sizes given (default: 256x256, quarter- and half-resolution
N3DV 676x507 and 1352x1014). Timed: SSIM forward, and forward + backward with respect to the image (what the
trainer does every iteration). Implementations:
- stgc: `stgc.metrics.ssim`, the five local moments stacked and blurred by a separable numba kernel that is its own
  backward (CPU);
- 3DGS: the `loss_utils.ssim` structure, five grouped 11x11 convolutions (one per moment);
- separable: two torch 1-D convolutions (11x1 then 1x11) over the stacked moments, 22 instead of 121 taps per pixel.
All compute the same numbers (tests/metrics/test_metrics.py); |Δssim| is the largest difference to stgc's value. Wall seconds are the median of --repeats after
one warm-up call; process CPU seconds are also reported, since the machine may be shared.

    .venv/bin/python benchmarks/eval_metrics.py [--sizes 256x256 676x507 1352x1014] [--repeats 5] [--json]
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from collections.abc import Callable

import torch
import torch.nn.functional as F

from stgc import machine
from stgc.metrics import psnr, ssim


def ssim_2d_window(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """The 3DGS formulation: a full 11x11 window, one grouped conv per moment."""
    x, y = img.permute(2, 0, 1)[None], ref.permute(2, 0, 1)[None]
    c = x.shape[1]
    g = torch.tensor([math.exp(-((i - 5) ** 2) / (2 * 1.5**2)) for i in range(11)], dtype=x.dtype)
    g = g / g.sum()
    window = (g[:, None] @ g[None, :]).expand(c, 1, 11, 11).contiguous()

    def conv(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(t, window, padding=5, groups=c)

    mu1, mu2 = conv(x), conv(y)
    s11, s22, s12 = conv(x * x) - mu1**2, conv(y * y) - mu2**2, conv(x * y) - mu1 * mu2
    c1, c2 = 0.01**2, 0.03**2
    return (((2 * mu1 * mu2 + c1) * (2 * s12 + c2)) / ((mu1**2 + mu2**2 + c1) * (s11 + s22 + c2))).mean()


def ssim_separable(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Two 1-D zero-padded passes over the five stacked moments."""
    x, y = img.permute(2, 0, 1), ref.permute(2, 0, 1)
    c, h, w = x.shape
    g = torch.tensor([math.exp(-((i - 5) ** 2) / (2 * 1.5**2)) for i in range(11)], dtype=x.dtype)
    g = g / g.sum()
    stack = torch.stack([x, y, x * x, y * y, x * y]).reshape(5 * c, 1, h, w)
    out = F.conv2d(F.conv2d(stack, g.view(1, 1, 11, 1), padding=(5, 0)), g.view(1, 1, 1, 11), padding=(0, 5))
    mu1, mu2, e11, e22, e12 = out.reshape(5, c, h, w)
    s11, s22, s12 = e11 - mu1**2, e22 - mu2**2, e12 - mu1 * mu2
    c1, c2 = 0.01**2, 0.03**2
    return (((2 * mu1 * mu2 + c1) * (2 * s12 + c2)) / ((mu1**2 + mu2**2 + c1) * (s11 + s22 + c2))).mean()


def _time(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    fn()
    walls, cpus = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - w0)
        cpus.append(time.process_time() - c0)
    return statistics.median(walls), statistics.median(cpus)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", nargs="+", default=["256x256", "676x507", "1352x1014"], help="WxH")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--json", action="store_true", help="print one JSON object per row instead of a table")
    args = parser.parse_args()
    machine.use_threads(args.threads)  # torch's and numba's (numba alone kept every core)
    host = machine.one_line()  # the load before the timings
    gen = torch.Generator().manual_seed(0)
    rows = []
    for size in args.sizes:
        w, h = (int(v) for v in size.lower().split("x"))
        ref = torch.rand(h, w, 3, generator=gen)
        img = (ref + 0.1 * torch.randn(h, w, 3, generator=gen)).clamp(0, 1)
        value = float(ssim(img, ref))
        for name, fn in (("stgc", ssim), ("3DGS 5 convs", ssim_2d_window), ("separable", ssim_separable)):
            diff = abs(float(fn(img, ref)) - value)
            def forward(fn: Callable = fn) -> None:
                with torch.no_grad():
                    fn(img, ref)

            def forward_backward(fn: Callable = fn) -> None:
                x = img.clone().requires_grad_(True)
                fn(x, ref).backward()

            fw, fc = _time(forward, args.repeats)
            bw, bc = _time(forward_backward, args.repeats)
            rows.append({"size": f"{w}x{h}", "impl": name, "forward_ms": 1e3 * fw, "forward_cpu_ms": 1e3 * fc,
                         "fwd_bwd_ms": 1e3 * bw, "fwd_bwd_cpu_ms": 1e3 * bc, "max_abs_diff": diff})
        pw, _ = _time(lambda: psnr(img, ref), args.repeats)
        rows.append({"size": f"{w}x{h}", "impl": "psnr", "forward_ms": 1e3 * pw, "forward_cpu_ms": None,
                     "fwd_bwd_ms": None, "fwd_bwd_cpu_ms": None, "max_abs_diff": None})
    if args.json:
        for r in rows:
            print(json.dumps({**r, "threads": args.threads, "machine": host}))
        return
    print(f"machine: {host}, {args.threads} threads")
    print(f"{'size':>10} {'implementation':<18} {'fwd ms':>9} {'fwd cpu':>9} {'fwd+bwd ms':>11} {'f+b cpu':>9}"
          f" {'|Δssim|':>9}")
    for r in rows:
        def f(v: float | None, spec: str = "9.2f") -> str:
            return format(v, spec) if v is not None else format("-", ">" + spec.split(".")[0])

        print(f"{r['size']:>10} {r['impl']:<18} {f(r['forward_ms'])} {f(r['forward_cpu_ms'])} "
              f"{f(r['fwd_bwd_ms'], '11.2f')} {f(r['fwd_bwd_cpu_ms'])} {f(r['max_abs_diff'], '9.1e')}")


if __name__ == "__main__":
    main()
