"""Training configuration: optimisation, densification, floater control, EMS, logging, checkpoints.

`iterations` is the number of real iterations a run trains. Every other iteration number that belongs to the
*schedule* (densification start/interval, pruning and reset windows, EMS start, PLY save points) is written on
the official 30k-iteration scale and multiplied by ONE factor, `schedule_scale`, when the run starts
(`resolve_schedule`). The `paper` preset is scale 1 with 30,000 iterations (the official STG schedule); the `cpu`
preset shrinks the same schedule by 0.3 and trains 9,000 iterations, so a 2-core CPU finishes a 320x180 capture
in about 20 minutes and a 640x360 one in about an hour. Operational counters (logging, checkpointing,
`stop_after`) are in real iterations and are not scaled.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import ClassVar, Literal

from stgc.codec.format import DEFAULT_QUALITY, QUALITY_LEVELS
from stgc.config import ConfigError, check
from stgc.official import family_options, official_value
from stgc.render.api import Backend


# Learning rates a run leaves to the data's official config family (TrainConfig.resolved).
RESOLVED_BY_DATA = family_options("train.lr.")


@dataclass(frozen=True)
class LearningRates:
    """Adam learning rates per parameter group (official STG `training_setup` defaults)."""

    xyz_init: float = field(default=1.6e-4, metadata={"help": "xyz lr at iteration 0, times the scene extent E"})
    xyz_final: float = field(
        default=1.6e-6, metadata={"help": "xyz lr at the last iteration (log-linear decay), times E"}
    )
    motion: float = field(default=2.8e-4, metadata={"help": "polynomial motion lr, times E (official 1.6e-4*0.5*3.5)"})
    features_dc: float = field(default=2.5e-3, metadata={"help": "base colour / feature lr"})
    features_t: float = field(default=1e-3, metadata={"help": "time-feature lr (full variant)"})
    opacity: float = field(default=5e-2, metadata={"help": "opacity logit lr"})
    scaling: float | None = field(default=None, metadata={
        "help": "log-scale lr; default: the official config of the data's family (stgc.official: 1.5e-3 for N3DV, "
                "else 5e-3)"})
    rotation: float = field(default=1e-3, metadata={"help": "quaternion lr"})
    omega: float = field(default=1e-4, metadata={"help": "angular velocity lr"})
    trbf_center: float = field(default=1e-4, metadata={"help": "temporal centre mu_t lr"})
    trbf_scale: float = field(default=3e-2, metadata={"help": "log temporal scale lr"})
    decoder: float = field(default=1e-4, metadata={"help": "feature decoder MLP lr (full variant)"})
    colour_correction: float = field(
        default=2e-3, metadata={"help": "per-camera colour correction lr (log gain and offset, SparseAdam)"}
    )

    def validate(self, prefix: str = "") -> None:
        # Zero is allowed: it freezes a group.
        for name, value in dataclasses.asdict(self).items():
            if value is None and name in RESOLVED_BY_DATA:
                continue
            check(value is not None and math.isfinite(value) and value >= 0, f"{prefix}{name}", value,
                  "a learning rate >= 0")
        check(self.xyz_init > 0 and self.xyz_final > 0, f"{prefix}xyz_final", self.xyz_final,
              "the xyz rates decay log-linearly, so both must be > 0")


@dataclass(frozen=True)
class DensifyConfig:
    """Clone/split, opacity pruning and opacity reset (official `controlgaussians`, densify mode 1)."""

    enabled: bool = field(default=True, metadata={"help": "run clone/split densification at all"})
    start: int = field(default=500, metadata={"help": "first densification iteration (schedule units)"})
    interval: int | None = field(
        default=None,
        metadata={"help": "iterations between densify/prune steps (schedule units); default: the official 100 when "
                          "the data ships its initial points, 500 when they are sparse (see SPARSE_CLOUD)"},
    )
    rounds: int | None = field(
        default=None,
        metadata={"help": "number of clone/split rounds (official desicnt: 6 N3D, 12 Technicolor); default: when the "
                          "data ships its initial points, its official config's (12 Technicolor, else 6), 20 when "
                          "they are sparse"},
    )
    grad_threshold: float = field(
        default=2e-4, metadata={"help": "mean NDC screen-space gradient norm above which a Gaussian is densified"}
    )
    percent_dense: float = field(
        default=0.01, metadata={"help": "max scale (fraction of E) below which a Gaussian is cloned, above split"}
    )
    split_count: int = field(default=2, metadata={"help": "Gaussians a split one becomes"})
    prune_opacity: float = field(
        default=0.005, metadata={"help": "after the densification rounds, prune Gaussians with opacity below this"}
    )
    prune_until: int = field(
        default=7000, metadata={"help": "opacity pruning stops at this iteration (schedule units; official 7000)"}
    )
    prune_in_rounds: bool | None = field(
        default=None,
        metadata={"help": "also prune Gaussians with opacity below prune_opacity at every clone/split round, as 3DGS "
                          "does (the official STG code computes that mask but never applies it, and prunes only after "
                          "the rounds, until prune_until: with the sparse-cloud schedule's 20 rounds to 35 percent of "
                          "the run, never); default: off when the data ships its initial points, on when they are "
                          "sparse"},
    )
    opacity_reset_interval: int = field(
        default=3000, metadata={"help": "reset opacities every this many iterations (schedule units; 0 = never)"}
    )
    opacity_reset_until: int = field(
        default=9000, metadata={"help": "no opacity reset at or after this iteration (schedule units)"}
    )
    opacity_reset_value: float = field(default=0.01, metadata={"help": "opacities are clamped to at most this value"})
    stats_views: Literal["last", "all"] = field(
        default="all",
        metadata={"help": "views of each batch whose screen-space gradients feed the statistics: all, or only the "
                          "last (official STG; half the signal for the same iterations)"},
    )
    stats_count: Literal["rendered", "in_frustum"] = field(
        default="rendered",
        metadata={"help": "views a Gaussian's mean gradient is averaged over: those that rendered it (temporally "
                          "visible), or every view whose frustum its 3-sigma box reaches, temporally visible or not "
                          "(official STG: its rasterizer sees every Gaussian; an invisible one adds 0 to the sum and "
                          "1 to the count)"},
    )
    max_gaussians: int = field(
        default=0,
        metadata={"help": "clone/split never takes the model above this many Gaussians: the candidates with the "
                          "largest gradients go first (0 = no cap). Bounds memory and iteration time"},
    )
    max_growth: float | None = field(
        default=None,
        metadata={"help": "clone/split never takes the model above this multiple of its initial Gaussian count "
                          "(0 = no cap; with max_gaussians, the smaller cap wins); default: no cap when the data "
                          "ships its initial points, 2 when they are sparse"},
    )

    # The official schedule: 6 rounds, one every 100 iterations right after iteration 500 (of 30k). It suits what
    # STG trains from, a dense per-frame COLMAP cloud. A cloud stgc builds itself (SIFT triangulation: a few hundred
    # points per frame; or random points) starts far too sparse for that: its Gaussians stay few and large, and the
    # render soft. For those, densify for longer (every 500 iterations for 20 rounds, to a third of the run, as 3DGS
    # does from its sparse SfM clouds), bounded to twice the initial count so that iteration time stays bounded.
    # Pruning in the rounds keeps the faint Gaussians (46 % of a trained panoptic model, never visible) from
    # holding the growth bound: measured +0.15 dB at 320x180 and +0.36 dB at 640x360 (benchmarks/RESULTS.md).
    OFFICIAL: ClassVar[dict] = {"interval": 100, "rounds": 6, "max_growth": 0.0, "prune_in_rounds": False}
    SPARSE_CLOUD: ClassVar[dict] = {"interval": 500, "rounds": 20, "max_growth": 2.0, "prune_in_rounds": True}

    def resolved(self, sparse_cloud: bool, family: str | None = None) -> DensifyConfig:
        """This config with every option left to its default (None) set for the initial cloud's kind: from the
        clouds a source ships, as the official config of the data's `family` trains (stgc.official)."""
        defaults = dict(self.SPARSE_CLOUD) if sparse_cloud else {
            **self.OFFICIAL, **{k: v for k in self.OFFICIAL
                                if (v := official_value(f"train.densify.{k}", family)) is not None}}
        return dataclasses.replace(self, **{k: v for k, v in defaults.items() if getattr(self, k) is None})

    @property
    def is_resolved(self) -> bool:
        return all(getattr(self, k) is not None for k in self.OFFICIAL)

    def validate(self, prefix: str = "") -> None:
        for name in ("start", "prune_until", "opacity_reset_interval", "opacity_reset_until"):
            check(getattr(self, name) >= 0, f"{prefix}{name}", getattr(self, name), ">= 0")
        check(self.rounds is None or self.rounds >= 0, f"{prefix}rounds", self.rounds, ">= 0 (or unset)")
        check(self.interval is None or self.interval >= 1, f"{prefix}interval", self.interval, ">= 1 (or unset)")
        check(self.split_count >= 2, f"{prefix}split_count", self.split_count, ">= 2")
        check(math.isfinite(self.grad_threshold) and self.grad_threshold > 0, f"{prefix}grad_threshold",
              self.grad_threshold, "> 0")
        check(0 < self.percent_dense < 1, f"{prefix}percent_dense", self.percent_dense, "in (0, 1)")
        check(0 <= self.prune_opacity < 1, f"{prefix}prune_opacity", self.prune_opacity, "in [0, 1)")
        check(0 < self.opacity_reset_value < 1, f"{prefix}opacity_reset_value", self.opacity_reset_value, "in (0, 1)")
        check(self.max_gaussians >= 0, f"{prefix}max_gaussians", self.max_gaussians, ">= 0 (0 = no cap)")
        check(self.max_growth is None or self.max_growth == 0 or (math.isfinite(self.max_growth)
                                                                   and self.max_growth >= 1),
              f"{prefix}max_growth", self.max_growth, "0 (no cap) or a finite number >= 1 (or unset)")

    def cap(self, initial_gaussians: int) -> int:
        """The Gaussian count clone/split may not exceed (0 = none) for a model that started with this many."""
        caps = [c for c in (self.max_gaussians, int((self.max_growth or 0) * initial_gaussians)) if c > 0]
        return min(caps) if caps else 0


