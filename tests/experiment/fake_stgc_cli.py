"""A stand-in for `python -m stgc.cli` that trains nothing: it writes plausible run files in milliseconds.

train: config.json, checkpoint.pt, train_summary.json (finished) and eval.json whose PSNR/rate depend on
compaction.case. `--set fake.fail=1` exits 3; `--set fake.no_eval=1` leaves eval.json to the eval verb;
`--set fake.sleep=S` trains for S seconds after its first checkpoint (a kill can land mid-run). `--resume` continues
with the options of the run's config.json. finetune: the source's files, its evaluation 0.1 dB lower at half the rate.
compress: a valid .stgc of no Gaussians whose header and metadata say what `stgc compress` records (quality, the
run's final iteration, run config, allocation option), about 1000 bytes per quality level.
Every call is appended to <run parent>/invocations.txt so tests can count launches."""

from __future__ import annotations

import hashlib
import json
import os
import struct
import sys
import time
import zlib
from pathlib import Path

# What a lite model's .stgc holds (stgc.codec.format, docs/stgc-format.md), copied here: importing stgc takes
# seconds per call. test_runner.py checks that stgc reads these files back.
_MAGIC = b"STGC\r\n\x1a\n"
_LITE_SECTIONS = {b"POSI": 3, b"TCEN": 1, b"TSCL": 1, b"MOTN": 9, b"FDC_": 3, b"OPAC": 1, b"SCAL": 3, b"ROTN": 4,
                  b"OMGA": 4}  # tag: components


FAKE_COMPACTION_DEFAULTS = {"pair_order": "weight", "loss_signal": "prune_damage", "loss_budget_db": 0.3,
                            "ratio_increase": "slow_start", "ratio_max": 0.5, "removal_rate_max": 0.002,
                            "reset_settle_steps": 10, "prune_trials": 3}


def _record(out: Path, argv: list[str]) -> None:
    with open(out.parent / "invocations.txt", "a") as f:
        f.write(" ".join(argv) + "\n")


def _eval_record(case: int, preprocess: str, run: Path, seed: int = 0) -> dict:
    """With the training iterations of the run's summary, as the real record keeps them (none before it finished).
    train.seed moves the PSNR by -0.1 dB and the Gaussians by -100 per seed and case, as seeds move real runs."""
    rate = 100.0 / (1 + case) * (0.5 if preprocess != "none" else 1.0)
    summary = run / "train_summary.json"
    trained = json.loads(summary.read_text()).get("iterations") if summary.is_file() else None
    return {"psnr": 30.0 - 0.3 * case - (0.1 if preprocess != "none" else 0.0) - 0.1 * seed * (1 + case),
            "ssim": 0.9, "mbps": rate, "size_mb": rate / 8.388608, "num_gaussians": int(rate * 1000) - 100 * seed * case,
            "fps": 5.0,
            **({"iterations": trained} if trained is not None else {})}


def stgc_bytes(quality: int, metadata: dict, size: int = 0) -> bytes:
    """A valid version-4 .stgc of a lite model with no Gaussians, storing `quality` and `metadata` (padded with a
    "pad" entry to `size` bytes where that is more than it needs)."""
    meta = json.dumps(metadata, sort_keys=True).encode()
    unpadded = 32 + sum(20 + 16 * c for c in _LITE_SECTIONS.values()) + 20 + len(meta)
    pad = size - unpadded - len(', "pad": ""')
    if pad > 0:
        meta = json.dumps({**metadata, "pad": "x" * pad}, sort_keys=True).encode()
    table = b""
    for tag, components in _LITE_SECTIONS.items():  # stored, 8 bits, empty payloads; quantizer step 1, zero 0
        table += struct.pack("<4sBBBBIII", tag, 0, 8, components, 0, 0, 0, 0)
        table += struct.pack("<dq", 1.0, 0) * components
    table += struct.pack("<4sBBBBIII", b"META", 0, 8, 0, 0, len(meta), len(meta), zlib.crc32(meta))
    head = struct.pack("<8sHBBIHHII", _MAGIC, 4, 2, quality, 0, len(_LITE_SECTIONS) + 1, 0, len(table),
                       zlib.crc32(table))
    return head + struct.pack("<I", zlib.crc32(head)) + table + meta


def _set_train_options(train: dict, sets: dict[str, str]) -> None:
    """Write the train.* options of `sets` into a config.json train section (as strings: read back, they are
    coerced to their types)."""
    for key, value in sets.items():
        if key.startswith("train."):
            *parents, name = key.split(".")[1:]
            target = train
            for parent in parents:
                target = target.setdefault(parent, {})
            target[name] = value


