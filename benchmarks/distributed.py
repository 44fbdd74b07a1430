"""Ray's overhead on a whole video: the same segments trained in this process, one after another, and as tasks on a
local Ray, in one run.

Each segment asks for the whole machine (train.threads=0), so on Ray too they run one at a time and the two wall
times compare like with like. A warm-up first fills stgc's triangulation cache, so neither timed run triangulates. Overhead = Ray wall - in-process wall: starting Ray, a worker per task (importing
torch and stgc, loading numba's cache), scheduling, and shutting down. It is mostly fixed per command and per
segment, so the share is also given for a real segment (the `cpu` preset's iterations, 9,000, from the measured
iteration rate).

    .venv/bin/python benchmarks/distributed.py ../shared/data/panoptic_basketball --frames 20 --segment-frames 10 \\
        --iterations 300
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import tempfile
import time
from pathlib import Path

from stgc import machine
from stgc.options import resolve_configs
from stgc.run import Run
from stgc.train.config import train_preset
from stgc.train.video import train_video

CPU_PRESET_ITERATIONS = train_preset("cpu").iterations


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data")
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--segment-frames", type=int, default=10)
    parser.add_argument("--iterations", type=int, default=300)
    parser.add_argument("--out", default=None, help="work folder (default: a temporary one, removed)")
    args = parser.parse_args()

    configs = resolve_configs("cpu", {}, {}, {
        "data.duration": str(args.frames), "train.iterations": str(args.iterations), "train.progress": "false",
        "train.tensorboard": "false", "train.eval_every": "0", "train.eval_at_end": "false", "train.threads": "0"})
    work = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="stgc-bench-ray-"))
    # Warm-up: the triangulated initial points land in stgc's cache, which both timed runs then read alike.
    warm = dict(configs, train=dataclasses.replace(configs["train"], iterations=1))
    train_video(args.data, warm, work / "warm-up", args.segment_frames, overwrite=True)
    walls = {}
    for mode, use_ray in (("in-process", False), ("ray", True)):
        out = work / mode
        shutil.rmtree(out, ignore_errors=True)
        start = time.perf_counter()
        train_video(args.data, configs, out, args.segment_frames, use_ray=use_ray)
        walls[mode] = time.perf_counter() - start
        segments = Run(out).segments()
        train_s = sum(float(s.read_summary()["wall_seconds"]) for s in segments)
        print(f"{mode:>10}: {len(segments)} segments, wall {walls[mode]:7.1f} s, training loops {train_s:7.1f} s")
    n = len(Run(work / "ray").segments())
    overhead = walls["ray"] - walls["in-process"]
    per_segment = overhead / n
    summaries = [s.read_summary() for s in Run(work / "in-process").segments()]
    it_per_s = sum(float(s["it_per_s"]) for s in summaries) / len(summaries)
    real_segment_s = CPU_PRESET_ITERATIONS / it_per_s
    print(f"\nRay overhead: {overhead:.1f} s in all, {per_segment:.1f} s per segment "
          f"({100 * overhead / walls['in-process']:.1f} % of this run's in-process wall)")
    print(f"per segment of {CPU_PRESET_ITERATIONS} iterations at {it_per_s:.2f} it/s ({real_segment_s / 60:.0f} min): "
          f"{100 * per_segment / real_segment_s:.2f} %")
    print(f"machine: {machine.one_line()}")
    if not args.out:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