@dataclass(frozen=True)
class FloaterConfig:
    """Floater control (not in official STG; see docs/training.md). Zero disables a rule."""

    near_camera: float = field(
        default=0.0,
        metadata={"help": "prune Gaussians whose centre is closer than this fraction of E to a training camera"},
    )
    max_world_scale: float = field(
        default=0.5,
        metadata={"help": "prune Gaussians whose largest axis (one standard deviation) exceeds this fraction of the "
                  "scene radius: the larger of E and the 99th percentile of the Gaussian centres' distances from "
                  "the training cameras' centroid (a Gaussian the size of the scene fogs views that no training "
                  "view constrains)"},
    )
    scale_min_opacity: float = field(
        default=0.5,
        metadata={"help": "the max_world_scale rule removes only Gaussians whose base opacity is at least this (a haze "
                  "needs opacity; large translucent Gaussians inside the scene do real work for some views, at "
                  "640x360 about 0.4 dB of them; 0 = any)"},
    )
    until: int = field(
        default=30000, metadata={"help": "apply the rules at densification intervals until this iteration (schedule units)"}
    )

    def validate(self, prefix: str = "") -> None:
        for name in ("near_camera", "max_world_scale"):
            value = getattr(self, name)
            check(math.isfinite(value) and value >= 0, f"{prefix}{name}", value, ">= 0 (0 = off)")
        check(0 <= self.scale_min_opacity <= 1, f"{prefix}scale_min_opacity", self.scale_min_opacity,
              "in [0, 1] (0 = any opacity)")
        check(self.until >= 0, f"{prefix}until", self.until, ">= 0")


