"""File-level codec operations: compress a trained run to .stgc, restore a run from it, size helpers."""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, get_args

from tqdm import tqdm

from stgc.config import check
from stgc.data.config import open_run_dataset
from stgc.errors import DataError, FormatError, StgcError
from stgc.fileio import atomic_open, file_sha256, write_json
from stgc.model import MIN_VISIBLE_OPACITY, STGModel
from stgc.model.layout import bytes_per_gaussian as ply_bytes_per_gaussian
from stgc.model.ply import resolve_ply_path
from stgc.run import Run, iteration_of
from stgc.train.colour import COLOUR_CORRECTION_NAME, saved_corrections

from .allocation import Allocation, encoder_settings
from .format import (
    DEFAULT_QUALITY,
    DEFAULT_ZSTD_LEVEL,
    QUALITY_LEVELS,
    DecodedModel,
    StgcHeader,
    decode,
    decode_metadata,
    encode,
    read_capped,
    read_header,
)
from .video import (
    VideoIndex,
    encode_video,
    is_video_stgc,
    read_video_index,
    read_video_segment,
    read_video_segment_metadata,
)
from .views import optimise_on_views

AllocationMode = Literal["auto", "trained", "optimised", "ladder"]
ALLOCATION_MODES = get_args(AllocationMode)
RESTORED_CONFIG_SECTIONS = ("data", "model")

log = logging.getLogger(__name__)


@dataclass
class CodecConfig:
    """How a trained model is written to the .stgc bitstream."""

    quality: int = field(default=DEFAULT_QUALITY, metadata={
        "help": "rate point 1 (smallest) .. 5 (most precise). With the rd-optimised allocation it is a PSNR budget "
                "on training views (1.0, 0.3, 0.1, 0.03, 0.01 dB); with the ladder it picks fixed bit depths "
                "(docs/stgc-format.md section 7). Default 3"})
    allocation: AllocationMode = field(default="auto", metadata={
        "help": "how bit depths are chosen: 'optimised' (render training views of the run's dataset and take the "
                "cheapest depths within the quality's PSNR budget), 'ladder' (fixed depths per quality, needs no "
                "data), 'trained' (the depths the run's rate-aware window trained the model through, "
                "train.quantization_aware; refused for a model that had none at this quality), 'auto' (trained "
                "when there are such depths, else optimised when the run's dataset can be opened, else ladder)"})
    allocation_views: int = field(default=16, metadata={
        "help": "training views (camera x frame, drawn with a fixed seed) the optimised allocation renders"})
    zstd_level: int = field(default=DEFAULT_ZSTD_LEVEL, metadata={
        "help": "zstd compression level 1..22 for every section (higher: a little smaller, slower to encode; "
                "decoding speed barely changes)"})
    position_bits: int = field(default=0, metadata={
        "help": "bits per position axis over the bounding box, 2..24; 0 = chosen with the other depths (the "
                "ladder allocation: the quality level's value)"})
    adaptive_delta: bool = field(default=True, metadata={
        "help": "per section, also try the adaptive layouts (delta along the Morton order, centred, predicted, "
                "byte-interleaved) and keep the smallest; off: plain planar bytes only (docs/stgc-format.md "
                "section 3)"})
    outlier_guard: bool = field(default=True, metadata={
        "help": "add bits to an attribute group whose range a few outliers stretch (keeps the bulk's precision)"})
    drop_invisible: bool = field(default=True, metadata={
        "help": "leave out Gaussians that no frame can show (temporal opacity below the rasterizer's 1/255 cut at "
                "every t in [0, 1]); renders are unchanged"})
    embed_run_config: bool = field(default=True, metadata={
        "help": "store the data and model sections of the run's config.json (about 0.4 KB compressed) so that "
                "`decompress` restores a run that can be evaluated"})

    def validate(self, prefix: str = "") -> None:
        check(self.quality in QUALITY_LEVELS, f"{prefix}quality", self.quality,
              f"one of {', '.join(map(str, QUALITY_LEVELS))}")
        check(1 <= self.zstd_level <= 22, f"{prefix}zstd_level", self.zstd_level, "in 1..22")
        check(self.position_bits == 0 or 2 <= self.position_bits <= 24, f"{prefix}position_bits", self.position_bits,
              "0 or in 2..24")
        check(self.allocation in ALLOCATION_MODES, f"{prefix}allocation", self.allocation,
              f"one of {', '.join(ALLOCATION_MODES)}")
        check(self.allocation_views >= 1, f"{prefix}allocation_views", self.allocation_views, ">= 1")
        # An option that would act on nothing is refused, not ignored (the user meant something by it).
        default_views = CodecConfig.__dataclass_fields__["allocation_views"].default
        check(self.allocation not in ("ladder", "trained") or self.allocation_views == default_views,
              f"{prefix}allocation_views", self.allocation_views,
              f"allocation {self.allocation} renders no views: leave it at {default_views} or use allocation "
              "optimised or auto")


