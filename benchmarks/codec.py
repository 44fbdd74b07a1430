"""Benchmark of the .stgc codec on synthetic models with trained-model statistics (stgc.codec.synthetic).

Prints two tables: encode/decode time and throughput per model size, and bytes per Gaussian per quality level.
Throughput (MB/s) is measured against the float32 PLY rows the model replaces (152 B full / 128 B lite per
Gaussian), so encode and decode speeds are comparable across quality levels.

    .venv/bin/python benchmarks/codec.py                    # 100k and 1M Gaussians, full variant
    .venv/bin/python benchmarks/codec.py --sizes 20000 --json

With --runs RUN..., trained runs instead: each is compressed at every quality, with the rd-optimised allocation
into RUN/model_q<Q>.stgc and with the fixed ladder into RUN/model_q<Q>_ladder.stgc, and each bitstream is
evaluated on the run's test views (RUN/eval_model_q<Q>*.json, as `stgc eval` writes it), giving the real
rate-distortion points against the float32 model's RUN/eval.json:

    .venv/bin/python benchmarks/codec.py --runs runs/toys_full_cpu runs/pan_C
"""

from __future__ import annotations

import argparse
import json
import time

from stgc import machine
from stgc.codec import DEFAULT_QUALITY, QUALITY_LEVELS, decode, encode
from stgc.codec.format import DEFAULT_ZSTD_LEVEL
from stgc.codec.synthetic import synthetic_model
from stgc.eval.accounting import mbps
from stgc.model.layout import bytes_per_gaussian


def _timed(fn, repeat: int):
    best, result = float("inf"), None
    for _ in range(repeat):
        start = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - start)
    return best, result


def speed_rows(sizes: list[int], variant: str, quality: int, zstd_level: int, repeat: int) -> list[dict]:
    rows = []
    for n in sizes:
        arrays, decoder = synthetic_model(n, variant, seed=0)
        ply_mb = n * bytes_per_gaussian(variant) / 1e6
        enc_s, data = _timed(lambda: encode(arrays, variant, decoder, quality, zstd_level=zstd_level), repeat)
        dec_s, _ = _timed(lambda: decode(data), repeat)
        rows.append({
            "table": "speed", "variant": variant, "gaussians": n, "quality": quality, "zstd_level": zstd_level,
            "file_bytes": len(data), "bytes_per_gaussian": round(len(data) / n, 3),
            "ratio_vs_ply": round(n * bytes_per_gaussian(variant) / len(data), 2),
            "encode_s": round(enc_s, 3), "decode_s": round(dec_s, 3),
            "encode_mb_s": round(ply_mb / enc_s, 1), "decode_mb_s": round(ply_mb / dec_s, 1),
        })
    return rows


def quality_rows(n: int, zstd_level: int) -> list[dict]:
    rows = []
    for variant in ("full", "lite"):
        arrays, decoder = synthetic_model(n, variant, seed=0)
        for quality in QUALITY_LEVELS:
            data = encode(arrays, variant, decoder, quality, zstd_level=zstd_level)
            header = decode(data).header
            rows.append({
                "table": "quality", "variant": variant, "gaussians": n, "quality": quality,
                "bits": {s.tag: s.bits for s in header.sections if s.components},
                "bytes_per_gaussian": round(len(data) / n, 3),
                "ratio_vs_ply": round(n * bytes_per_gaussian(variant) / len(data), 2),
                "mbps_at_1s": round(mbps(len(data), 1.0), 3),
                "section_bytes_per_gaussian": {k: round(v / n, 3) for k, v in header.section_bytes().items()},
            })
    return rows


def trained_rows(runs: list[str], qualities: tuple[int, ...] = QUALITY_LEVELS,
                 allocations: tuple[str, ...] = ("optimised", "ladder")) -> list[dict]:
    from pathlib import Path

    from stgc.codec import CodecConfig, compress_run
    from stgc.eval import evaluate_run
    from stgc.fileio import read_json_object

    rows = []
    for run in map(Path, runs):
        base = read_json_object(run / "eval.json")
        for allocation in allocations:
            for quality in qualities:
                suffix = "" if allocation == "optimised" else f"_{allocation}"
                target = run / f"model_q{quality}{suffix}.stgc"
                start = time.perf_counter()
                result = compress_run(run, target, quality=quality, config=CodecConfig(allocation=allocation))
                seconds = time.perf_counter() - start
                record = evaluate_run(target, measure_fps=False)
                rows.append({
                    "table": "trained", "run": str(run), "allocation": allocation, "quality": quality,
                    "gaussians": result.input_gaussians, "dropped_invisible": result.dropped_invisible,
                    "encode_seconds": round(seconds, 1),
                    "bytes_per_gaussian": round(result.bytes_per_input_gaussian, 3),  # 152 / it = ratio_vs_ply
                    "ratio_vs_ply": round(result.ratio_vs_ply, 2), "size_mb": record["size_mb"],
                    "mbps": record["mbps"], "psnr": record["psnr"], "float_psnr": base["psnr"],
                    "float_size_mb": base["size_mb"], "float_mbps": base["mbps"],
                    "delta_psnr": record["psnr"] - base["psnr"],
                    "train_view_loss_bound_db": (result.allocation or {}).get("train_view_loss_bound_db"),
                })
    return rows


