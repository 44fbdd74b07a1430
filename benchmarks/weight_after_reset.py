"""What the blending weights rank right after an opacity reset (issue #17, item 5; compaction.reset_settle_steps).

Takes a trained run's final model and ranks its Gaussians by their blending weight summed over the training views
the trainer's weight order renders (`importance_views`), once as the model is and once with every opacity clamped
as an opacity reset clamps it (`train.densify.opacity_reset_value`, 0.01). Then removes the least-seen fraction by
each ranking, in one go (no training), and scores the test views of the model as it was (the reset is only in the
ranking). Prints the rank correlation of the two rankings (and of each with the Gaussians' size), and per fraction
how much of the two least-seen sets agree and the test PSNR after each removal. The run is not changed.

    .venv/bin/python benchmarks/weight_after_reset.py RUN --fractions 0.2,0.3,0.4,0.5
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from stgc.eval.evaluate import evaluate
from stgc.eval.video import load_model_and_dataset
from stgc.model import STGModel
from stgc.train.config import DensifyConfig
from stgc.train.loop import blending_weights, importance_views


def test_psnr(model: STGModel, dataset, background: torch.Tensor) -> float:  # type: ignore[no-untyped-def]
    result = evaluate(lambda cam: model.render(cam, t=float(cam.time), background=background).rgb, dataset.test,
                      dataset.load_image, warmup=0)
    return float(result.overall["psnr"])


def rank_correlation(a: torch.Tensor, b: torch.Tensor) -> float:
    """Spearman's rank correlation (ties broken by order: the weights are continuous)."""
    ranks = torch.stack([torch.argsort(torch.argsort(x)).double() for x in (a, b)])
    return float(torch.corrcoef(ranks)[0, 1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--fractions", default="0.2,0.3,0.4,0.5", help="fractions of the Gaussians removed")
    parser.add_argument("--reset-value", type=float, default=DensifyConfig().opacity_reset_value)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    model, dataset = load_model_and_dataset(args.run)
    background = torch.tensor(dataset.background, dtype=torch.float32)
    views = importance_views(dataset.train)
    state, n = model.state_dict(), model.num_gaussians
    weights = {"as trained": blending_weights(model, views, background)}
    reset = STGModel.from_state_dict(state)
    reset.reset_opacity(args.reset_value)
    weights["after a reset"] = blending_weights(reset, views, background)
    size = model.scales.max(dim=1).values
    print(f"{n} Gaussians, {len(views)} weight views; rank correlation: as trained / after a reset "
          f"{rank_correlation(weights['as trained'], weights['after a reset']):.3f}, with the largest scale "
          f"{rank_correlation(weights['as trained'], size):.3f} / {rank_correlation(weights['after a reset'], size):.3f}")
    before = test_psnr(model, dataset, background)
    print(f"test PSNR before: {before:.3f} dB\n")
    print("| removed | least-seen sets agree | test dB, ranked as trained | after a reset | drop as trained | after a reset |")
    print("|---:|---:|---:|---:|---:|---:|")
    for fraction in (float(x) for x in args.fractions.split(",")):
        count = int(fraction * n)
        least = {name: torch.argsort(w)[:count] for name, w in weights.items()}
        agree = len(set(least["as trained"].tolist()) & set(least["after a reset"].tolist())) / max(count, 1)
        scores = []
        for name in weights:
            pruned = STGModel.from_state_dict(state)
            keep = torch.ones(n, dtype=torch.bool)
            keep[least[name]] = False
            pruned.prune(keep)
            scores.append(test_psnr(pruned, dataset, background))
        print(f"| {fraction:.0%} | {agree:.0%} | {scores[0]:.3f} | {scores[1]:.3f} | {scores[0] - before:+.3f} | "
              f"{scores[1] - before:+.3f} |", flush=True)


if __name__ == "__main__":
    main()
