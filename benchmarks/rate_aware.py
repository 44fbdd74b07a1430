"""Rate-aware fine-tuning (issue #17) on a trained run: what the codec's quantization in the forward buys.

    .venv/bin/python benchmarks/rate_aware.py runs/RUN --out runs/rate_aware --iterations 1000 --quality 3 1

From a finished run (its checkpoint), three models per quality: the run as it is; the run trained N more
iterations at the window's lower learning rates (`train.quantization_aware` with simulate=false: the control); and
the same N iterations through the codec's quantization at that quality (simulate=true), at the depths `--allocation`
names (the fixed ladder, or the rd-optimised allocation measured when the window opens). Each is compressed at that
quality with `codec.allocation` set to `--compress-allocation`: `auto` (the default, what `stgc compress` does
since session 27: the rate-aware model's file stores the depths its window trained, the other two, which have no
such depths, are measured with the rd-optimised allocation, or get the ladder where the run's dataset cannot be
opened), `optimised` (measured again on each final model, the rate-aware one included: `stgc compress` before
session 27) or `ladder` (the quality's fixed depths for all three).
Each file is evaluated on the test views, float and decoded. Prints one table: test PSNR float / decoded, the
quantization loss, the file size and the extra training time. The continuation extends the run's schedule (xyz
decay over the new total); a run trained with compaction is refused, since a longer schedule would move its
compaction window.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

from stgc.config import to_dict
from stgc.model import STGModel
from stgc.model.layout import bytes_per_gaussian
from stgc.train.config import QuantizationAwareConfig

STGC = [sys.executable, "-m", "stgc.cli"]


def continue_run(run: Path, out: Path, iterations: int, quality: int, simulate: bool, allocation: str) -> float:
    """Copy `run` to `out` with its schedule extended by `iterations` rate-aware ones; train them; seconds spent."""
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    config = json.loads((run / "config.json").read_text())
    if (config.get("compaction") or {}).get("method", "none") != "none":
        raise SystemExit(f"{run}: trained with compaction; a longer schedule would move its compaction window")
    train = config["train"]
    base = int((train.get("resolved_schedule") or train)["iterations"])
    train["iterations"] = base + iterations
    train.pop("resolved_schedule", None)  # recomputed from the options (it would restore the old total)
    # Every option of the window, as a training saves it: `stgc compress` reads a config without them as one saved
    # before they existed, and measures the depths again instead of storing the window's.
    train["quantization_aware"] = to_dict(QuantizationAwareConfig(iterations=iterations, quality=quality,
                                                                  simulate=simulate, allocation=allocation))
    train["eval_every"] = 0
    train["save_iterations"] = [base + iterations]
    (out / "config.json").write_text(json.dumps(config, indent=2))
    shutil.copy(run / "checkpoint.pt", out / "checkpoint.pt")
    shutil.copy(run / "metrics.jsonl", out / "metrics.jsonl")
    subprocess.run([*STGC, "-q", "train", "--out", str(out), "--resume"], check=True)
    # The training's own clock (train_summary.json counts on from the source's): not the process's start-up, image
    # checks and end-of-run evaluation.
    summaries = [json.loads((path / "train_summary.json").read_text()) for path in (out, run)]
    return float(summaries[0]["wall_seconds"]) - float(summaries[1]["wall_seconds"])


def compressed_eval(run: Path, quality: int, allocation: str) -> dict:
    """Compress `run` at `quality` with `codec.allocation=allocation` (auto, optimised or ladder), evaluate the file
    and the float model (if not yet)."""
    name = f"{allocation}_q{quality}"
    stgc_file = run / f"{name}.stgc"
    subprocess.run([*STGC, "-q", "compress", str(run), "--out", str(stgc_file), "--quality", str(quality),
                    "--set", f"codec.allocation={allocation}"], check=True, stdout=subprocess.DEVNULL)
    if not (run / "eval.json").is_file():
        subprocess.run([*STGC, "-q", "eval", str(run), "--no-fps"], check=True, stdout=subprocess.DEVNULL)
    subprocess.run([*STGC, "-q", "eval", str(stgc_file), "--no-fps"], check=True, stdout=subprocess.DEVNULL)
    float_record = json.loads((run / "eval.json").read_text())
    decoded = json.loads((run / f"eval_{name}.json").read_text())
    return {"float": float_record["psnr"], "decoded": decoded["psnr"], "bytes": stgc_file.stat().st_size,
            "gaussians": decoded["num_gaussians"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="a finished run (config.json, checkpoint.pt)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--iterations", type=int, default=1000, help="rate-aware iterations added to the run")
    parser.add_argument("--quality", type=int, nargs="+", default=[3], help="codec qualities")
    parser.add_argument("--allocation", choices=["ladder", "optimised"], default="ladder",
                        help="bit depths the window simulates (train.quantization_aware.allocation): the quality's "
                             "fixed ladder, or the rd-optimised allocation measured when the window opens")
    parser.add_argument("--compress-allocation", choices=["auto", "optimised", "ladder"], default="auto",
                        help="codec.allocation of every compression: auto (stgc compress's default: the rate-aware "
                             "model stores its window's depths, the others are measured), optimised (measured again "
                             "on each final model, stgc compress before session 27) or ladder (the quality's fixed "
                             "depths); default auto")
    args = parser.parse_args()
    args.run, args.out = args.run.resolve(), args.out.resolve()
    rows = []
    for quality in args.quality:
        rows.append(("as trained", quality, compressed_eval(args.run, quality, args.compress_allocation), 0.0))
        for name, simulate in (("control", False), ("aware", True)):
            out = args.out / f"{name}_{args.allocation}_q{quality}"
            seconds = continue_run(args.run, out, args.iterations, quality, simulate, args.allocation)
            rows.append((name, quality, compressed_eval(out, quality, args.compress_allocation), seconds))
    print(f"\n{args.run}: +{args.iterations} iterations, {args.allocation} bit depths in the window, compressed with "
          f"codec.allocation={args.compress_allocation}, test views")
    print("| model | quality | test PSNR float | decoded | loss dB | file KiB | x smaller than PLY rows | Gaussians | "
          "extra training s |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    trained = STGModel.load(args.run)  # the ratio is against the trained model's float32 PLY rows
    ply_bytes = trained.num_gaussians * bytes_per_gaussian(trained.variant)
    for name, quality, r, seconds in rows:
        print(f"| {name} | q{quality} | {r['float']:.2f} | {r['decoded']:.2f} | {r['float'] - r['decoded']:+.2f} | "
              f"{r['bytes'] / 1024:.1f} | {ply_bytes / r['bytes']:.1f} | {r['gaussians']:,} | {seconds:.0f} |")
    print(json.dumps([{"model": n, "quality": q, **r, "extra_seconds": s} for n, q, r, s in rows]))


if __name__ == "__main__":
    main()