def print_trained(rows: list[dict]) -> None:
    for run in dict.fromkeys(r["run"] for r in rows):
        mine = [r for r in rows if r["run"] == run]
        first = mine[0]
        print(f"{run}: {first['gaussians']} Gaussians ({first['dropped_invisible']} never visible, left out of the "
              f"files); float32 PLY rows {first['float_size_mb']:.3f} MB, {first['float_mbps']:.2f} Mbps, test PSNR "
              f"{first['float_psnr']:.3f} dB; B/G per input Gaussian")
        print(f"{'allocation':>10} {'quality':>7} {'B/G':>6} {'x PLY':>6} {'MB':>7} {'Mbps':>6} {'PSNR':>7} "
              f"{'dPSNR':>7} {'train-view bound':>16} {'encode s':>8}")
        for r in mine:
            bound = r["train_view_loss_bound_db"]
            print(f"{r['allocation']:>10} {r['quality']:>7} {r['bytes_per_gaussian']:>6.2f} {r['ratio_vs_ply']:>6.2f} "
                  f"{r['size_mb']:>7.4f} {r['mbps']:>6.3f} {r['psnr']:>7.3f} {r['delta_psnr']:>+7.3f} "
                  f"{'' if bound is None else f'{bound:+.3f}':>16} {r['encode_seconds']:>8.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[100_000, 1_000_000])
    parser.add_argument("--variant", choices=("full", "lite"), default="full")
    parser.add_argument("--quality", type=int, default=DEFAULT_QUALITY, choices=QUALITY_LEVELS)
    parser.add_argument("--zstd-level", type=int, default=DEFAULT_ZSTD_LEVEL)
    parser.add_argument("--quality-sweep-size", type=int, default=100_000,
                        help="Gaussians in the per-quality size table (0 skips it)")
    parser.add_argument("--repeat", type=int, default=1, help="best of this many runs per timing")
    parser.add_argument("--json", action="store_true", help="print one JSON row per measurement instead")
    parser.add_argument("--runs", nargs="+", help="trained run directories: real RD points instead of synthetic")
    parser.add_argument("--allocations", nargs="+", choices=("optimised", "ladder"), default=["optimised", "ladder"],
                        help="with --runs: how bit depths are chosen (CodecConfig.allocation); each is measured")
    args = parser.parse_args()
    host = machine.one_line()  # the load before the timings

    if args.runs:
        rows = trained_rows(args.runs, allocations=tuple(args.allocations))
        if args.json:
            for row in rows:
                print(json.dumps({**row, "machine": host}))
        else:
            print(f"machine: {host}")
            print_trained(rows)
        return

    rows = speed_rows(args.sizes, args.variant, args.quality, args.zstd_level, args.repeat)
    if args.quality_sweep_size:
        rows += quality_rows(args.quality_sweep_size, args.zstd_level)
    if args.json:
        for row in rows:
            print(json.dumps({**row, "machine": host}))
        return
    print(f"machine: {host}")
    print(f"Encode/decode speed ({args.variant}, quality {args.quality}, zstd {args.zstd_level}; MB/s of float32 PLY)")
    print(f"{'gaussians':>10} {'file MB':>8} {'B/G':>6} {'x PLY':>6} {'enc s':>7} {'dec s':>7} {'enc MB/s':>9} "
          f"{'dec MB/s':>9}")
    for r in (r for r in rows if r["table"] == "speed"):
        print(f"{r['gaussians']:>10} {r['file_bytes'] / 1e6:>8.2f} {r['bytes_per_gaussian']:>6.2f} "
              f"{r['ratio_vs_ply']:>6.2f} {r['encode_s']:>7.2f} {r['decode_s']:>7.3f} {r['encode_mb_s']:>9.1f} "
              f"{r['decode_mb_s']:>9.1f}")
    quality = [r for r in rows if r["table"] == "quality"]
    if quality:
        print(f"\nBytes per Gaussian per quality level ({quality[0]['gaussians']} Gaussians)")
        print(f"{'variant':>7} {'quality':>7} {'B/G':>6} {'x PLY':>6}  bits per group")
        for r in quality:
            bits = " ".join(f"{k}={v}" for k, v in r["bits"].items())
            print(f"{r['variant']:>7} {r['quality']:>7} {r['bytes_per_gaussian']:>6.2f} {r['ratio_vs_ply']:>6.2f}  {bits}")


if __name__ == "__main__":
    main()