def main(argv: list[str]) -> int:
    verb = argv[0]
    if verb == "train":
        out = Path(argv[argv.index("--out") + 1])
        sets = {}
        for i, a in enumerate(argv):
            if a == "--set":
                k, v = argv[i + 1].split("=", 1)
                sets[k] = v
        out.mkdir(parents=True, exist_ok=True)
        _record(out, argv)
        if "--resume" in argv:
            sets = json.loads((out / "config.json").read_text()).get("sets", {})
        if sets.get("fake.fail") == "1":
            print("fake failure", file=sys.stderr)
            return 3
        case = int(sets.get("compaction.case", 0)) if sets.get("compaction.method") == "st-knn" else 0
        preprocess = sets.get("data.preprocess", "none")
        # The options it was given, as a real config.json records them (the runner compares those it holds).
        compaction = {"method": sets.get("compaction.method", "none"),
                      "criterion": sets.get("compaction.criterion", "timestamp")}
        if "compaction.case" in sets:
            compaction["case"] = int(sets["compaction.case"])
        # Options whose default is not how a config.json without them trained (CompactionConfig.SAVED_BEFORE):
        # written as a real run writes them (today's defaults; test_runner.py checks that they are).
        for key, default in FAKE_COMPACTION_DEFAULTS.items():
            value = sets.get(f"compaction.{key}", default)
            compaction[key] = value if isinstance(default, str) else float(value)
        # mask_points_per_frame: a data section without it is read as a config from before it existed (0).
        data = {"path": argv[1], "preprocess": preprocess,
                "mask_points_per_frame": int(sets.get("data.mask_points_per_frame", 1000))}
        # The preset's train section (test_runner.py hands it over), with the run's train.* options in it.
        preset = argv[argv.index("--preset") + 1] if "--preset" in argv else "cpu"
        train = json.loads(os.environ.get("STGC_FAKE_TRAIN", "{}")).get(preset, {"iterations": 10})
        _set_train_options(train, sets)
        behaviour = json.loads(os.environ.get("STGC_FAKE_BEHAVIOUR", "[]"))
        (out / "config.json").write_text(json.dumps({"data": data, "model": {}, "train": train,
                                                     "compaction": compaction, "sets": sets,
                                                     "behaviour": behaviour}))
        (out / "checkpoint.pt").write_bytes(b"fake")
        if "--resume" not in argv:
            time.sleep(float(sets.get("fake.sleep", 0)))
        (out / "train_summary.json").write_text(json.dumps({"finished": True, "wall_seconds": 1.5,
                                                            "iterations": 10}))
        if sets.get("fake.no_eval") != "1":
            seed = int(sets.get("train.seed", 0))
            (out / "eval.json").write_text(json.dumps(_eval_record(case, preprocess, out, seed)))
        return 0
    if verb == "finetune":
        # A continuation of a finished run: refuses an unfinished source, as `stgc finetune` does; its evaluation
        # is the source's less 0.1 dB at half the rate.
        source, out = Path(argv[1]), Path(argv[argv.index("--out") + 1])
        out.mkdir(parents=True, exist_ok=True)
        _record(out, argv)
        if not json.loads((source / "train_summary.json").read_text()).get("finished"):
            return 2
        config = json.loads((source / "config.json").read_text())
        iterations = int(argv[argv.index("--iterations") + 1])
        # As `stgc finetune` writes it: the source's schedule extended, its --set train.* options, no compaction.
        config["train"]["iterations"] = int(config["train"]["iterations"]) + iterations
        _set_train_options(config["train"], {argv[i + 1].split("=", 1)[0]: argv[i + 1].split("=", 1)[1]
                                             for i, a in enumerate(argv) if a == "--set"})
        config["compaction"] = {**config["compaction"], "method": "none"}
        (out / "config.json").write_text(json.dumps({**config, "from": str(source)}))
        (out / "continued_from.json").write_text(json.dumps({"run": str(source.resolve()), "iterations": iterations}))
        (out / "checkpoint.pt").write_bytes(b"fake")
        (out / "train_summary.json").write_text(json.dumps({"finished": True, "wall_seconds": 0.5, "iterations": 20}))
        record = json.loads((source / "eval.json").read_text())
        record |= {"psnr": record["psnr"] - 0.1, "mbps": record["mbps"] / 2, "size_mb": record["size_mb"] / 2,
                   "iterations": 20}
        (out / "eval.json").write_text(json.dumps(record))
        return 0
    if verb == "eval":
        target = Path(argv[1])
        run = target.parent if target.suffix == ".stgc" else target
        _record(run, argv)
        cfg = json.loads((run / "config.json").read_text())
        compaction = cfg["compaction"]
        case = compaction.get("case", 0) if compaction["method"] == "st-knn" else 0
        rec = _eval_record(case, cfg["data"]["preprocess"], run, int(cfg["train"].get("seed", 0)))
        if target.suffix == ".stgc":
            rec["mbps"] = target.stat().st_size * 8 / 1e6
            rec["psnr"] -= 0.05
            # What the real record keeps to tell that it scored this very file.
            rec |= {"size_bytes": target.stat().st_size, "bitstream": target.name,
                    "bitstream_sha256": hashlib.sha256(target.read_bytes()).hexdigest()}
            (run / f"eval_{target.stem}.json").write_text(json.dumps(rec))
        else:
            (run / "eval.json").write_text(json.dumps(rec))
        print(json.dumps(rec))
        return 0
    if verb == "compress":
        run = Path(argv[1])
        _record(run, argv)
        out = Path(argv[argv.index("--out") + 1])
        quality = int(argv[argv.index("--quality") + 1])
        sets = dict(argv[i + 1].split("=", 1) for i, a in enumerate(argv) if a == "--set")
        summary = json.loads((run / "train_summary.json").read_text())
        config = json.loads((run / "config.json").read_text())
        metadata = {"source": run.name, "iteration": summary["iterations"]}  # a run's latest model: its final one
        if sets.get("codec.embed_run_config", "True") == "True":
            metadata["run_config"] = {k: config[k] for k in ("data", "model") if k in config}
        if sets.get("codec.allocation", "auto") != "auto":
            metadata["allocation_option"] = sets["codec.allocation"]
        out.write_bytes(stgc_bytes(quality, metadata, 1000 * quality))
        return 0
    return 2


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
