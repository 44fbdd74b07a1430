"""Which Gaussians a held-out camera sees that the training views barely see: a diagnostic for a test view that one
run renders worse than another of the same data.

For each run, test camera and sampled frame, every Gaussian's blending weight (alpha x transmittance summed over the
pixels, `stgc.train.loop.blending_weights`) is summed over the test view and over all training views of the same
frame. A Gaussian whose weight in the one test view exceeds its weight in all the training views together is
constrained by almost nothing that training saw: a flat disc seen edge-on by the training cameras and face-on by the
test camera is the usual case. Prints per run and camera the share of the test view's weight such Gaussians hold
(mean over the frames that have both), then the run's largest one: its weight in the test view and in the training
views, its base opacity, axes (one standard deviation, world units) and canonical centre (not at the frame's time).

    .venv/bin/python benchmarks/test_view_only_gaussians.py RUN [RUN ...] [--frames 2 8 14 20 26] [--cameras 15]

A diagnostic only: nothing in training or evaluation looks at the test views.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from stgc import machine
from stgc.eval.video import load_model_and_dataset
from stgc.train.loop import blending_weights


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run directories (or iteration directories)")
    parser.add_argument("--frames", nargs="+", type=int, default=[2, 8, 14, 20, 26],
                        help="frames sampled (each test camera at each)")
    parser.add_argument("--cameras", nargs="+", default=None, help="test cameras (default: all)")
    args = parser.parse_args()
    print(machine.one_line())
    background = torch.zeros(3)
    print("| run | Gaussians | camera | test-only share of the view's weight (frames) | largest: weight test / "
          "train, base opacity, axes, canonical centre (frame) |")
    print("|---|---:|---|---:|---|")
    for run in args.runs:
        model, dataset = load_model_and_dataset(run)
        tested = sorted({str(c.name) for c in dataset.test}, key=lambda n: (len(n), n))
        unknown = sorted(set(args.cameras or ()) - set(tested))
        if unknown:
            raise SystemExit(f"{run}: no test camera {', '.join(unknown)} (test cameras: {', '.join(tested)})")
        opacity = torch.sigmoid(model.params["opacity"]).detach().numpy().ravel()
        axes = torch.exp(model.params["scaling"]).detach().numpy()
        centres = model.params["xyz"].detach().numpy()
        in_train: dict[int, np.ndarray] = {}  # per frame, summed over that frame's training views
        for name in args.cameras or tested:
            shares, largest = [], (0.0, 0.0, -1, -1)
            for frame in args.frames:
                test = next((c for c in dataset.test if str(c.name) == name and c.frame == frame), None)
                train = [c for c in dataset.train if c.frame == frame]
                if test is None or not train:  # monocular data: a frame's test view has no training view beside it
                    continue
                if frame not in in_train:
                    in_train[frame] = blending_weights(model, train, background).numpy()
                in_test = blending_weights(model, [test], background).numpy()
                test_only = in_test > in_train[frame]
                shares.append(in_test[test_only].sum() / max(in_test.sum(), 1e-12))
                excess = np.where(test_only, in_test, 0.0)
                top = int(np.argmax(excess))
                if excess[top] > largest[0]:
                    largest = (float(in_test[top]), float(in_train[frame][top]), top, frame)
            if not shares:
                print(f"| {run} | {model.num_gaussians:,} | {name} | no frame of {args.frames} with this test view "
                      "and training views | |", flush=True)
                continue
            weight, train_weight, row, frame = largest
            detail = "none" if row < 0 else (
                f"{weight:.0f} / {train_weight:.0f}, {opacity[row]:.2f}, {np.array2string(axes[row], precision=2)}, "
                f"{np.array2string(centres[row], precision=2)} ({frame})")
            print(f"| {run} | {model.num_gaussians:,} | {name} | {100 * float(np.mean(shares)):.2f} % "
                  f"({len(shares)}) | {detail} |", flush=True)


if __name__ == "__main__":
    main()
