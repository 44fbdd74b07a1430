"""Model accounting: number of Gaussians, size, bitrate, render speed, training time.

Units, stated once (docs/evaluation.md has the derivation):
- `size_bytes` in the *paper convention* = #Gaussians × float32 row of the official STG PLY (152 B full, 128 B
  lite, both including the 3 unused normals) + float32 bytes of the decoder state dict (full only, 90 weights
  = 360 B). For a `.stgc` file it is simply that file's size.
- `size_mib` = size_bytes / 2^20. The paper's "MB" column is this MiB figure (433,936 × 152 B = 62.90); we
  also report `size_mb_si` = size_bytes / 10^6 so nobody has to guess.
- `mbps` = size_bytes × 8 / 10^6 / duration_s, with duration_s = frames / fps (the time span the model covers).
  For a 1-s model this is MiB × 8.388608, the paper's conversion (62.90 MiB -> 527.67 Mbps; the paper prints
  527.68 because it evidently counted the files, PLY header and decoder `.pt` included: `mbps_files`).
- `mbps_files` uses the bytes of the files we actually write (PLY with header, decoder `.pt`, or `.stgc`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from stgc import run as run_layout
from stgc.errors import DataError, FormatError
from stgc.model import STGModel
from stgc.model.layout import bytes_per_gaussian, ply_fields

BYTES_PER_MIB = 2**20
BYTES_PER_MB = 10**6
# MiB -> Mbps for one second of content: 2^20 · 8 / 10^6.
MIB_TO_MBPS_PER_SECOND = BYTES_PER_MIB * 8 / 1e6  # 8.388608


def mib(num_bytes: float) -> float:
    return num_bytes / BYTES_PER_MIB


def mbps(num_bytes: float, duration_s: float) -> float:
    """Megabits (10^6 bits) per second for `num_bytes` that represent `duration_s` seconds of video."""
    if not duration_s > 0:
        raise ValueError(f"duration must be positive, got {duration_s}")
    return num_bytes * 8 / 1e6 / duration_s


def duration_seconds(frames: int, fps: float) -> float:
    """Seconds of video a model covers: frames / fps."""
    if frames <= 0 or not fps > 0:
        raise ValueError(f"need frames > 0 and fps > 0, got frames={frames}, fps={fps}")
    return frames / fps


def paper_model_bytes(num_gaussians: int, variant: str = "full", decoder_floats: int = 0) -> int:
    """Bytes in the paper's convention: raw float32 PLY rows (normals included) + float32 decoder weights."""
    return int(num_gaussians) * bytes_per_gaussian(variant, include_normals=True) + 4 * int(decoder_floats)


def ply_header_bytes(num_gaussians: int, variant: str) -> int:
    """Exact header length of the official binary PLY (as plyfile writes it) for `num_gaussians` rows."""
    lines = ["ply", "format binary_little_endian 1.0", f"element vertex {int(num_gaussians)}"]
    lines += [f"property float {name}" for name in ply_fields(variant)]
    lines += ["end_header"]
    return sum(len(line) + 1 for line in lines)


def ply_file_bytes(num_gaussians: int, variant: str) -> int:
    """Size of the official `point_cloud.ply` file: header + float32 rows."""
    return ply_header_bytes(num_gaussians, variant) + int(num_gaussians) * bytes_per_gaussian(variant)


def state_dict_floats(state: Mapping[str, Any] | None) -> int:
    """Number of scalars in a (decoder) state dict of tensors or arrays."""
    if not state:
        return 0
    return int(sum(int(np.prod(np.shape(np.asarray(v.detach().cpu() if hasattr(v, "detach") else v))))
                   for v in state.values()))