@dataclass(frozen=True)
class EMSConfig:
    """Error-guided sampling: add Gaussians along the rays of badly reconstructed patches (official train.py)."""

    enabled: bool = field(default=False, metadata={"help": "enable error-guided sampling"})
    start: int = field(default=1600, metadata={"help": "first EMS iteration (schedule units)"})
    select_ssim: float = field(default=0.91, metadata={"help": "cameras below this SSIM are EMS candidates"})
    trigger_ssim: float = field(default=0.88, metadata={"help": "add points when a candidate's SSIM is below this"})
    error_quantile: float = field(default=0.6, metadata={"help": "pixels above this error quantile are errors"})
    patch: int = field(default=16, metadata={"help": "patch size in pixels"})
    patch_fraction: float = field(default=0.85, metadata={"help": "fraction of error pixels that marks a patch"})
    depth_near: float = field(default=0.7, metadata={"help": "near sample depth as a fraction of the view depth"})
    depth_far: float = field(default=7.5, metadata={"help": "far sample depth as a fraction of the view depth"})
    max_events: int = field(default=2, metadata={"help": "at most this many EMS insertions per run"})
    min_gap: int = field(default=100, metadata={"help": "iterations between two EMS insertions (schedule units)"})

    def validate(self, prefix: str = "") -> None:
        check(self.start >= 0, f"{prefix}start", self.start, ">= 0")
        for name in ("select_ssim", "trigger_ssim", "error_quantile", "patch_fraction"):
            value = getattr(self, name)
            check(math.isfinite(value) and 0 <= value <= 1, f"{prefix}{name}", value, "in [0, 1]")
        check(self.patch >= 1, f"{prefix}patch", self.patch, ">= 1 pixel")
        check(math.isfinite(self.depth_far) and 0 < self.depth_near <= self.depth_far, f"{prefix}depth_near",
              (self.depth_near, self.depth_far), "0 < depth_near <= depth_far")
        check(self.max_events >= 0, f"{prefix}max_events", self.max_events, ">= 0")
        check(self.min_gap >= 0, f"{prefix}min_gap", self.min_gap, ">= 0")


