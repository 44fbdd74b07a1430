"""What a codebook (vector quantization) of one attribute group could save in a `.stgc` file, before building one.

    .venv/bin/python benchmarks/codebook_probe.py RUN FILE.stgc [--sizes 256 1024 4096] [--every 3]

Issue #17 lists codebooks for scales, rotations and colour features as a candidate way to share values between
Gaussians. For each group and codebook size K, k-means (scipy, k-means++ seeds, on the parameters standardised per
component; rotations as unit quaternions with w >= 0) replaces every Gaussian's values of the group by its centroid,
and the test views (every `--every`-th) are scored against the float model. The bytes such a section would take are
estimated generously: the indices as zstd level 19 of their little-endian bytes (about their entropy) plus the
codebook at the bit depth the file gives the group (K x C codes, not entropy coded); they are compared with the
group's payload bytes in FILE. The PSNR change is before any fine-tuning, so it is what fine-tuning starts from.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
import zstandard
from scipy.cluster.vq import kmeans2

from stgc import machine
from stgc.codec.format import read_header
from stgc.eval.evaluate import evaluate, open_run_dataset
from stgc.model import STGModel

# parameter keys of each candidate group, and the .stgc sections whose bytes the codebook would replace
CANDIDATES: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "scale + rotation": (("scaling", "rotation"), ("SCAL", "ROTN")),
    "colour (f_dc)": (("features_dc",), ("FDC_",)),
    "colour (f_dc + f_t)": (("features_dc", "features_t"), ("FDC_", "FT__")),
    "motion": (("motion",), ("MOTN",)),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("file", type=Path, help="the run's .stgc file whose section bytes are the baseline")
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 1024, 4096])
    parser.add_argument("--every", type=int, default=3, help="score every n-th test view")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    machine.use_threads(args.threads)  # torch's and numba's (numba alone kept every core)

    dataset = open_run_dataset(args.run)
    background = torch.tensor(dataset.background, dtype=torch.float32)
    views = dataset.test[:: args.every]
    header = read_header(args.file.read_bytes())
    sections = {s.tag: s for s in header.sections}
    n_file = header.num_gaussians

    def score(model: STGModel) -> float:
        with torch.no_grad():
            return evaluate(lambda cam: model.render(cam, t=float(cam.time), background=background),
                            views, dataset.load_image, warmup=0).psnr

    model = STGModel.load(args.run, scene_extent=dataset.scene_extent())
    reference = score(model)
    print(f"{args.run}: {model.num_gaussians:,} Gaussians, {len(views)} test views, float PSNR {reference:.3f} dB; "
          f"{args.file}: {header.file_size:,} B, {n_file:,} Gaussians")
    print("| group | K | sections' bytes in the file | indices B | codebook B | saved B | saved % of file | "
          "PSNR change dB (no fine-tuning) |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for name, (keys, tags) in CANDIDATES.items():
        if any(key not in model.params for key in keys) or any(tag not in sections for tag in tags):
            continue
        columns = [_values(model, key) for key in keys]
        values = np.concatenate(columns, axis=1)
        spread = values.std(axis=0) + 1e-12
        baseline = sum(sections[tag].payload_size for tag in tags)
        codebook_bits = sum(sections[tag].bits * sections[tag].components for tag in tags)
        for size in args.sizes:
            centroids, labels = kmeans2(values / spread, size, iter=20, minit="++", seed=0)
            quantized = centroids[labels] * spread
            probe = STGModel.load(args.run, scene_extent=dataset.scene_extent())
            start = 0
            for key, column in zip(keys, columns):
                width = column.shape[1]
                probe.params[key].data[:] = torch.as_tensor(quantized[:, start:start + width], dtype=torch.float32)
                start += width
            change = score(probe) - reference
            index_dtype = np.uint8 if size <= 256 else np.uint16
            # the file's Gaussians only (the codec leaves out what no frame shows): scale the index bytes by count
            index_bytes = len(zstandard.ZstdCompressor(level=19).compress(
                labels.astype(index_dtype).tobytes())) * n_file / len(labels)
            table_bytes = size * codebook_bits / 8
            saved = baseline - index_bytes - table_bytes
            print(f"| {name} | {size:,} | {baseline:,} | {index_bytes:,.0f} | {table_bytes:,.0f} | {saved:,.0f} | "
                  f"{100 * saved / header.file_size:+.1f} | {change:+.3f} |", flush=True)


def _values(model: STGModel, key: str) -> np.ndarray:
    values = model.params[key].detach().numpy().astype(np.float64)
    if key == "rotation":  # q and -q are one rotation: cluster unit quaternions with w >= 0
        values = values / np.maximum(np.linalg.norm(values, axis=1, keepdims=True), 1e-12)
        values = values * np.where(values[:, :1] < 0, -1.0, 1.0)
    return values


if __name__ == "__main__":
    main()