@dataclass(frozen=True)
class CompressResult:
    path: Path
    num_gaussians: int
    variant: str
    file_bytes: int
    ply_bytes: int  # the input model's float32 PLY rows (152 B full / 128 B lite per Gaussian), the paper's anchor
    allocation: dict[str, Any] | None = None  # Allocation.summary() when the bit depths were rd-optimised
    dropped_invisible: int = 0  # Gaussians of the input left out because no frame shows them

    @property
    def input_gaussians(self) -> int:
        return self.num_gaussians + self.dropped_invisible

    @property
    def bytes_per_gaussian(self) -> float:
        """File bytes per Gaussian stored in it (per input Gaussian: bytes_per_input_gaussian)."""
        return self.file_bytes / self.num_gaussians if self.num_gaussians else float("nan")

    @property
    def bytes_per_input_gaussian(self) -> float:
        """File bytes per Gaussian of the input model: PLY row bytes / ratio_vs_ply."""
        return self.file_bytes / self.input_gaussians if self.input_gaussians else float("nan")

    @property
    def ratio_vs_ply(self) -> float:
        return self.ply_bytes / self.file_bytes

    def __str__(self) -> str:
        text = (f"{self.path}: {self.num_gaussians} Gaussians ({self.variant}), {self.file_bytes} bytes = "
                f"{self.bytes_per_gaussian:.2f} B per stored Gaussian, {self.ratio_vs_ply:.2f}x smaller than the "
                "input's float32 PLY rows")
        if self.dropped_invisible:
            text += f"\n{self.dropped_invisible} Gaussians left out: no frame shows them (opacity < 1/255 at every t)"
        if self.allocation and self.allocation.get("mode") == WINDOW_MODE:
            depths = self.allocation.get("depths")
            text += (f"\nbit depths of the rate-aware window the model trained through (quality "
                     f"{self.allocation['quality']}): "
                     + (" ".join(f"{k}={v:g}" for k, v in depths.items()) if depths else "the quality's ladder"))
        elif self.allocation:
            a = self.allocation
            text += (f"\nbit depths rd-optimised on {a['views']} training views: "
                     f"{' '.join(f'{k}={v:g}' for k, v in a['depths'].items())}; PSNR drop on those views "
                     f"{a['train_view_loss_db']:+.3f} dB, with one standard error {a['train_view_loss_bound_db']:+.3f} dB "
                     f"(budget {a['budget_db']} dB)")
            if not a["within_budget"]:
                text += "; the budget could not be met, the most precise depths were kept"
        else:
            text += "\nbit depths from the fixed ladder"
        return text


WINDOW_MODE = "rate-aware window"  # the allocation's mode in a file written with a window's depths