@dataclass(frozen=True)
class QuantizationAwareConfig:
    """Rate-aware fine-tuning (issue #17): the run's last iterations render the model as the .stgc codec stores it,
    so the model learns to survive the codec's quantization instead of meeting it after training."""

    iterations: int = field(default=0, metadata={
        "help": "the last N iterations render every Gaussian attribute quantized as the codec stores it at `quality` "
                "(straight-through gradients to the float parameters); 0 = off"})
    quality: int = field(default=DEFAULT_QUALITY, metadata={
        "help": "codec quality 1..5 (as stgc compress --quality) whose bit depths are simulated"})
    allocation: Literal["optimised", "ladder"] = field(default="optimised", metadata={
        "help": "how the depths are chosen, as the codec's option: 'optimised' = the rd-optimised allocation "
                "measured on the training views when the window opens (what stgc compress does by default), "
                "'ladder' = the quality's fixed depths (stgc compress of the run's final model at this quality "
                "stores the window's depths either way)"})
    position_bits: int = field(default=0, metadata={"help": "as the codec's position_bits (0 = the quality's)"})
    lr_scale: float = field(default=0.01, metadata={
        "help": "every learning rate is multiplied by this inside the window: the straight-through gradient only "
                "points the way, and a parameter that moves by a quantization step per iteration jumps between "
                "levels instead of settling (measured on a small scene: 0.01 beats 0.1 and 1)"})
    rate_weight: float = field(default=0.0, metadata={
        "help": "lambda of the rate term: the loss adds lambda x the estimated bits per Gaussian of the quantized "
                "attributes (their order-0 entropy under the model's own code histograms, stgc.codec.rate), so "
                "training trades distortion for rate; each lambda is one point of an RD curve; 0 = no rate term"})
    simulate: bool = field(default=True, metadata={
        "help": "render through the codec's quantization in the window; false keeps only the window's lower "
                "learning rates (the control that separates what the quantization teaches from what annealing does)"})
    mask: bool = field(default=False, metadata={
        "help": "also learn a keep factor per Gaussian in the window (after Compact3D's learned mask; it multiplies "
                "the opacity): with it the rate term charges every Gaussian lambda x its estimated bits, all of "
                "its sections included, times its factor, so a Gaussian whose contribution to the views is worth "
                "less than its bits fades out; in the window's last fifth the faded ones (factor < 1/2) are removed "
                "and the others keep their factor in their opacity; needs rate_weight > 0"})
    remeasure_at_settle: bool = field(default=True, metadata={
        "help": "with mask and the optimised allocation: when the mask settles, measure the depths again on the "
                "model it leaves, and train the window's last fifth at them (what compress then stores): the "
                "depths measured when the window opened were chosen for the unmasked model (no effect without "
                "a mask or with the ladder)"})
    mask_lr: float = field(default=0.02, metadata={
        "help": "Adam learning rate of the mask logits (not scaled by lr_scale; they start at 3, a Gaussian is "
                "removed if its logit is below 0 when the mask settles: at 0.02 a logit can cross 0 in 150 of a "
                "500-iteration window's 400 learning iterations)"})

    def validate(self, prefix: str = "") -> None:
        check(self.iterations >= 0, f"{prefix}iterations", self.iterations, ">= 0 (0 = off)")
        check(math.isfinite(self.lr_scale) and 0 < self.lr_scale <= 1, f"{prefix}lr_scale", self.lr_scale, "in (0, 1]")
        check(math.isfinite(self.rate_weight) and self.rate_weight >= 0, f"{prefix}rate_weight", self.rate_weight,
              ">= 0 (0 = no rate term)")
        check(self.rate_weight == 0 or self.simulate, f"{prefix}rate_weight", self.rate_weight,
              "0 when simulate is false: the rate term measures the codec's quantization, which the control skips")
        check(not self.mask or self.rate_weight > 0, f"{prefix}mask", self.mask,
              "false when rate_weight is 0: a Gaussian's price is lambda x its bits")
        check(math.isfinite(self.mask_lr) and self.mask_lr > 0, f"{prefix}mask_lr", self.mask_lr, "> 0")
        check(self.quality in QUALITY_LEVELS, f"{prefix}quality", self.quality,
              f"one of {', '.join(map(str, QUALITY_LEVELS))} (the codec's levels)")
        check(self.position_bits == 0 or 2 <= self.position_bits <= 24, f"{prefix}position_bits",
              self.position_bits, "0 or in 2..24")


