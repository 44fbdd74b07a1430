"""How the `v<version>_<variant>_q<quality>_meta.stgc` reference files were made (tests/codec/reference/README.md).

Two steps, so that every version's encoder gets the same inputs:

1. `inputs OUT.npz`, run with the checkout whose `stgc.codec.synthetic` the inputs come from: a synthetic full
   model of 800 Gaussians with three far-off values (a floater, a stray colour, a stray motion coefficient) that
   the outlier guard absorbs with extra bits (its 0.1 / 99.9 percentiles leave a single Gaussian out only from
   about 800 Gaussians on), and a lite model of 64; static Gaussians' motion and omega are exactly 0, as after
   training.
2. `encode INPUTS.npz OUT_DIR`, run with an old encoder (`PYTHONPATH=<worktree of that commit>/src`): writes a run
   directory as training does (point_cloud/iteration_<N>/ and a config.json of that commit's `cpu` preset; the
   full model's decoder activation `clamp`, not the default), compresses it with *that commit's* `compress_run`
   (the fixed ladder, so the META section is what compress_run wrote then: source, iteration,
   decoder_activation, run_config, dropped_invisible, ...), and decodes the file with that commit's decoder into
   `<stem>_decoded.npz`: `fields` and `arrays` (every PLY field, one row each), `d:<decoder weight>`, `meta`
   (the metadata, JSON), `header` (version, variant code 1 full / 2 lite, quality, N), `tags` and `table`
   (codec, bits, components, flags, raw_size, payload_size per section) and `encoder` (JSON: VERSION, the
   options, the depth each group was asked for before the outlier guard).
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import numpy as np

# variant -> (Gaussians, seed, quality, position_bits, iteration, decoder activation)
FILES = {
    "full": (800, 11, 1, 20, 1234, "clamp"),
    "lite": (64, 12, 5, None, 600, None),
}


def make_inputs(out: Path) -> None:
    from stgc.codec.synthetic import synthetic_model

    saved = {}
    for variant, (n, seed, *_rest) in FILES.items():
        arrays, decoder = synthetic_model(n, variant, seed=seed)
        arrays = {k: np.array(v, np.float32) for k, v in arrays.items()}
        static = np.abs(arrays["motion_0"]) < 1e-3  # as after training: static Gaussians' motion and omega are 0
        for k in arrays:
            if k.startswith(("motion_", "omega_")):
                arrays[k][static] = 0.0
        if variant == "full":  # far-off values for the outlier guard (one Gaussian each)
            arrays["x"][5] = 4000.0  # a floater
            arrays["f_dc_0"][9] = 100.0  # a stray colour
            arrays["motion_0"][np.flatnonzero(~static)[0]] = 200.0  # a stray motion coefficient (time-span domain)
        for k, v in arrays.items():
            saved[f"{variant}/a:{k}"] = v
        for k, v in (decoder or {}).items():
            saved[f"{variant}/d:{k}"] = np.asarray(v, np.float32)
    np.savez_compressed(out, **saved)


def encode_references(inputs: Path, out_dir: Path) -> None:
    from dataclasses import fields

    from stgc.cli import default_configs
    from stgc.codec import format as fmt
    from stgc.codec.files import CodecConfig, compress_run
    from stgc.config import to_dict
    from stgc.model import STGModel

    stored = np.load(inputs)
    version = fmt.VERSION
    for variant, (_n, _seed, quality, position_bits, iteration, activation) in FILES.items():
        arrays = {k.split(":", 1)[1]: stored[k] for k in stored.files if k.startswith(f"{variant}/a:")}
        decoder = {k.split(":", 1)[1]: stored[k] for k in stored.files if k.startswith(f"{variant}/d:")} or None
        stem = f"v{version}_{variant}_q{quality}_meta"
        with tempfile.TemporaryDirectory() as tmp:
            run = Path(tmp) / f"ref_{variant}_run"
            model = STGModel.from_ply_arrays(arrays, variant, decoder, decoder_activation=activation or "sigmoid")
            model.save(run / "point_cloud" / f"iteration_{iteration}")
            configs = default_configs("cpu")
            model_cfg = to_dict(configs["model"])
            model_cfg["variant"] = variant
            if activation:
                model_cfg["decoder_activation"] = activation
            data_cfg = {"format": "blender", "path": "data/blender_toys", **to_dict(configs["data"])}
            (run / "config.json").write_text(json.dumps(
                {"data": data_cfg, "model": model_cfg, "train": to_dict(configs["train"]),
                 "compaction": to_dict(configs["compaction"])}, indent=2))
            options = {"quality": quality, "position_bits": position_bits or 0}  # 0: the ladder's
            if "allocation" in {f.name for f in fields(CodecConfig)}:
                options["allocation"] = "ladder"  # the ladder, as every older version: no dataset to optimise on
            path = out_dir / f"{stem}.stgc"
            compress_run(run, path, config=CodecConfig(**options))
        decoded = fmt.decode(path.read_bytes(), source=str(path))
        header = decoded.header
        # Few npz members (each costs ~250 bytes of headers): every field in one array, the table in another.
        result = {"fields": np.array(list(decoded.arrays)),
                  "arrays": np.stack([np.asarray(v, np.float32) for v in decoded.arrays.values()])}
        result.update({f"d:{k}": np.asarray(v) for k, v in (decoded.decoder_state or {}).items()})
        result["meta"] = np.array(json.dumps(decoded.metadata, sort_keys=True).encode())  # UTF-8: 1/4 of str
        result["header"] = np.array([header.version, {"full": 1, "lite": 2}[header.variant], header.quality,
                                     header.num_gaussians], np.int64)
        result["tags"] = np.array([s.tag for s in header.sections])
        result["table"] = np.array([[s.codec, s.bits, s.components, s.flags, s.raw_size, s.payload_size]
                                    for s in header.sections], np.int64)
        asked = {g.tag.decode(): fmt.bits_for(g, quality) for g in fmt.groups_for(variant)}
        asked["POSI"] = position_bits or asked["POSI"]
        result["encoder"] = np.array(json.dumps({"version": version, "variant": variant, **options,
                                                 "requested_bits": asked}, sort_keys=True).encode())
        np.savez_compressed(out_dir / f"{stem}_decoded.npz", **result)
        print(path, path.stat().st_size, "bytes;", {s.tag: s.bits for s in header.sections}, decoded.metadata.keys())


if __name__ == "__main__":
    if sys.argv[1] == "inputs":
        make_inputs(Path(sys.argv[2]))
    elif sys.argv[1] == "encode":
        encode_references(Path(sys.argv[2]), Path(sys.argv[3]))
    else:
        raise SystemExit(__doc__)