@dataclass(frozen=True)
class WindowDepths:
    """The bit depths a run's rate-aware window (train.quantization_aware) trained its final model through.

    For the window's whole length the forward pass saw the codec's quantization at these depths, so the model's
    values sit where these quantizers put them and the decoded file renders what training rendered. Measuring an
    allocation again on that model spends the quality's loss budget a second time: on blender_toys' learned-mask
    model it chose coarser depths, 4.6 % fewer bytes for 0.23 dB more loss (benchmarks/RESULTS.md)."""

    variant: str
    quality: int
    position_bits: int  # 0 = the quality's
    optimised: dict[str, Any] | None  # the window's rd-optimised allocation (its summary); None: the quality's ladder

    def encoder_settings(self) -> tuple[dict[str, int] | None, dict[str, list[float]] | None]:
        if self.optimised is None:
            return None, None
        return encoder_settings(self.variant, self.optimised["depths"], self.optimised.get("coarser_bits") or {})

    def summary(self) -> dict[str, Any]:
        window = {} if self.optimised is None else {
            "depths": dict(self.optimised["depths"]), "coarser_bits": dict(self.optimised.get("coarser_bits") or {}),
            "window_train_view_loss_db": self.optimised.get("train_view_loss_db")}
        return {"mode": WINDOW_MODE, "quality": self.quality, **window}

    def fits(self, config: CodecConfig) -> bool:
        """Whether `config` writes what the window simulated: the same quality and position bits, with the outlier
        guard, the invisible Gaussians left out of the fits and the adaptive layouts whose sizes it measured (as
        the simulation always has them)."""
        return (self.quality == config.quality and self.position_bits == config.position_bits
                and config.outlier_guard and config.drop_invisible and config.adaptive_delta)


def window_depths(source: str | Path) -> WindowDepths | None:
    """The depths a rate-aware window trained `source` through: when `source` is the final model of a finished run
    whose training ended with a simulating window (a fine-tuning's window is its own run's); else None (also for a
    config saved before the window's options existed: its depths are measured again, as they were then)."""
    run = Run.of(source)
    if run is None or not run.training_finished():
        return None
    latest = run.latest_model_dir()
    summary = run.read_summary(strict=False) or {}
    try:
        # Resolved: Run.of gives the run's absolute path, the source is as the user typed it.
        if latest is None or resolve_ply_path(latest).resolve() != resolve_ply_path(source).resolve():
            return None  # an earlier iteration: saved before the window, or inside it
    except FormatError:
        return None
    if iteration_of(latest) is None or iteration_of(latest) != summary.get("iterations"):
        return None  # the final iteration's model is gone (deleted, a partial copy): the latest is an earlier one
    train = (run.read_config(strict=False) or {}).get("train")
    window = train.get("quantization_aware") if isinstance(train, dict) else None
    if not isinstance(window, dict) or not window.get("iterations") or window.get("simulate") is not True:
        return None
    if not {"quality", "position_bits", "allocation"} <= set(window) or "variant" not in summary:
        return None
    optimised = summary.get("quantization_aware_allocation")
    if window["allocation"] == "optimised" and not (isinstance(optimised, dict) and optimised.get("depths")):
        return None
    return WindowDepths(str(summary["variant"]), int(window["quality"]), int(window["position_bits"]),
                        optimised if window["allocation"] == "optimised" else None)


# The codec options a file would not tell otherwise (quality is in the header, allocation in allocation_option,
# embed_run_config in whether run_config is there): recorded where they are not the defaults.
RECORDED_CODEC_OPTIONS = ("allocation_views", "zstd_level", "position_bits", "adaptive_delta", "outlier_guard",
                          "drop_invisible")


def custom_codec_options(config: CodecConfig) -> dict[str, Any]:
    """{option: value} of `config`'s RECORDED_CODEC_OPTIONS that are not the defaults: what a file written with
    it records as metadata `codec_options` (absent when empty), so that a reader can tell what wrote it."""
    default = CodecConfig()
    return {name: getattr(config, name) for name in RECORDED_CODEC_OPTIONS
            if getattr(config, name) != getattr(default, name)}


def written_without_window_depths(bitstream: str | Path, config: CodecConfig) -> bool:
    """Whether `bitstream`, written from its run's final model with the default allocation, measured its depths
    again although the model trained through a rate-aware window that `config` (the options it would be compressed
    with now) writes: compressed today it would store the window's (an stgc before `auto` took them). A file whose
    allocation was chosen explicitly (metadata `allocation_option`) is what was asked for, and `config` asking for
    a measured allocation or the ladder makes none out of date. A whole-video container is so when any of its
    segments is."""
    bitstream = Path(bitstream)
    if config.allocation not in ("auto", "trained"):
        return False
    try:
        if is_video_stgc(bitstream):
            run = Run(bitstream.parent)
            if not run.is_video():
                return False
            index = read_video_index(bitstream)
            return any(_measured_again(segment.path, read_video_segment_metadata(bitstream, k, index), config)
                       for k, segment in enumerate(run.segments()) if k < index.num_segments)
        return _measured_again(bitstream.parent, read_stgc_metadata(bitstream), config)
    except (FormatError, OSError, StgcError):
        return False