@dataclass(frozen=True)
class TrainConfig:
    """Everything the trainer needs besides data, model and compaction configs."""

    preset: str = field(default="custom", metadata={
        "help": "name of the preset these values came from, as config.json records it; set by --preset, never given "
                "itself (a name of its own would contradict the schedule the run trains with)"})
    iterations: int = field(default=30000, metadata={"help": "iterations to train (real iterations, not scaled)"})
    schedule_scale: float = field(
        default=1.0, metadata={"help": "multiplies every schedule iteration (1 = official 30k schedule)"}
    )
    batch: int = field(default=2, metadata={"help": "training views of one timestamp per iteration (grads averaged)"})
    lambda_dssim: float = field(default=0.2, metadata={"help": "loss = (1-l)*L1 + l*(1-SSIM)"})
    seed: int = field(default=0, metadata={"help": "seed of every random stream (frame/view sampling, densification)"})
    colour_correction: Literal["auto", "on", "off"] = field(
        default="auto",
        metadata={"help": "learn a gain and offset per training camera and channel (Dynamic 3D Gaussians); auto: on "
                          "for real captures, off for synthetic renders (Blender/D-NeRF), whose cameras agree"},
    )
    mask_loss: float = field(
        default=0.0,
        metadata={"help": "weight of an extra L1 term over the foreground pixels of views that have a mask (Panoptic "
                          "seg/), normalised by their number, so that small moving subjects count as much as their "
                          "share of the error and not only of the image; 0 = off"},
    )
    backend: Backend = field(default="auto", metadata={"help": "rasterizer backend passed to stgc.render"})
    threads: int = field(default=0, metadata={
        "help": "threads of torch and the numba rasterizer, and the CPUs a segment's task asks Ray for (0 = leave "
                "as is: every core; a segment then takes a whole machine)"})
    lr: LearningRates = field(default_factory=LearningRates)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    floaters: FloaterConfig = field(default_factory=FloaterConfig)
    ems: EMSConfig = field(default_factory=EMSConfig)
    quantization_aware: QuantizationAwareConfig = field(default_factory=QuantizationAwareConfig)
    save_iterations: tuple[int, ...] = field(
        default=(7000, 10000, 12000, 25000, 30000),
        metadata={"help": "write an official PLY at these iterations (schedule units); the last one is always written"},
    )
    checkpoint_every: int = field(default=500, metadata={"help": "write RUN/checkpoint.pt every N iterations (0 = end only)"})
    log_every: int = field(default=50, metadata={"help": "append to RUN/metrics.jsonl every N iterations"})
    eval_every: int = field(default=0, metadata={"help": "evaluate on the test views every N iterations (0 = end only)"})
    eval_at_end: bool = field(default=True, metadata={"help": "evaluate on all test views x frames at the end"})
    progress: bool = field(default=True, metadata={"help": "show a progress bar"})
    tensorboard: bool = field(default=True, metadata={"help": "log to TensorBoard when it is importable"})
    stop_after: int | None = field(
        default=None,
        metadata={"help": "stop (checkpoint, unfinished) after this many iterations, as if killed; resume continues"},
    )

    # How a run saved before these options existed was trained (stgc.config.from_saved).
    SAVED_BEFORE: ClassVar[dict] = {"colour_correction": "off", "densify.stats_views": "last",
                                    "densify.stats_count": "rendered", "densify.prune_in_rounds": False,
                                    "densify.max_growth": 0.0, "quantization_aware.remeasure_at_settle": False,
                                    "floaters.scale_min_opacity": 0.0}

    def resolved(self, sparse_cloud: bool, family: str | None) -> TrainConfig:
        """This config with every option left to the data (None) resolved: the densification schedule for the
        initial cloud's kind, the learning rates for the official config of the data's `family`
        (`Dataset.official_config`; stgc.official). config.json records the resolved values."""
        lr = dataclasses.replace(self.lr, **{name: official_value(f"train.lr.{name}", family)
                                              for name in RESOLVED_BY_DATA if getattr(self.lr, name) is None})
        return dataclasses.replace(self, lr=lr, densify=self.densify.resolved(sparse_cloud, family))

    def validate(self, prefix: str = "") -> None:
        # The fixed-choice options (Literal-typed: backend, colour_correction, densify.stats_views, ...) are checked
        # by stgc.config.validate_config, which calls this.
        check(self.iterations >= 1, f"{prefix}iterations", self.iterations, ">= 1")
        check(math.isfinite(self.schedule_scale) and self.schedule_scale > 0, f"{prefix}schedule_scale",
              self.schedule_scale, "> 0")
        check(self.batch >= 1, f"{prefix}batch", self.batch, ">= 1")
        check(0 <= self.lambda_dssim <= 1, f"{prefix}lambda_dssim", self.lambda_dssim, "in [0, 1]")
        check(math.isfinite(self.mask_loss) and self.mask_loss >= 0, f"{prefix}mask_loss", self.mask_loss,
              ">= 0 (0 = off)")
        check(self.threads >= 0, f"{prefix}threads", self.threads, ">= 0 (0 = leave as is)")
        check(self.seed >= 0, f"{prefix}seed", self.seed, ">= 0")
        for name in ("checkpoint_every", "log_every", "eval_every"):
            check(getattr(self, name) >= 0, f"{prefix}{name}", getattr(self, name), ">= 0 (0 = never)")
        check(self.stop_after is None or self.stop_after >= 1, f"{prefix}stop_after", self.stop_after, ">= 1")
        check(all(i >= 1 for i in self.save_iterations), f"{prefix}save_iterations", self.save_iterations,
              "iterations >= 1")
        check(self.quantization_aware.iterations <= self.iterations, f"{prefix}quantization_aware.iterations",
              self.quantization_aware.iterations, f"at most the run's {self.iterations} iterations")


