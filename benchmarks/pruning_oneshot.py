"""What a pruning step's removals cost before any training repairs them (issue #17, item 5): ST-KNN pruning of a
trained run's model in one go, with no training between the steps, for each way of choosing and removing.

Each variant starts from the run's final model and prunes it step by step with the trainer's compaction step
(`STKNNCompactor`: ST-KNN pairs at a training frame drawn with a fixed seed, the timestamp criterion,
`keeper_time_coverage`, a fixed ratio of the matched pairs per step), until each target fraction of the Gaussians is gone, and scores the test views there.
Variants: `distance` (the paper: closest pairs first), `distance+merge` (the keeper takes its losers' opacity,
compaction.merge_opacity), `weight` and `weight+merge` (the pairs whose loser shows least first,
compaction.pair_order=weight: its blending weight summed over the training views the trainer would use).
Prints one row per variant and target: Gaussians left, test PSNR and its drop. The run is not changed.

    .venv/bin/python benchmarks/pruning_oneshot.py RUN --targets 0.1,0.2,0.3 --variants distance,weight+merge
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
import torch

from stgc.compaction import CompactionConfig, STKNNCompactor
from stgc.eval.evaluate import evaluate
from stgc.eval.video import load_model_and_dataset
from stgc.train.loop import blending_weights, importance_views

VARIANTS = ("distance", "distance+merge", "weight", "weight+merge")


def test_psnr(model, dataset, background) -> float:  # type: ignore[no-untyped-def]
    """Mean PSNR over the test views, as `stgc eval` scores them."""
    result = evaluate(lambda cam: model.render(cam, t=float(cam.time), background=background).rgb, dataset.test,
                      dataset.load_image, warmup=0)
    return float(result.overall["psnr"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--targets", default="0.1,0.2,0.3", help="fractions of the Gaussians removed, ascending")
    parser.add_argument("--variants", default=",".join(VARIANTS), help=f"comma-separated, of {', '.join(VARIANTS)}")
    parser.add_argument("--ratio", type=float, default=0.02, help="fraction of the matched pairs per step")
    parser.add_argument("--coverage", type=float, default=0.5, help="compaction.keeper_time_coverage")
    parser.add_argument("--seed", type=int, default=0, help="seed of the frames the steps match at")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    targets = [float(x) for x in args.targets.split(",")]
    variants = args.variants.split(",")
    unknown = sorted(set(variants) - set(VARIANTS))
    if unknown:
        parser.error(f"unknown variants {', '.join(unknown)}; choose from {', '.join(VARIANTS)}")

    print(f"{'variant':<16} {'removed':>8} {'Gaussians':>9} {'test dB':>8} {'drop dB':>8} {'seconds':>8}")
    for variant in variants:
        model, dataset = load_model_and_dataset(args.run)
        background = torch.tensor(dataset.background, dtype=torch.float32)
        views = importance_views(dataset.train)
        frames = sorted({float(cam.time) for cam in dataset.train})
        rng = np.random.default_rng(args.seed)
        start, started, iteration = model.num_gaussians, time.perf_counter(), 0
        before = test_psnr(model, dataset, background)
        print(f"{variant:<16} {0.0:>8.1%} {start:>9} {before:>8.2f} {0.0:>8.2f} {0.0:>8.0f}", flush=True)
        for target in targets:
            # The trainer's compaction step itself, at a fixed ratio on every iteration, stopping at the target.
            config = CompactionConfig(
                case=0, window_start=0.0, window_end=1.0, interval=1, ratio_init=args.ratio, ratio_min=args.ratio,
                ratio_max=args.ratio, criterion="timestamp", keeper_time_coverage=args.coverage,
                pair_order="weight" if variant.startswith("weight") else "distance",
                merge_opacity=variant.endswith("+merge"), min_gaussians=math.ceil(start * (1.0 - target)),
                loss_signal="training", loss_budget_db=0.0)  # the ratio is fixed: no signal to render
            compactor = STKNNCompactor(config, total_iterations=1 << 30)
            while model.num_gaussians > config.min_gaussians:
                iteration += 1
                event = compactor.step(iteration, float(rng.choice(frames)), model, 1.0,
                                       importance_fn=lambda: blending_weights(model, views, background))
                if event is not None and event["removed"] == 0 and event["selected_pairs"] > 0:
                    break  # nothing left that the rules let go
            score = test_psnr(model, dataset, background)
            print(f"{variant:<16} {1.0 - model.num_gaussians / start:>8.1%} {model.num_gaussians:>9} {score:>8.2f} "
                  f"{score - before:>8.2f} {time.perf_counter() - started:>8.0f}", flush=True)


if __name__ == "__main__":
    main()