def _measured_again(run_dir: Path, metadata: dict[str, Any], config: CodecConfig) -> bool:
    """Whether a model's bitstream `metadata` says its depths were measured by default although the run's final
    model trained through a rate-aware window that `config` writes."""
    depths = window_depths(run_dir)
    if depths is None or not depths.fits(config):
        return False
    allocation = metadata.get("allocation")
    return "allocation_option" not in metadata and not (isinstance(allocation, dict)
                                                         and allocation.get("mode") == WINDOW_MODE)


def encode_with_config(arrays: dict, variant: str, decoder_state: dict | None, config: CodecConfig,
                       metadata: dict[str, Any] | None = None,
                       allocation: Allocation | WindowDepths | None = None) -> bytes:
    """Encode with `config`'s ladder, or with an rd-optimised allocation's (or a rate-aware window's) depths and
    step shapes."""
    config.validate()
    group_bits, step_scales = allocation.encoder_settings() if allocation else (None, None)
    return encode(arrays, variant, decoder_state, config.quality, zstd_level=config.zstd_level,
                  position_bits=config.position_bits or None, group_bits=group_bits, step_scales=step_scales,
                  adaptive_delta=config.adaptive_delta, outlier_guard=config.outlier_guard, metadata=metadata)


def write_stgc(path: str | Path, data: bytes) -> Path:
    """Write an encoded bitstream atomically (a failed write leaves no partial file)."""
    path = Path(path)
    with atomic_open(path, "wb") as f:  # fsynced before the rename: a crash cannot leave an empty file in place
        f.write(data)
    return path


def read_stgc(path: str | os.PathLike) -> DecodedModel:
    """Decode a .stgc file; any defect raises FormatError naming the file."""
    return decode(read_capped(path), source=str(path))


def read_stgc_metadata(path: str | Path) -> dict[str, Any]:
    """The metadata a .stgc file embeds (its run config, allocation, source), without decoding its Gaussians."""
    return decode_metadata(read_capped(path), source=str(path))


def read_stgc_header(path: str | Path) -> StgcHeader:
    """Header and section table only (sizes per section, counts); payloads are not decompressed."""
    return read_header(read_capped(path), source=str(path))


def stgc_file_bytes(path: str | Path) -> int:
    """The real size on disk of a .stgc file, in bytes (what rate/Mbps numbers must be computed from)."""
    return Path(path).stat().st_size


def stgc_bytes_per_gaussian(path: str | Path) -> float:
    """File bytes divided by the number of Gaussians stored in it."""
    return read_stgc_header(path).bytes_per_gaussian


def compress_run(run_or_model_path: str | Path, out_path: str | Path, quality: int | None = None,
                 config: CodecConfig | None = None) -> CompressResult | VideoCompressResult:
    """Compress a trained model (a run dir -> its latest iteration, an iteration dir, or a point_cloud.ply), or a
    whole-video run (`stgc train --segment-frames`) into one whole-video .stgc of its segments' bitstreams."""
    config = CodecConfig(**vars(config)) if config is not None else CodecConfig()
    if quality is not None:
        config.quality = quality
    config.validate()  # before minutes of bit allocation
    out_path = Path(out_path)
    if out_path.suffix != ".stgc":  # every reader tells a bitstream from a PLY by this suffix, case and all
        raise ValueError(f"{out_path}: the bitstream is written as a .stgc file (the name must end in .stgc, "
                         "lower case)")
    source = Path(run_or_model_path)
    if source.is_dir() and Run(source).is_video():
        return _compress_video(Run(source), out_path, config)
    if (source.is_dir() and Run(source).has_config() and not Run(source).holds_final_model()
            and Run(source).latest_model_dir() is not None):  # (without any, _encode_model says so)
        log.warning("%s has not finished training: compressing its latest saved model, %s", source,
                    Run(source).latest_model_dir())
    data, result = _encode_model(source, out_path, config)
    write_stgc(out_path, data)
    return result


