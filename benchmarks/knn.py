"""One full spatiotemporal KNN matching step (the expensive part of a compaction step) against brute force.

Scene: a synthetic trained-looking STG model of N Gaussians: positions on the surfaces of 20 spheres inside a
[-2, 2]^3 box (scene extent 5), uniformly random rotations (the hardest case for the 7-D search: the rotation
coordinates spread as much as they can), 30 % dynamic Gaussians with cubic motion and angular velocity, mu_t uniform.
The timed step is `match_spatiotemporal_pairs(model, t, rotation_weight)`: evaluating the canonical and time-t
features, two exact nearest-neighbour searches (k-d trees), the agreement test and the pair merge. The step that
follows (`select_removals` at ratio 0.05) is timed separately. Wall seconds (best of --repeats) and the process CPU
seconds are both reported: on a shared machine the wall time grows with the load average, the CPU time much less.

Reference: the brute-force searches of `match_pairs_bruteforce` (torch.cdist in float64, exact arithmetic) cost the
same for every query row, so their time is measured on a random subsample of `--reference-rows` query rows of both
searches against all N Gaussians and scaled by N / rows (marked "estimated"); with `--full-reference-max N'` sizes up
to N' are run in full instead. The subsample's neighbours are also compared with the fast path's ("agree").

    .venv/bin/python benchmarks/knn.py [--sizes 100000 500000 1000000] [--rotation-weight 0.01]
        [--rotations random|near-identity] [--reference-rows 1000] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
import torch

from stgc import machine
from stgc.compaction import (
    match_pairs,
    match_pairs_bruteforce,
    nearest_other_bruteforce,
    select_removals,
    spacetime_features,
)
from stgc.compaction.matching import _workers, nearest_other
from stgc.model import STGModel


def synthetic_model(n: int, seed: int = 0, rotations: str = "random") -> STGModel:
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-2, 2, (20, 3))
    radii = rng.uniform(0.2, 1.0, 20)
    sphere = rng.integers(0, 20, n)
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    xyz = centres[sphere] + radii[sphere, None] * direction + rng.normal(scale=0.005, size=(n, 3))
    dynamic = rng.random(n) < 0.3
    params = {
        "xyz": xyz,
        "scaling": rng.normal(-5.0, 0.5, (n, 3)),
        # near-identity: what a short (CPU) schedule leaves, STG initialises every rotation to identity
        "rotation": rng.normal(size=(n, 4)) if rotations == "random" else [1, 0, 0, 0] + rng.normal(scale=0.1, size=(n, 4)),
        "omega": rng.normal(scale=0.3, size=(n, 4)) * dynamic[:, None],
        "opacity": rng.normal(size=(n, 1)),
        "trbf_center": rng.random((n, 1)),
        "trbf_scale": rng.normal(-1.0, 0.3, (n, 1)),
        "motion": rng.normal(scale=0.2, size=(n, 9)) * dynamic[:, None],
        "features_dc": rng.random((n, 3)),
    }
    tensors = {k: torch.as_tensor(v, dtype=torch.float32) for k, v in params.items()}
    return STGModel(tensors, "lite", scene_extent=5.0)


def time_fast(model: STGModel, t: float, rotation_weight: float, repeats: int):
    best, best_cpu = float("inf"), float("inf")
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        spaces = spacetime_features(model, t, rotation_weight)
        pairs = match_pairs(spaces)
        best = min(best, time.perf_counter() - start)
        best_cpu = min(best_cpu, time.process_time() - start_cpu)
    scores = model.params["trbf_center"].detach().double().numpy()[:, 0]
    start = time.perf_counter()
    selection = select_removals(pairs, 0.05, scores)
    prune_seconds = time.perf_counter() - start
    return best, best_cpu, spaces, pairs, selection, prune_seconds


def time_reference(spaces, pairs, n: int, rows: int, full_max: int, seed: int):
    if n <= full_max:
        start = time.perf_counter()
        reference = match_pairs_bruteforce(spaces)
        seconds = time.perf_counter() - start
        agree = bool(
            np.array_equal(reference.reference, pairs.reference) and np.array_equal(reference.partner, pairs.partner)
        )
        return seconds, False, n, agree
    sample = np.sort(np.random.default_rng(seed).choice(n, size=min(rows, n), replace=False))
    seconds = 0.0
    agree = True
    for features in spaces:
        start = time.perf_counter()
        ref_nn, _ = nearest_other_bruteforce(features, chunk=256, rows=sample)
        seconds += time.perf_counter() - start
        fast_nn, _ = nearest_other(features)  # untimed: only to check the subsample's answers
        agree &= bool(np.array_equal(fast_nn[sample], ref_nn))
    return seconds * n / sample.size, True, int(sample.size), agree


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[100_000, 500_000, 1_000_000])
    parser.add_argument("--rotation-weight", type=float, default=0.01)
    parser.add_argument("--t", type=float, default=0.37, help="current training time of the step")
    parser.add_argument("--repeats", type=int, default=3, help="fast path: best of this many runs")
    parser.add_argument("--reference-rows", type=int, default=1000, help="brute-force query rows per search")
    parser.add_argument("--full-reference-max", type=int, default=0, help="run brute force in full up to this N")
    parser.add_argument("--rotations", choices=["random", "near-identity"], default="random")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--json", action="store_true", help="one JSON object per line instead of a table")
    args = parser.parse_args()
    machine.use_threads(args.threads)  # torch's and numba's (numba alone kept every core)

    rows = []
    for n in args.sizes:
        model = synthetic_model(n, rotations=args.rotations)
        seconds, cpu_seconds, spaces, pairs, selection, prune_seconds = time_fast(model, args.t, args.rotation_weight, args.repeats)
        ref_seconds, estimated, ref_rows, agree = time_reference(
            spaces, pairs, n, args.reference_rows, args.full_reference_max, seed=n
        )
        rows.append(
            {
                "n": n,
                "seconds": round(seconds, 3),
                "cpu_seconds": round(cpu_seconds, 3),
                "reference_seconds": round(ref_seconds, 1),
                "reference_estimated": estimated,
                "reference_rows": ref_rows,
                "agree": agree,
                "matched_pairs": len(pairs),
                "prune_seconds": round(prune_seconds, 3),
                "removed_at_ratio_0.05": int(selection.remove.size),
                "rotation_weight": args.rotation_weight,
                "rotations": args.rotations,
                "threads": args.threads,
                "cpus": os.cpu_count(),
                "load_average_1min": round(os.getloadavg()[0], 2),
                "machine": machine.one_line(),
            }
        )
        if args.json:
            print(json.dumps(rows[-1]), flush=True)
    if not args.json:
        print(f"machine: {machine.one_line()}")
        print(f"ST-KNN matching step, rotation_weight {args.rotation_weight}, {args.rotations} rotations, "
              f"{args.threads} threads (torch, numba; the k-d tree queries use {_workers()})")
        print(f"{'N':>9} {'match s':>8} {'cpu s':>7} {'brute s':>10} {'speedup':>8} {'agree':>6} {'pairs':>8} {'prune s':>8} {'load':>5}")
        for r in rows:
            brute = f"{r['reference_seconds']:.1f}{'*' if r['reference_estimated'] else ''}"
            print(
                f"{r['n']:>9} {r['seconds']:>8.3f} {r['cpu_seconds']:>7.3f} {brute:>10} {r['reference_seconds'] / r['seconds']:>7.0f}x "
                f"{r['agree']!s:>6} {r['matched_pairs']:>8} {r['prune_seconds']:>8.3f} {r['load_average_1min']:>5.1f}"
            )
        if any(r["reference_estimated"] for r in rows):
            print("* estimated from a subsample of query rows (brute-force cost is the same for every row)")
        print("cpu s: process CPU time of the best run (all threads); load: 1-min load average of the machine")


if __name__ == "__main__":
    main()
