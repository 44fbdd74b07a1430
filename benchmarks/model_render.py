"""STGModel.render: what the temporal culling (drop Gaussians with temporal opacity < 1/255 before projection) buys.

For N Gaussians whose temporal centres μ_t are spread uniformly over [0, 1) with temporal width exp(s_t), render one
camera at t = 0.5 through `model.render` (culled) and through `stgc.render.rasterize` on all N Gaussians (unculled,
the official way), forward only and forward + backward. Prints a table; `--json` prints one JSON row per case.

    .venv/bin/python benchmarks/model_render.py [--sizes 20000 100000] [--widths 0.05 0.2 1.0] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from types import SimpleNamespace

import numpy as np
import torch

from stgc import machine
from stgc.data.cameras import Camera
from stgc.model import MIN_VISIBLE_OPACITY, STGModel
from stgc.render import rasterize


def make_model(count: int, temporal_width: float, variant: str, seed: int = 0) -> STGModel:
    rng = np.random.default_rng(seed)
    cloud = SimpleNamespace(
        xyz=np.column_stack([rng.uniform(-1.2, 1.2, count), rng.uniform(-0.9, 0.9, count), rng.uniform(-1, 1, count)]),
        rgb=rng.uniform(size=(count, 3)),
        time=rng.uniform(size=count),
    )
    model = STGModel.from_points(cloud, variant=variant, trbf_scale_init=float(np.log(temporal_width)))
    with torch.no_grad():
        model.params["opacity"].fill_(2.0)  # sigmoid 0.88: a trained scene's opaque Gaussians
    return model


def make_camera(width: int, height: int) -> Camera:
    focal = 0.9 * width
    K = np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
    w2c = np.eye(4)
    w2c[2, 3] = 3.0
    return Camera(name="bench", frame=0, time=0.5, K=K, w2c=w2c, width=width, height=height)


def render_unculled(model: STGModel, camera: Camera, t: float, backend: str) -> torch.Tensor:
    out = rasterize(
        model.means_at(t), model.rotations_at(t), model.scales, model.temporal_opacity(t), model.features_at(t),
        torch.tensor(camera.K, dtype=torch.float32), torch.tensor(camera.w2c, dtype=torch.float32),
        camera.width, camera.height, backend=backend,
    )
    return out.image


def timed(fn, repeats: int) -> tuple[float, float]:
    """(min wall ms, min process CPU ms). CPU time (all threads) is the figure to trust on a shared machine:
    waiting for a core inflates wall time but not CPU time."""
    fn()  # warm-up (JIT, caches)
    best_wall = best_cpu = float("inf")
    for _ in range(repeats):
        wall, cpu = time.perf_counter(), time.process_time()
        fn()
        best_wall = min(best_wall, time.perf_counter() - wall)
        best_cpu = min(best_cpu, time.process_time() - cpu)
    return best_wall * 1e3, best_cpu * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[20_000, 100_000])
    parser.add_argument("--widths", type=float, nargs="+", default=[0.05, 0.2, 1.0])
    parser.add_argument("--variant", default="full", choices=["full", "lite"])
    parser.add_argument("--backend", default="auto")
    parser.add_argument("--resolution", type=int, nargs=2, default=[256, 192], metavar=("W", "H"))
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2, help="torch and numba threads (1 makes CPU time robust)")
    parser.add_argument("--json", action="store_true", help="print one JSON object per case instead of the table")
    args = parser.parse_args()
    machine.use_threads(args.threads)  # torch's and numba's
    host = machine.one_line()  # the load before the timings
    camera = make_camera(*args.resolution)
    t = camera.time
    rows = []
    for count in args.sizes:
        for width in args.widths:
            model = make_model(count, width, args.variant)
            visible = int((model.temporal_opacity(t).detach() >= MIN_VISIBLE_OPACITY).sum())

            def culled_fwd():
                with torch.no_grad():
                    model.render(camera, backend=args.backend)

            def unculled_fwd():  # with the decoder, as culled_fwd (model.render) and unculled_bwd have it
                with torch.no_grad():
                    rgb = render_unculled(model, camera, t, args.backend)
                    if model.decoder is not None:
                        model.decoder(rgb, model._rays(camera, model._camera_tensors(camera)))

            def culled_bwd():
                model.render(camera, backend=args.backend).rgb.sum().backward()

            def unculled_bwd():
                rgb = render_unculled(model, camera, t, args.backend)
                if model.decoder is not None:
                    rgb = model.decoder(rgb, model._rays(camera, model._camera_tensors(camera)))
                rgb.sum().backward()

            row = {
                "variant": args.variant,
                "gaussians": count,
                "temporal_width": width,
                "rasterized": visible,
                "resolution": f"{camera.width}x{camera.height}",
                "load_1min": os.getloadavg()[0],
                "threads": args.threads,
                "machine": host,
            }
            for name, fn in (("fwd_culled", culled_fwd), ("fwd_all", unculled_fwd),
                             ("fwdbwd_culled", culled_bwd), ("fwdbwd_all", unculled_bwd)):
                row[f"{name}_ms"], row[f"{name}_cpu_ms"] = timed(fn, args.repeats)
            rows.append(row)
            if args.json:
                print(json.dumps(row), flush=True)
    if not args.json:
        print(f"machine: {host}")
        print(f"STGModel.render, {args.variant}, {camera.width}x{camera.height}, t=0.5, min of {args.repeats}, "
              f"torch threads {torch.get_num_threads()}; wall ms / process CPU ms")
        print("| N | exp(s_t) | rasterized | fwd culled | fwd all | fwd+bwd culled | fwd+bwd all | load |")
        print("|---|---|---|---|---|---|---|---|")
        for r in rows:
            cells = [f"{r[f'{n}_ms']:.0f} / {r[f'{n}_cpu_ms']:.0f}" for n in ("fwd_culled", "fwd_all", "fwdbwd_culled", "fwdbwd_all")]
            print(f"| {r['gaussians']} | {r['temporal_width']} | {r['rasterized']} | " + " | ".join(cells)
                  + f" | {r['load_1min']:.1f} |")


if __name__ == "__main__":
    main()