@dataclass(frozen=True)
class VideoCompressResult:
    """A whole video written as one container: each segment's own result (its bytes inside the container)."""

    path: Path
    names: tuple[str, ...]
    segments: tuple[CompressResult, ...]
    file_bytes: int  # the container: the segments' bitstreams plus its header and index

    @property
    def num_gaussians(self) -> int:
        return sum(s.num_gaussians for s in self.segments)

    @property
    def ply_bytes(self) -> int:
        return sum(s.ply_bytes for s in self.segments)

    @property
    def ratio_vs_ply(self) -> float:
        return self.ply_bytes / self.file_bytes

    def __str__(self) -> str:
        lines = [f"{self.path}: whole video, {len(self.segments)} segments, {self.num_gaussians} Gaussians, "
                 f"{self.file_bytes} bytes, {self.ratio_vs_ply:.2f}x smaller than the inputs' float32 PLY rows"]
        for name, segment in zip(self.names, self.segments):
            text = str(segment).replace(f"{segment.path}: ", "", 1).replace("\n", "\n    ")
            lines.append(f"  {name}: {text}")
        return "\n".join(lines)


def _compress_video(run: Run, out_path: Path, config: CodecConfig) -> VideoCompressResult:
    # Everything that can refuse the video does so before the first segment's minutes of encoding.
    plan = run.read_video()["segments"]
    run.check_segment_frames(plan)  # the container gives each model the frames video.json says
    for entry in plan:
        segment = Run(run.path / str(entry["name"]))
        if segment.latest_model_dir() is None or not segment.holds_final_model():
            # A killed or failed segment still holds the models save_iterations wrote: half-trained, not the video.
            raise DataError(segment.path, "segment has not finished training (finish it with stgc train --resume)")
    payloads, results = [], []
    for entry in tqdm(plan, desc="compressing segments", unit="segment", leave=False, disable=len(plan) < 2):
        data, result = _encode_model(run.path / str(entry["name"]), out_path, config)
        payloads.append((entry["start"], entry["duration"], data))
        results.append(result)
    container = encode_video(payloads)
    write_stgc(out_path, container)
    return VideoCompressResult(out_path, tuple(str(e["name"]) for e in plan), tuple(results), len(container))


def _encode_model(source: Path, out_path: Path, config: CodecConfig) -> tuple[bytes, CompressResult]:
    """One model's bitstream and its result (named `out_path`, where it will be written)."""
    model = STGModel.load(source)
    input_gaussians = model.num_gaussians
    if config.drop_invisible:
        # A small margin below the cut: float rounding in a render must not be able to bring a dropped one back.
        model.prune(model.peak_temporal_opacity() >= MIN_VISIBLE_OPACITY * (1.0 - 1e-3))
    arrays = model.to_ply_arrays()
    # scene_extent is not stored: the official files do not carry it (it comes from the dataset's cameras).
    metadata: dict[str, Any] = {"source": source.name, "source_digest": model_digest(source)}
    if model.decoder_activation is not None:  # not in the official files; renders depend on it
        metadata["decoder_activation"] = model.decoder_activation
    iteration = iteration_of(source)
    if iteration is not None:
        metadata["iteration"] = iteration
    if model.num_gaussians < input_gaussians:
        metadata["dropped_invisible"] = input_gaussians - model.num_gaussians
    run = Run.of(source)
    run_dir = None if run is None else run.path
    if config.embed_run_config and run is not None and run.has_config():
        saved = run.read_config() or {}
        # What evaluating the restored run needs (its dataset and model options); training options would only
        # add bytes: a compressed model cannot resume training anyway.
        metadata["run_config"] = {key: saved[key] for key in RESTORED_CONFIG_SECTIONS if key in saved}
    if config.allocation != "auto":
        metadata["allocation_option"] = config.allocation  # asked for: never replaced as an old default's choice
    custom = custom_codec_options(config)
    if custom:  # (a file of the defaults stays as it was, byte for byte)
        metadata["codec_options"] = custom
    allocation: Allocation | WindowDepths | None = None
    window = window_depths(source) if config.allocation in ("auto", "trained") else None
    if window is not None and window.fits(config) and window.variant == model.variant:
        allocation = window
        metadata["allocation"] = window.summary()
    elif config.allocation == "trained":
        raise DataError(source, "codec.allocation=trained: " + (
            "the model did not train through a rate-aware window (train.quantization_aware) as a finished run's "
            "final model" if window is None else
            f"its rate-aware window trained quality {window.quality}, position_bits {window.position_bits}, with "
            "the outlier guard, invisible Gaussians left out and the adaptive layouts; compress with those"))
    elif window is not None and window.quality != config.quality:
        log.info("%s trained through a rate-aware window at quality %d: compress at that quality to store the "
                 "depths it learned; at quality %d the depths are chosen again", source, window.quality,
                 config.quality)
    if allocation is None and config.allocation != "ladder":
        dataset = _training_dataset(run_dir, source, required=config.allocation == "optimised")
        if dataset is not None:
            corrections = _corrections_of(source)
            if not corrections and run is not None and (run.path / Run.RESTORED_FROM).is_file() \
                    and not dataset.synthetic:
                log.warning("%s is restored from a bitstream, which does not hold the training cameras' colour "
                            "correction: the allocation measures its renders without it, so the depths it picks may "
                            "differ from those of a compression of the trained run", source)
            allocation = optimise_on_views(model, dataset, config.quality, views=config.allocation_views,
                                           position_bits=config.position_bits, outlier_guard=config.outlier_guard,
                                           adaptive_delta=config.adaptive_delta, corrections=corrections)
            metadata["allocation"] = allocation.summary()
    data = encode_with_config(arrays, model.variant, model.decoder_state(), config, metadata, allocation)
    return data, CompressResult(out_path, model.num_gaussians, model.variant, len(data),
                                input_gaussians * ply_bytes_per_gaussian(model.variant),
                                allocation.summary() if allocation else None, input_gaussians - model.num_gaussians)