@dataclass
class ModelSize:
    """How big a model is, in every unit we report. See the module docstring for the conventions."""

    num_gaussians: int
    variant: str
    size_bytes: int
    convention: str  # "ply-rows+decoder-f32" (paper) or "file" (a .stgc bitstream)
    duration_s: float
    decoder_floats: int = 0
    file_bytes: dict[str, int] = field(default_factory=dict)

    @property
    def size_mib(self) -> float:
        return mib(self.size_bytes)

    @property
    def size_mb_si(self) -> float:
        return self.size_bytes / BYTES_PER_MB

    @property
    def mbps(self) -> float:
        return mbps(self.size_bytes, self.duration_s)

    @property
    def files_total_bytes(self) -> int:
        return int(sum(self.file_bytes.values()))

    @property
    def mbps_files(self) -> float | None:
        return mbps(self.files_total_bytes, self.duration_s) if self.file_bytes else None

    @property
    def bytes_per_gaussian(self) -> float | None:
        return self.size_bytes / self.num_gaussians if self.num_gaussians else None

    def as_dict(self) -> dict[str, Any]:
        """The fields written into eval.json (size_mb is the paper's MB, i.e. MiB)."""
        return {
            "num_gaussians": int(self.num_gaussians),
            "variant": self.variant,
            "size_bytes": int(self.size_bytes),
            "size_convention": self.convention,
            "size_mb": self.size_mib,
            "size_mib": self.size_mib,
            "size_mb_si": self.size_mb_si,
            "mbps": self.mbps,
            "duration_s": self.duration_s,
            "decoder_floats": int(self.decoder_floats),
            "bytes_per_gaussian": self.bytes_per_gaussian,
            "file_bytes": dict(self.file_bytes),
            "files_total_bytes": self.files_total_bytes,
            "mbps_files": self.mbps_files,
        }


def model_size(
    num_gaussians: int,
    variant: str,
    duration_s: float,
    decoder_floats: int = 0,
    files: Iterable[str | Path] = (),
) -> ModelSize:
    """Paper-convention size of a model, plus the on-disk sizes of the given files."""
    return ModelSize(
        num_gaussians=int(num_gaussians),
        variant=variant,
        size_bytes=paper_model_bytes(num_gaussians, variant, decoder_floats),
        convention="ply-rows+decoder-f32",
        duration_s=duration_s,
        decoder_floats=int(decoder_floats),
        file_bytes=_file_sizes(files),
    )


def model_size_of(model: STGModel, duration_s: float, files: Iterable[str | Path] = ()) -> ModelSize:
    """`model_size` for an `stgc.model.STGModel` (anything with num_gaussians, variant, decoder_state())."""
    decoder = model.decoder_state() if hasattr(model, "decoder_state") else None
    return model_size(model.num_gaussians, model.variant, duration_s, state_dict_floats(decoder), files)


def bitstream_size(path: str | Path, num_gaussians: int, variant: str, duration_s: float) -> ModelSize:
    """Size of a compressed `.stgc` file: its real byte count is the size."""
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "bitstream file not found")
    nbytes = path.stat().st_size
    return ModelSize(int(num_gaussians), variant, nbytes, "file", duration_s, 0, {path.name: nbytes})


def _file_sizes(files: Iterable[str | Path]) -> dict[str, int]:
    out: dict[str, int] = {}
    for f in files:
        p = Path(f)
        if p.is_file():
            out[p.name] = p.stat().st_size
    return out


# ------------------------------------------------------------------------------------ reading run dirs


