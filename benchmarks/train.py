"""Train one STG model with a preset and report time, it/s, #Gaussians and test PSNR/SSIM.

    python benchmarks/train.py --data ../shared/data/blender_toys --preset cpu --out runs/toys_cpu
    python benchmarks/train.py --data ../shared/data/blender_toys --iterations 40 --json   # it/s only

Prints a table (and a JSON row with --json). `--iterations N` runs only N iterations of the preset's schedule
(no evaluation) to measure speed; without it the whole schedule runs and the test views are evaluated.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import torch

from stgc import machine
from stgc.options import PRESET_DATA_OVERRIDES
from stgc.config import apply_overrides, parse_set_arguments
from stgc.data import DataConfig
from stgc.eval import RunEvaluator
from stgc.model import ModelConfig
from stgc.train import Trainer, train_preset

HERE = Path(__file__).resolve().parent


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(HERE.parent.parent / "shared" / "data" / "blender_toys"))
    ap.add_argument("--preset", default="cpu", choices=["cpu", "paper"])
    ap.add_argument("--variant", default="full", choices=["full", "lite"])
    ap.add_argument("--downscale", type=float, default=1.0)
    ap.add_argument("--duration", type=int, default=None, help="train on the first N frames (default: all)")
    ap.add_argument("--init-every", type=int, default=None,
                    help="initial points from every k-th frame (default: the preset's, as `stgc train`)")
    ap.add_argument("--points-per-frame", type=int, default=None, help="default: the preset's, as `stgc train`")
    ap.add_argument("--iterations", type=int, default=None, help="speed run: stop after N iterations, no eval")
    ap.add_argument("--out", default=None, help="run directory (default: a temporary one under runs/)")
    ap.add_argument("--set", action="append", default=[], help="train config override key=value (repeatable)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)

    machine.use_threads(args.threads)  # torch's and numba's (numba alone kept every core)
    preset_data = PRESET_DATA_OVERRIDES[args.preset]
    init_every = args.init_every or int(preset_data.get("init_frames_every", 1))
    points_per_frame = args.points_per_frame or (int(preset_data["max_points_per_frame"])
                                                 if "max_points_per_frame" in preset_data else None)
    data_cfg = DataConfig(downscale=args.downscale, duration=args.duration, init_frames_every=init_every,
                          max_points_per_frame=points_per_frame)
    dataset = data_cfg.open(args.data)
    model_cfg = ModelConfig(variant=args.variant)
    cfg = apply_overrides(train_preset(args.preset), parse_set_arguments(args.set))
    overrides = {"threads": str(args.threads), **({"progress": "false"} if args.iterations else {})}
    if args.iterations:
        overrides.update({"stop_after": str(args.iterations), "checkpoint_every": "0"})
    cfg = apply_overrides(cfg, overrides)
    out = Path(args.out or f"runs/bench_train_{int(time.time())}")
    t0 = time.perf_counter()
    trainer = Trainer(dataset, data_cfg, model_cfg, cfg, None, out, evaluator=RunEvaluator())
    setup_s = time.perf_counter() - t0
    n0 = trainer.model.num_gaussians
    summary = trainer.run()
    row = {
        "dataset": dataset.name, "variant": args.variant, "preset": cfg.preset, "schedule_scale": cfg.schedule_scale,
        "resolution": f"{dataset.train[0].width}x{dataset.train[0].height}",
        "iterations": summary["iterations"], "train_s": summary["wall_seconds"],
        "it_per_s": round(summary["it_per_s"], 3), "gaussians_init": n0, "gaussians": summary["num_gaussians"],
        "test_psnr": summary.get("test_psnr"), "test_ssim": summary.get("test_ssim"), "setup_s": round(setup_s, 1),
        "load_avg_1min": os.getloadavg()[0],
        "machine": machine.one_line(summary["machine"]),
    }
    width = max(len(k) for k in row)
    for k, v in row.items():
        print(f"{k:<{width}}  {v}")
    if args.json:
        print(json.dumps(row))
    return 0


if __name__ == "__main__":
    sys.exit(main())