SOURCE_DIGEST_DIGITS = 16


def model_digest(path: str | Path) -> str:
    """The first 16 hex digits of the SHA-256 of a saved model's PLY (`path`: the PLY, its iteration folder or its
    run): what a bitstream records of the model it was compressed from (metadata `source_digest`). Two runs whose
    configs differ only in training options (seeds, compaction cases) embed the same run config; this tells their
    files apart (`stgc.eval.evaluate.foreign_model`)."""
    return file_sha256(resolve_ply_path(path))[:SOURCE_DIGEST_DIGITS]


def _training_dataset(run_dir: Path | None, source: Path, required: bool) -> Any:
    """The dataset the run was trained on, or None (ladder) when it cannot be opened and is not required."""
    try:
        if run_dir is None:
            raise DataError(source, "not inside a run directory, so its dataset is unknown")
        return open_run_dataset(run_dir)
    except (DataError, FormatError) as exc:
        if required:
            raise DataError(source, f"the optimised allocation needs the run's training images: {exc}") from None
        return None


def _corrections_of(source: Path) -> dict:
    """The training cameras' colour correction saved beside the model (empty when it was trained without)."""
    return saved_corrections(resolve_ply_path(source).parent / COLOUR_CORRECTION_NAME)


def _model_from_decoded(decoded: DecodedModel, source: str | Path) -> Any:
    # The model package owns the parameter layout and the decoder.

    meta = decoded.metadata
    extent = meta.get("scene_extent", 1.0)
    if isinstance(extent, bool) or not isinstance(extent, (int, float)) or not extent > 0:
        raise FormatError(source, f"metadata scene_extent {extent!r} is not a positive number")
    activation = meta.get("decoder_activation", "sigmoid")
    if not isinstance(activation, str):
        raise FormatError(source, f"metadata decoder_activation {activation!r} is not a string")
    try:
        return STGModel.from_ply_arrays(decoded.arrays, decoded.variant, decoded.decoder_state,
                                        scene_extent=float(extent), decoder_activation=activation)
    except ValueError as exc:  # includes DataError/FormatError from validation of the decoder state
        raise FormatError(source, f"decoded model is invalid ({exc})") from None


def load_model(stgc_path: str | Path) -> Any:
    """Decode a .stgc file straight into an `stgc.model.STGModel` (e.g. to render or evaluate it)."""
    return _model_from_decoded(read_stgc(stgc_path), stgc_path)