def read_ply_header(path: str | Path) -> tuple[int, list[str]]:
    """(#vertices, property names) from a PLY header, without reading the body."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            if f.readline().strip() != b"ply":
                raise FormatError(path, "not a PLY file (missing 'ply' magic)")
            count, names = None, []
            for _ in range(10_000):
                line = f.readline()
                if not line:
                    break
                words = line.decode("ascii", errors="replace").split()
                if words[:2] == ["element", "vertex"] and len(words) == 3:
                    count = int(words[2])
                elif words[:1] == ["property"] and count is not None and len(words) >= 3:
                    names.append(words[-1])
                elif words[:1] == ["end_header"]:
                    if count is None:
                        raise FormatError(path, "PLY header has no 'element vertex' line")
                    return count, names
    except OSError as exc:
        raise DataError(path, f"cannot read PLY: {exc.strerror or exc}") from None
    except ValueError as exc:
        raise FormatError(path, f"malformed PLY header ({exc})") from None
    raise FormatError(path, "PLY header has no end_header line")


def variant_of_fields(names: Sequence[str], path: str | Path | None = None) -> str:
    for variant in ("full", "lite"):
        if list(names) == ply_fields(variant):
            return variant
    raise FormatError(path, f"PLY fields are not the official STG full or lite layout ({len(names)} fields)")


def latest_iteration_dir(run_dir: str | Path) -> Path:
    """RUN/point_cloud/iteration_<N> with the largest N (`stgc.run.latest_iteration_dir`), else a DataError."""
    latest = run_layout.latest_iteration_dir(run_dir)
    if latest is None:
        raise DataError(run_dir, "no point_cloud/iteration_<N>/point_cloud.ply in this run directory")
    return latest


def size_of_saved_model(path: str | Path, duration_s: float) -> ModelSize:
    """Accounting for a saved model: a run dir (latest iteration), an iteration dir, a .ply, or a .stgc file.

    Reads only the PLY header and the decoder state dict, so it works without the model package."""
    path = Path(path)
    if path.suffix == ".stgc":
        raise ValueError("use bitstream_size() for .stgc files: it needs the Gaussian count from the decoder")
    if path.is_file() and path.suffix == ".ply":
        ply = path
    elif (path / "point_cloud.ply").is_file():
        ply = path / "point_cloud.ply"
    else:
        ply = latest_iteration_dir(path) / "point_cloud.ply"
    count, names = read_ply_header(ply)
    variant = variant_of_fields(names, ply)
    decoder_file = ply.with_name("point_cloud.pt")
    floats = 0
    files = [ply]
    if decoder_file.is_file():

        try:
            state = torch.load(decoder_file, map_location="cpu", weights_only=True)
        except Exception as exc:  # a corrupt decoder file must name itself
            raise FormatError(decoder_file, f"cannot read decoder state dict ({exc})") from None
        floats = state_dict_floats(state)
        files.append(decoder_file)
    return model_size(count, variant, duration_s, floats, files)


def training_seconds(summary: Mapping[str, Any] | None) -> float | None:
    """Wall-clock training time from a train summary (RUN/train_summary.json, key `wall_seconds`)."""
    if not summary or summary.get("wall_seconds") is None:
        return None
    return float(summary["wall_seconds"])


# ------------------------------------------------------------------------------------------ speed


@dataclass
class RenderSpeed:
    """Render timing after warm-up: fps = 1 / mean seconds per frame, rendering with `threads` torch threads."""

    fps: float
    mean_ms: float
    median_ms: float
    frames_timed: int
    warmup: int
    threads: int = 0

    def as_dict(self) -> dict[str, float | int]:
        return asdict(self)


def speed_from_times(seconds: Sequence[float], warmup: int = 0) -> RenderSpeed | None:
    """Summarise per-render times, dropping the first `warmup` (JIT, caches, allocator)."""
    timed = np.asarray(list(seconds)[warmup:], dtype=np.float64)
    if timed.size == 0:
        return None
    mean = float(timed.mean())
    return RenderSpeed(
        fps=1.0 / mean if mean > 0 else math.inf,
        mean_ms=1e3 * mean,
        median_ms=1e3 * float(np.median(timed)),
        frames_timed=int(timed.size),
        warmup=int(warmup),
        threads=torch.get_num_threads(),
    )


def measure_render_speed(
    render: Callable[[Any], Any],
    items: Sequence[Any],
    warmup: int = 2,
    passes: int = 1,
    synchronize: Callable[[], None] | None = None,
) -> RenderSpeed:
    """Time `render(item)` for every item, `passes` times, after `warmup` untimed calls.

    `synchronize` (e.g. torch.cuda.synchronize) runs after each call so asynchronous GPU work is counted,
    as STG's test.py does."""
    if not items:
        raise ValueError("measure_render_speed needs at least one item to render")
    for i in range(warmup):
        render(items[i % len(items)])
        if synchronize:
            synchronize()
    times = []
    for _ in range(max(1, passes)):
        for item in items:
            start = time.perf_counter()
            render(item)
            if synchronize:
                synchronize()
            times.append(time.perf_counter() - start)
    result = speed_from_times(times, 0)
    assert result is not None
    result.warmup = warmup
    return result
