"""How much of a trained run's test PSNR is lost to each test camera's own colour (exposure, white balance).

    .venv/bin/python benchmarks/test_view_colour.py runs/RUN [--every 3] [--json]

Real rigs differ in colour from camera to camera. Training learns a gain and offset per *training* camera; a test
camera is rendered with the identity (the published Panoptic protocol), so a test camera whose colour is off the
training cameras' mean loses PSNR that no model can win back. This script measures that share, the way appearance
embeddings are scored in the literature (NeRF-W): per test camera, fit a gain and offset per channel on the left half
of its views (all its frames, or every `--every`-th), then score the right half with and without the fit. Fitting on
one half and scoring the other keeps the fitted number honest; the right half alone is scored both ways so the two
columns compare like with like. The "mean colour" columns are the right halves' mean RGB, render and ground truth.

A diagnostic only: `stgc eval` and every table keep the identity for test views.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from stgc import machine
from stgc.eval.evaluate import open_run_dataset
from stgc.metrics.image import psnr
from stgc.model import STGModel


def fit_affine(render: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares gain [3] and offset [3] with gain * render + offset ~ truth, per channel ([N, 3] inputs)."""
    gains, offsets = np.empty(3), np.empty(3)
    for c in range(3):
        design = np.stack([render[:, c], np.ones(len(render))], axis=1)
        (gains[c], offsets[c]), *_ = np.linalg.lstsq(design, truth[:, c], rcond=None)
    return gains, offsets


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="a trained run directory")
    ap.add_argument("--every", type=int, default=1, help="use every k-th frame of each test camera")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    machine.use_threads(args.threads)  # torch's and numba's (numba alone kept every core)

    dataset = open_run_dataset(args.run)
    model = STGModel.load(args.run)
    background = torch.tensor(dataset.background, dtype=torch.float32)
    halves: dict[str, list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]] = {}
    with torch.no_grad():
        for cam in dataset.test:
            if cam.frame % args.every:
                continue
            rgb = model.render(cam, t=float(cam.time), background=background)
            rgb = getattr(rgb, "rgb", rgb).clamp(0.0, 1.0).numpy().astype(np.float64)
            truth = dataset.load_image(cam)[..., :3].astype(np.float64) / 255.0
            mid = rgb.shape[1] // 2
            halves.setdefault(str(cam.name), []).append(
                (rgb[:, :mid].reshape(-1, 3), truth[:, :mid].reshape(-1, 3),
                 rgb[:, mid:].reshape(-1, 3), truth[:, mid:].reshape(-1, 3)))

    rows = []
    for name, views in sorted(halves.items()):
        gains, offsets = fit_affine(np.concatenate([v[0] for v in views]), np.concatenate([v[1] for v in views]))
        raw = float(np.mean([float(psnr(v[2], v[3])) for v in views]))
        fitted = float(np.mean([float(psnr(np.clip(v[2] * gains + offsets, 0.0, 1.0), v[3])) for v in views]))
        rows.append({"camera": name, "views": len(views), "psnr_right_half": round(raw, 2),
                     "psnr_right_half_colour_fitted": round(fitted, 2), "colour_share_db": round(fitted - raw, 2),
                     "gain": [round(float(g), 3) for g in gains], "offset": [round(float(o), 3) for o in offsets],
                     "mean_render": [round(float(x), 3) for x in np.concatenate([v[2] for v in views]).mean(0)],
                     "mean_truth": [round(float(x), 3) for x in np.concatenate([v[3] for v in views]).mean(0)]})
    mean_raw = float(np.mean([r["psnr_right_half"] for r in rows]))
    mean_fit = float(np.mean([r["psnr_right_half_colour_fitted"] for r in rows]))

    print(f"{args.run}: test cameras' right halves, identity vs a gain and offset fitted on the left halves")
    print("| camera | views | PSNR dB | colour-fitted | colour share dB | gain RGB | offset RGB | mean render | mean truth |")
    print("|---|---:|---:|---:|---:|---|---|---|---|")
    for r in rows:
        print(f"| {r['camera']} | {r['views']} | {r['psnr_right_half']:.2f} | {r['psnr_right_half_colour_fitted']:.2f} "
              f"| {r['colour_share_db']:+.2f} | {r['gain']} | {r['offset']} | {r['mean_render']} | {r['mean_truth']} |")
    print(f"| mean | | {mean_raw:.2f} | {mean_fit:.2f} | {mean_fit - mean_raw:+.2f} | | | | |")
    if args.json:
        print(json.dumps({"run": str(args.run), "cameras": rows, "mean_psnr_right_half": round(mean_raw, 3),
                          "mean_psnr_right_half_colour_fitted": round(mean_fit, 3)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
