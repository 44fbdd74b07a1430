"""What a static per-frame export loses: each test camera rendered from the exported 3DGS PLY against the model's own
render at the same time, and both against the ground truth.

    .venv/bin/python benchmarks/export.py runs/RUN [--frames 0,15,29]

Prints a table: PSNR in dB of the static render against the model's render, and each against the ground truth. The
static splats are rendered at the model's near plane (what stgc culls at), and also at the near planes of the tools
that read the exports, 0.2 (the INRIA viewers) and 0.01 (gsplat, nerfstudio): where the model's is larger (Panoptic's
1.0) those show Gaussians the model never showed to its cameras.
"""

from __future__ import annotations

import argparse
import sys
import tempfile

import numpy as np
import torch

from stgc.eval.export import export_ply_frames, read_inria_ply, static_render_inputs
from stgc.metrics import psnr
from stgc.eval.video import load_model_and_dataset
from stgc.render import rasterize

VIEWER_NEAR_PLANES = (0.2, 0.01)  # the INRIA viewers'; gsplat's and nerfstudio's


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run")
    ap.add_argument("--frames", default=None, help="frames A,B,... (default: first, middle, last)")
    args = ap.parse_args(argv)
    model, dataset = load_model_and_dataset(args.run)
    frames = args.frames or ",".join(str(f) for f in sorted({dataset.frames[0], dataset.frames[len(dataset.frames) // 2],
                                                             dataset.frames[-1]}))
    background = torch.tensor(dataset.background, dtype=torch.float32)
    rows = []
    with tempfile.TemporaryDirectory() as out, torch.no_grad():
        for path in export_ply_frames(args.run, out, frames=frames):
            frame = int(path.stem.split("_")[1])
            static = static_render_inputs(read_inria_ply(path))
            for camera in [c for c in dataset.test if c.frame == frame]:
                own = model.render(camera, t=camera.time, background=background).rgb.clamp(0, 1)
                flat, *at_viewer_near = [
                    rasterize(**static, K=torch.tensor(camera.K, dtype=torch.float32),
                              viewmat=torch.tensor(camera.w2c, dtype=torch.float32), width=camera.width,
                              height=camera.height, background=background, near_plane=near).image.clamp(0, 1)
                    for near in (camera.near, *VIEWER_NEAR_PLANES)]
                gt = torch.from_numpy(np.asarray(dataset.load_image(camera))[..., :3].astype(np.float32) / 255.0)
                rows.append((camera.name, frame, float(psnr(flat, own)),
                             *(float(psnr(image, own)) for image in at_viewer_near),
                             float(psnr(own, gt)), float(psnr(flat, gt))))
    print(f"{dataset.name}, {model.variant} model, {model.num_gaussians} Gaussians, near plane {dataset.near_plane:g}")
    print("| camera | frame | static vs model render | the same, static at near "
          + " | the same, static at near ".join(f"{near:g}" for near in VIEWER_NEAR_PLANES)
          + " | model vs ground truth | static vs ground truth |")
    print("|---|---:|" + "---:|" * (3 + len(VIEWER_NEAR_PLANES)))
    for name, frame, *values in rows:
        print(f"| {name} | {frame} | " + " | ".join(f"{v:.2f}" for v in values) + " |")
    means = np.mean([r[2:] for r in rows], axis=0)
    print("| mean | | " + " | ".join(f"{v:.2f}" for v in means) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
