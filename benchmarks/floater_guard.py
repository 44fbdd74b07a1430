"""What the scale rule of the floater control (`train.floaters.max_world_scale`) does to trained models, after the
fact: for each run, the Gaussians whose largest axis exceeds each threshold (a fraction of the scene radius,
`stgc.train.densify.scene_radius`) are dropped, and the test views are scored with and without them.

A held-out camera that looks past the surfaces the training views modelled can see a Gaussian larger than the scene
as a haze over the whole image (issue #14: panoptic cameras fogged at 12-25 dB). Prints one row per run and
threshold: Gaussians removed, test PSNR overall and per camera.

    .venv/bin/python benchmarks/floater_guard.py RUN [RUN ...] --thresholds 2 1 0.5 [--min-opacity 0.5]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from stgc import machine
from stgc.eval.evaluate import evaluate, open_run_dataset
from stgc.model import STGModel
from stgc.train.densify import prune_mask_floaters


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--thresholds", nargs="+", type=float, default=[2.0, 1.0, 0.5],
                        help="largest axis / scene radius above which a Gaussian is dropped")
    parser.add_argument("--min-opacity", type=float, default=0.0,
                        help="drop only Gaussians at least this opaque (train.floaters.scale_min_opacity)")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    machine.use_threads(args.threads)  # torch's and numba's (numba alone kept every core)
    print("| run | rule | Gaussians | removed | test PSNR dB | per camera |")
    print("|---|---|---:|---:|---:|---|")
    for run in args.runs:
        dataset = open_run_dataset(run)
        model = STGModel.load(run, scene_extent=dataset.scene_extent())
        centres = np.array([c.center for c in dataset.train], dtype=np.float64).reshape(-1, 3)
        background = torch.tensor(dataset.background, dtype=torch.float32)
        for threshold in [0.0, *args.thresholds]:
            remove = prune_mask_floaters(model, centres, near_camera=0.0, max_world_scale=threshold,
                                         scale_min_opacity=args.min_opacity)
            keep = (~remove).float()
            with torch.no_grad():
                result = evaluate(lambda cam: model.render(cam, t=float(cam.time), background=background,
                                                           opacity_scale=keep),
                                  dataset.test, dataset.load_image, warmup=0)
            cameras = " / ".join(f"{name} {score['psnr']:.2f}" for name, score in result.per_camera.items())
            rule = f"larger than {threshold:g} x scene radius" if threshold else "none"
            if threshold and args.min_opacity:
                rule += f", opacity >= {args.min_opacity:g}"
            print(f"| {run} | {rule} | {model.num_gaussians:,} | {int(remove.sum()):,} | {result.psnr:.2f} | "
                  f"{cameras} |", flush=True)


if __name__ == "__main__":
    main()