def load_video_segment(stgc_path: str | Path, k: int, index: VideoIndex | None = None) -> tuple[Any, DecodedModel]:
    """Segment `k` of a whole-video .stgc as a renderable model, with what it decodes to (its metadata)."""
    decoded = read_video_segment(stgc_path, k, index)
    return _model_from_decoded(decoded, f"{stgc_path} segment {k}"), decoded


def decompress(stgc_path: str | Path, out_run_dir: str | Path, *, overwrite: bool = False) -> Path:
    """Restore a run directory from a .stgc file: point_cloud/iteration_<N>/ (official PLY + decoder) and, when
    the file embeds it, config.json. Returns the iteration directory. Like a training, it refuses a folder that
    already holds a run unless `overwrite` (its old model would stay beside the decoded one).

    A whole-video .stgc restores a whole-video run: RUN/video.json and one such run per segment in
    RUN/segment_<k>/; returns RUN."""
    if is_video_stgc(stgc_path):
        return _decompress_video(Path(stgc_path), Path(out_run_dir), overwrite)
    decoded = read_stgc(stgc_path)
    restored = _restorable(decoded, str(stgc_path))  # a defective file fails before anything is written
    run = Run.create(out_run_dir, overwrite=overwrite, keep=Path(stgc_path))
    return _restore(decoded, *restored, run, Path(stgc_path))


def _restorable(decoded: DecodedModel, source: str) -> tuple[Any, int]:
    """(model, iteration) of a decoded file, or a FormatError naming `source`."""
    iteration = decoded.metadata.get("iteration", 0)
    if isinstance(iteration, bool) or not isinstance(iteration, int) or iteration < 0:
        raise FormatError(source, f"metadata iteration {iteration!r} is not a non-negative integer")
    return _model_from_decoded(decoded, source), iteration


def _restore(decoded: DecodedModel, model: Any, iteration: int, run: Run, source: Path,
             frames: tuple[int, int] | None = None) -> Path:
    """Write the decoded model as `run`'s, with the run config the file embeds; `frames` (start, duration): a
    whole video's segment, whose frames restored_from.json keeps when no run config is embedded (else its data would
    open with every frame of the video, its times scaled by the whole length)."""
    iteration_dir = run.iteration_dir(iteration)
    model.save(iteration_dir)
    run_config = decoded.metadata.get("run_config")
    if isinstance(run_config, dict):
        run.write_config(run_config)
    # Renders depend on the decoder's activation, which the official files do not hold: without an embedded run
    # config (a bitstream of a bare or official model) restored_from.json says it (STGModel.load reads it there).
    activation = {} if model.decoder_activation is None else {"decoder_activation": model.decoder_activation}
    window = {} if frames is None or isinstance(run_config, dict) else {"start": frames[0], "duration": frames[1]}
    write_json(run.path / Run.RESTORED_FROM, {"bitstream": str(source.resolve()), "iteration": iteration,
                                              **activation, **window})
    return iteration_dir


def _decompress_video(stgc_path: Path, out_run_dir: Path, overwrite: bool) -> Path:
    index = read_video_index(stgc_path)
    # Every segment decodes before anything is written.
    decoded = [read_video_segment(stgc_path, k, index) for k in range(index.num_segments)]
    restored = [_restorable(d, f"{stgc_path} segment {k}") for k, d in enumerate(decoded)]
    run = Run.create(out_run_dir, overwrite=overwrite, keep=stgc_path)
    plan = []
    for k, (entry, segment, (model, iteration)) in enumerate(zip(index.entries, decoded, restored)):
        segment_run = run.segment(k)
        _restore(segment, model, iteration, segment_run, stgc_path, (entry.first_frame, entry.num_frames))
        plan.append({"name": segment_run.path.name, "start": entry.first_frame, "duration": entry.num_frames})
    run_config = decoded[0].metadata.get("run_config")
    data = run_config.get("data") if isinstance(run_config, dict) else None
    run.write_video({"segment_frames": index.entries[0].num_frames,
                     "data_path": data.get("path") if isinstance(data, dict) else None, "segments": plan})
    return run.path
