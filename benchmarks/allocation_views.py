"""How many views the rd allocation's table trials and step-shape probes render, and where the table's depth sweep
stops (issue #18): for each trained run and each setting, compress at a quality and evaluate the decoded file on the
test views.
Prints one row per run and setting: wall and CPU seconds of the compress call, bytes, test PSNR of the decoded model,
and the differences against the first setting. The files are written into each run as
`alloc_views_<setting>_q<Q>.stgc` (their eval files beside them) and removed afterwards unless --keep. A setting is
TABLE,PROBE[,NEGLIGIBLE] (view counts, and the fraction of the budget below which the sweep stops going finer).

    .venv/bin/python benchmarks/allocation_views.py RUN [RUN ...] --settings 8,8,1e-3 8,4,1e-2 --quality 3
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from stgc import machine
from stgc.codec import allocation
from stgc.codec.files import compress_run
from stgc.eval.evaluate import evaluate_run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--settings", nargs="+", default=["8,8,1e-3", "8,4,1e-3"], help="TABLE,PROBE[,NEGLIGIBLE]")
    parser.add_argument("--quality", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--keep", action="store_true")
    args = parser.parse_args()
    machine.use_threads(args.threads)  # torch's and numba's (numba alone kept every core)
    print(f"machine: {machine.one_line()}, {args.threads} threads")
    print("| run | table views | probe views | negligible | wall s | CPU s | bytes | test PSNR dB | bytes vs first | "
          "PSNR vs first |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for run in args.runs:
        first = None
        for setting in args.settings:
            fields = setting.split(",")
            table, probe = int(fields[0]), int(fields[1])
            negligible = float(fields[2]) if len(fields) > 2 else allocation._NEGLIGIBLE
            allocation._TABLE_VIEWS, allocation._PROBE_VIEWS, allocation._NEGLIGIBLE = table, probe, negligible
            out = run / f"alloc_views_t{table}_p{probe}_n{negligible:g}_q{args.quality}.stgc"
            wall, cpu = time.perf_counter(), time.process_time()
            result = compress_run(run, out, quality=args.quality)
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
            psnr = float(evaluate_run(out, measure_fps=False)["psnr"])
            size = out.stat().st_size
            first = first or (size, psnr)
            print(f"| {run} | {table} | {probe} | {negligible:g} | {wall:.1f} | {cpu:.1f} | {size:,} | {psnr:.3f} | "
                  f"{100 * (size / first[0] - 1):+.2f} % | {psnr - first[1]:+.3f} |", flush=True)
            assert result.file_bytes == size
            if not args.keep:
                for leftover in run.glob(f"{out.stem}*"):
                    leftover.unlink()
                for leftover in run.glob(f"eval_{out.stem}*"):
                    leftover.unlink()


if __name__ == "__main__":
    main()
