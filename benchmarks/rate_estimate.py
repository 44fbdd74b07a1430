"""How close the codec's rate estimate (stgc.codec.rate) is to the bytes the encoder writes, on trained runs.

    .venv/bin/python benchmarks/rate_estimate.py runs/RUN [runs/RUN2 ...] [--quality 1 2 3]

For each run's model and codec quality (the fixed ladder's depths, as `--set codec.allocation=ladder` stores; the
estimate itself takes any depths), prints the estimated and the real payload bytes of every attribute section,
their ratio, and the whole: what issue #17's rate term is built on (tested within 10 % in tests/codec/test_rate.py).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from stgc.codec.format import decode, encode, quantized_groups
from stgc.codec.rate import estimate_section_bits
from stgc.model import STGModel


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--quality", type=int, nargs="+", default=[1, 2, 3])
    args = parser.parse_args()
    for run in args.runs:
        model = STGModel.load(run)
        arrays, state = model.to_ply_arrays(), model.decoder_state()
        for quality in args.quality:
            start = time.perf_counter()
            estimate = estimate_section_bits(quantized_groups(arrays, model.variant, quality))
            seconds = time.perf_counter() - start
            real = decode(encode(arrays, model.variant, state, quality)).header.section_bytes()
            print(f"\n{run} ({model.num_gaussians:,} Gaussians), q{quality} ladder; estimate took {seconds:.2f} s")
            print("| section | estimated bytes | real bytes | estimate / real |")
            print("|---|---:|---:|---:|")
            for tag, bits in estimate.items():
                print(f"| {tag} | {bits / 8:,.0f} | {real[tag]:,} | {bits / 8 / real[tag]:.3f} |")
            total_estimate, total_real = sum(estimate.values()) / 8, sum(real[t] for t in estimate)
            print(f"| all | {total_estimate:,.0f} | {total_real:,} | {total_estimate / total_real:.3f} |")


if __name__ == "__main__":
    main()