# 0.3 x 30k = 9,000 iterations (0.2 and 6,000 until session 12, when the iteration had become 1.75-2.3x faster):
# every `cpu` curve was still rising at 6,000, and the longer schedule gained on every scene measured
# (benchmarks/RESULTS.md, "Real captures", session 12) while a 640x360 run stays within an hour on 2 cores.
CPU_SCHEDULE_SCALE = 0.3


def paper_preset() -> TrainConfig:
    """The official STG schedule (30k iterations, N3D densify mode 1, statistics from the last view of a batch)."""
    return TrainConfig(preset="paper", densify=DensifyConfig(stats_views="last"))


def cpu_preset() -> TrainConfig:
    """The official schedule shrunk by `CPU_SCHEDULE_SCALE` for a 2-core CPU."""
    return TrainConfig(preset="cpu", iterations=round(30000 * CPU_SCHEDULE_SCALE), schedule_scale=CPU_SCHEDULE_SCALE)


PRESETS = {"paper": paper_preset, "cpu": cpu_preset}


def refuse_preset_option(given: Iterable[str]) -> None:
    """Raise ConfigError when `train.preset` is among the options `given` (dotted names): it names the preset the
    schedule came from (--preset), and a value given to it would record a schedule under another's name (a paper
    schedule labelled cpu); config.json keeps it, for reading only."""
    if "train.preset" in set(given):
        raise ConfigError(f"train.preset: set by the preset a run starts from (--preset {' or '.join(PRESETS)}), "
                          "not given as an option; choose the preset, then change its options")


