"""Peak resident memory of training iterations (issue #18, session 48): the per-view backward (before session 47)
against one backward per batch (render_views). Builds the trainer of benchmarks/iteration_profile.py (the
`cpu` preset on a trained model, half-way through the schedule), runs --warmup iterations, then samples the
process's RSS every millisecond over --iterations more and prints the RSS before them, the peak during them, and
the difference.

    PYTHONPATH=<commit>/src .venv/bin/python benchmarks/results/speed_s48/peak_rss.py <commit>/benchmarks \
        --data ../shared/data/panoptic_basketball --model runs/s39/pan-stg --threads 1
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import threading
import time


def rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("benchmarks", help="the benchmarks folder of the commit measured (its iteration_profile.py)")
    ap.add_argument("--data", required=True)
    ap.add_argument("--model", required=True)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--set", action="append", default=[])
    args = ap.parse_args()
    sys.path.insert(0, args.benchmarks)
    import torch
    from iteration_profile import parse_set_arguments, steady_state_trainer

    from stgc.options import resolve_configs

    torch.set_num_threads(args.threads)
    configs = resolve_configs("cpu", {}, {}, parse_set_arguments(args.set))
    with tempfile.TemporaryDirectory() as out:
        trainer, start = steady_state_trainer(args.data, args.model, configs, out)
        for i in range(args.warmup):
            trainer.train_step(start + i)
        before = rss_mib()
        peak = [before]
        done = threading.Event()

        def sample() -> None:
            while not done.is_set():
                peak[0] = max(peak[0], rss_mib())
                time.sleep(0.001)

        sampler = threading.Thread(target=sample)
        sampler.start()
        for i in range(args.iterations):
            trainer.train_step(start + args.warmup + i)
        done.set()
        sampler.join()
        trainer.close()
    print(f"batch {trainer.cfg.batch}, {trainer.model.num_gaussians} Gaussians: RSS before {before:.1f} MiB, "
          f"peak {peak[0]:.1f} MiB, +{peak[0] - before:.1f} MiB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