def train_preset(name: str) -> TrainConfig:
    """The named preset ("paper" or "cpu")."""
    try:
        return PRESETS[name]()
    except KeyError:
        raise ValueError(f"unknown training preset {name!r}; expected one of {sorted(PRESETS)}") from None


@dataclass(frozen=True)
class Schedule:
    """The schedule in real iterations (the config's schedule units times `schedule_scale`)."""

    iterations: int
    densify_start: int
    densify_interval: int
    densify_end: int  # last iteration that may clone/split
    densify_rounds: int  # clone/split rounds (0 when densification is off)
    prune_until: int
    opacity_reset_interval: int
    opacity_reset_until: int
    floaters_until: int
    ems_start: int
    ems_min_gap: int
    save_iterations: tuple[int, ...]

    def is_densify_step(self, iteration: int) -> bool:
        return iteration > self.densify_start and (iteration - self.densify_start) % self.densify_interval == 0

    def is_opacity_reset(self, iteration: int) -> bool:
        return bool(self.opacity_reset_interval) and iteration % self.opacity_reset_interval == 0 \
            and iteration < self.opacity_reset_until

    def opacity_resets(self) -> tuple[int, ...]:
        """The iterations at which density control resets every opacity (`is_opacity_reset`)."""
        return _reset_iterations(self.opacity_reset_interval, self.opacity_reset_until, self.iterations)

    def first_densify_step(self, start: int) -> int | None:
        """The first iteration >= `start` at which density control acts (is_densify_step), or None when the run
        has none left."""
        after = max(start, self.densify_start + 1) - self.densify_start
        step = self.densify_start + self.densify_interval * -(-after // self.densify_interval)
        return step if step <= self.iterations else None

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


WINDOW_PREFIX = "train.quantization_aware."  # the rate-aware window's options, as dotted names with their section


def idle_window_options(train: TrainConfig) -> set[str]:
    """The rate-aware options (dotted, with their section) that act on nothing in a run trained with `train`
    (`_window_idle_reasons`). Two runs that differ only there trained alike; given for such a run, they are refused
    (`refuse_unused_window_options`), and a plan's --set leaves them out of it."""
    return set(_window_idle_reasons(train))


def _window_idle_reasons(train: TrainConfig) -> dict[str, str]:
    """{idle rate-aware option: why}: all but the window's length without a window; what the codec's quantization
    is simulated at, in the control (simulate false); the mask's learning rate without a mask; remeasure_at_settle
    without a settling mask measured by the optimised allocation."""
    window = train.quantization_aware
    if window.iterations == 0:
        return {f"{WINDOW_PREFIX}{f.name}": f"given for a run without a rate-aware window ({WINDOW_PREFIX}iterations "
                                            "is 0), where it acts on nothing; open a window or drop it"
                for f in dataclasses.fields(window) if f.name != "iterations"}
    idle: dict[str, str] = {}
    if not window.simulate:
        idle |= {f"{WINDOW_PREFIX}{name}": "acts only where the window simulates the codec's quantization "
                                           f"({WINDOW_PREFIX}simulate is false: the control)"
                 for name in ("quality", "allocation", "position_bits")}
    if not window.mask:
        idle[f"{WINDOW_PREFIX}mask_lr"] = f"acts only with {WINDOW_PREFIX}mask"
    if not (window.mask and window.allocation == "optimised"):
        idle[f"{WINDOW_PREFIX}remeasure_at_settle"] = (f"acts only with {WINDOW_PREFIX}mask and the optimised "
                                                        "allocation (a settling mask measured again)")
    return idle


def refuse_unused_window_options(train: TrainConfig, given: Iterable[str]) -> None:
    """Raise ConfigError when rate-aware options (`given`: dotted names) are set where they act on nothing
    (`idle_window_options`): they would be recorded, change nothing, and the run would be taken for the rate point
    they name."""
    reasons = _window_idle_reasons(train)
    unused = sorted(set(given) & set(reasons))
    if unused:
        raise ConfigError("; ".join(f"{key}: {reasons[key]}" for key in unused))


def _scaled(iteration: int, scale: float) -> int:
    return max(1, int(round(iteration * scale)))


def opacity_reset_iterations(cfg: TrainConfig) -> tuple[int, ...]:
    """The iterations at which density control resets every opacity (`Schedule.opacity_resets`), known before the
    data resolves the schedule: the reset options are not left to it."""
    d, s = cfg.densify, cfg.schedule_scale
    interval = _scaled(d.opacity_reset_interval, s) if d.opacity_reset_interval > 0 else 0
    return _reset_iterations(interval, _scaled(d.opacity_reset_until, s), int(cfg.iterations))


def _reset_iterations(interval: int, until: int, iterations: int) -> tuple[int, ...]:
    """Every multiple of `interval` (real iterations; 0 = none) below `until` and at most `iterations`."""
    return tuple(range(interval, min(until - 1, iterations) + 1, interval)) if interval > 0 else ()


def resolve_schedule(cfg: TrainConfig) -> Schedule:
    """Scale every schedule point but `iterations` by `cfg.schedule_scale` (never below one iteration)."""
    s = cfg.schedule_scale
    if s <= 0:
        raise ValueError(f"train.schedule_scale must be positive, got {s}")

    def scaled(x: int) -> int:
        return _scaled(x, s)

    d = cfg.densify
    if not d.is_resolved:
        raise ValueError("train.densify has options left to the data (interval, rounds, max_growth): resolve them "
                         "with TrainConfig.resolved(sparse_cloud, family) first")
    assert d.interval is not None and d.rounds is not None
    iterations = int(cfg.iterations)
    start, interval = scaled(d.start), scaled(d.interval)
    saves = sorted({min(scaled(x), iterations) for x in cfg.save_iterations} | {iterations})
    return Schedule(
        iterations=iterations,
        densify_start=start,
        densify_interval=interval,
        # Official: the first `desicnt` densification steps clone/split (start + interval * k, k = 1..rounds,
        # because its counter skips the very first call at `start`), later steps only prune.
        densify_end=start + interval * d.rounds if d.enabled else -1,
        densify_rounds=d.rounds if d.enabled else 0,
        prune_until=scaled(d.prune_until),
        opacity_reset_interval=scaled(d.opacity_reset_interval) if d.opacity_reset_interval > 0 else 0,
        opacity_reset_until=scaled(d.opacity_reset_until),
        # A learned mask tracks the model's rows through the rate-aware window: the floater rules stop before it.
        floaters_until=min(scaled(cfg.floaters.until), iterations - cfg.quantization_aware.iterations)
        if cfg.quantization_aware.mask else scaled(cfg.floaters.until),
        ems_start=scaled(cfg.ems.start),
        ems_min_gap=scaled(cfg.ems.min_gap),
        save_iterations=tuple(saves),
    )
