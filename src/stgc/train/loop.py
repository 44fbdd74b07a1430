"""The STG training loop (official `train.py`), with resumable checkpoints and compaction hooks.

One iteration: draw one timestamp and `batch` training views of it; render each view (the Gaussians at that
time computed once for all of them), loss 0.8·L1 + 0.2·(1 − SSIM) (+ `mask_loss` x L1 over the foreground where the
view has a mask), one backward of the views' summed loss / batch (so the parameter gradients are the batch mean);
one Adam step.
Then density control, opacity reset, the compaction controller, EMS, logging and checkpoints.

Determinism: every random draw of iteration i comes from streams seeded by (seed, i) (frame and view choice,
clone/split sampling, and the global python/numpy/torch generators that other packages may use), so a run resumed
from RUN/checkpoint.pt makes exactly the draws an uninterrupted run would have made.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import random
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol, cast

import numpy as np
import torch

from stgc import machine
from stgc.compaction import CompactionConfig, ProbeResult, STKNNCompactor
from stgc.compaction.config import REFERENCE_RUN_OPTIONS
from stgc.compaction.config import resolve_schedule as resolve_compaction_schedule
from stgc.config import (
    EXECUTION_OPTIONS,
    ConfigError,
    check_choices,
    from_saved,
    same_option_value,
    same_place,
    validate_config,
)
from stgc.data import DataConfig
from stgc.data.cameras import Camera
from stgc.data.config import initial_points_from_config
from stgc.data.dataset import Dataset
from stgc.errors import DataError, StgcError
from stgc.fileio import write_json
from stgc.metrics import mse, psnr_of_mse, ssim
from stgc.model import ModelConfig, STGModel
from stgc.model.config import DecoderActivation
from stgc.model.layout import Variant
from stgc.render import BACKENDS, select_backend
from stgc.run import Run, RunLock, run_config_problems, run_contents
from stgc.train.behaviour import BEHAVIOUR_KEY, recorded_behaviour
from stgc.train.checkpoint import (
    OPTIONS,
    OPTIONS_FINGERPRINT,
    load_checkpoint,
    restore_rng_states,
    save_checkpoint,
)
from stgc.train.colour import COLOUR_CORRECTION_NAME, ColourCorrection
from stgc.train.config import Schedule, TrainConfig, idle_window_options, resolve_schedule
from stgc.train.densify import DensityControl
from stgc.train.ems import ErrorGuidedSampler
from stgc.train.monitor import JsonLines, Progress, TensorBoard
from stgc.train.quantization import MASK_SETTLE_FRACTION, QuantizationSimulation
from stgc.train.strategy import (
    CompactionStrategy,
    DensityStrategy,
    ErrorGuidedStrategy,
    MaskStrategy,
    StepContext,
    Strategy,
)

IterationCallback = Callable[[int, dict[str, Any]], None]
ViewRenderer = Callable[[Camera], torch.Tensor]


class TestScore(Protocol):
    """What the trainer reads back from scoring the test views: their mean PSNR and SSIM."""

    @property
    def psnr(self) -> float: ...

    @property
    def ssim(self) -> float: ...


class TestEvaluator(Protocol):
    """Scores the dataset's test views during training (`train.eval_every`) and at its end (`train.eval_at_end`,
    recorded in the run). The evaluation layer provides one (`stgc.eval.RunEvaluator`) and the caller hands it in,
    so that the trainer stays below the evaluation: without one, training scores no test view."""

    def score(self, render: ViewRenderer, dataset: Dataset) -> TestScore: ...

    def score_and_record(self, render: ViewRenderer, dataset: Dataset, run: Run, model: STGModel) -> TestScore: ...

log = logging.getLogger(__name__)


def _config_dict(cfg: Any) -> Any:
    if cfg is None:
        return None
    if dataclasses.is_dataclass(cfg) and not isinstance(cfg, type):
        return dataclasses.asdict(cfg)
    return dict(cfg)


def _derive_seed(seed: int, iteration: int, stream: int) -> int:
    """A 63-bit seed for (run seed, iteration, stream) that does not depend on any earlier draw."""
    return int(np.random.SeedSequence([seed, iteration, stream]).generate_state(2, dtype=np.uint32).view(np.uint64)[0]) >> 1


def _seed_globals(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed & 0xFFFFFFFF)
    torch.manual_seed(seed)


# What a strategy reports once in a run and the metrics (when logged at all) must hold whenever it falls (the mask's
# settling step is rarely a logging iteration).
ALWAYS_LOGGED = ("mask_dropped",)


def _resolved(value: float | None) -> float:
    if value is None:
        raise ValueError("an option left to the data was not resolved")
    return value


def learning_rates(cfg: TrainConfig, extent: float, params: Any = None) -> dict[str, float]:
    """Initial lr per parameter group (position-like groups scale with the scene extent, as official).

    With `params` (a model's parameter dict), only the groups that model has (lite has no features_t)."""
    lr = cfg.lr
    rates = {
        "xyz": lr.xyz_init * extent,
        "scaling": _resolved(lr.scaling),  # TrainConfig.resolved
        "rotation": lr.rotation,
        "omega": lr.omega,
        "opacity": lr.opacity,
        "trbf_center": lr.trbf_center,
        "trbf_scale": lr.trbf_scale,
        "motion": lr.motion * extent,
        "features_dc": lr.features_dc,
        "features_t": lr.features_t,
    }
    return rates if params is None else {k: v for k, v in rates.items() if k in params}


def xyz_learning_rate(cfg: TrainConfig, extent: float, iteration: int, total: int) -> float:
    """Log-linear decay from xyz_init·E at iteration 0 to xyz_final·E at the last iteration (3DGS expon_lr, no delay)."""
    p = min(max(iteration / max(total, 1), 0.0), 1.0)
    a, b = cfg.lr.xyz_init * extent, cfg.lr.xyz_final * extent
    return math.exp(math.log(a) * (1 - p) + math.log(b) * p)


def _options_of_given_model(model: STGModel, model_cfg: ModelConfig | None) -> ModelConfig:
    """The model options config.json records for a run that starts from `model`: its own variant and decoder
    activation (a run recorded as 'sigmoid' that trained a 'clamp' decoder loads and renders wrong). A decoder
    activation given that contradicts the model's is refused; the variant is the model's (ModelConfig's default
    'full' is no request)."""
    activation = model.decoder_activation
    asked = None if model_cfg is None or model.variant == "lite" else model_cfg.decoder_activation
    if asked is not None and asked != activation:
        raise ConfigError(f"the options contradict the model training starts from: model.decoder_activation="
                          f"{asked!r}, the model's is {activation!r}")
    return dataclasses.replace(model_cfg or ModelConfig(), variant=cast(Variant, model.variant),
                               decoder_activation=cast(DecoderActivation | None, activation))


def build_initial_model(dataset: Dataset, data_cfg: DataConfig | None, model_cfg: ModelConfig | None) -> STGModel:
    """The STG model initialised from the dataset's point cloud as the data config asks (the model options left unset
    resolved for the dataset's official config family)."""
    cloud = initial_points_from_config(dataset, data_cfg)
    model_cfg = (model_cfg or ModelConfig()).resolved(dataset.official_config)
    return STGModel.from_config(cloud, model_cfg, scene_extent=dataset.scene_extent())


class GroundTruth:
    """Ground-truth images as float tensors in [0, 1], converted per use from the dataset's own cache (uint8, 4x
    smaller than float32, bounded by data.image_cache_mb: a second unbounded copy here held every image)."""

    def __init__(self, dataset: Dataset):
        self.dataset = dataset
        needed = sum(c.width * c.height * 3 for c in dataset.train)
        if needed > dataset.image_cache_bytes:  # then most draws decode their image again
            log.warning("%s: the training images take %d MiB decoded, more than data.image_cache_mb (%d): most "
                        "iterations will decode their images again; raise it if the memory is there",
                        dataset.name, needed >> 20, dataset.image_cache_bytes >> 20)

    def get(self, camera: Camera) -> torch.Tensor:
        return torch.from_numpy(self.dataset.load_image(camera)).to(torch.float32) / 255.0  # (a private copy)


class ForegroundMasks:
    """Training views' foreground masks as bool tensors, decoded once; None for a view without one."""

    def __init__(self, dataset: Dataset):
        self.dataset = dataset
        self._masks: dict[tuple[str, int], torch.Tensor | None] = {}

    def get(self, camera: Camera) -> torch.Tensor | None:
        key = (camera.name, camera.frame)
        if key not in self._masks:
            mask = self.dataset.load_mask(camera)
            self._masks[key] = None if mask is None else torch.from_numpy(np.ascontiguousarray(mask))
        return self._masks[key]


def _refuse_restarting_a_model_of_value(run: Run) -> None:
    """A resume without a checkpoint restarts the run from scratch, removing what the folder holds: refuse that
    where it holds a model this run's restart would not make again (a decoded bitstream's, an official run's, a
    finished training's whose checkpoint was removed) or a fine-tuning (it would restart as a run of its own). A
    start killed before its first checkpoint (a model saved on the way included) restarts, as a segment's retry."""
    why = ("a model restored from a bitstream (stgc decompress)" if (run.path / Run.RESTORED_FROM).is_file()
           else "a model without a config.json (an official STG run?)"
           if not run.has_config() and run.latest_model_dir() is not None
           else "a fine-tuning of another run" if (run.path / Run.CONTINUED_FROM).is_file()
           else "a finished training" if run.training_finished() else None)
    if why is None and run_contents(run.path) and not _holds_a_training(run):
        why = "files of a run no stgc training started (its config.json is not a training's)"
    if why is not None:
        raise StgcError(f"{run.path}: nothing to resume (no {Run.CHECKPOINT}): it holds {why}, which restarting would "
                        "remove; train into a new folder, or give --overwrite to replace it")


def _holds_a_training(run: Run) -> bool:
    """Whether the folder's run files are a training's start: its config.json is shaped as a training writes it."""
    try:
        saved = run.read_config()
    except StgcError:
        return False
    return saved is not None and not run_config_problems(saved)


def check_trainable(dataset: Dataset, train_cfg: TrainConfig, *, evaluate: bool) -> None:
    """What the trainer refuses about its data and options before it writes anything (a continuation calls it before
    it writes NEW, which the trainer then resumes). `evaluate`: whether the trainer gets a test evaluator."""
    extent = dataset.scene_extent()
    if not (math.isfinite(extent) and extent > 0):
        raise DataError(dataset.root, f"the scene extent (1.1 x the spread of the training cameras' centres) is "
                                      f"{extent:g}: the learning rates and the clone/split sizes scale with it, "
                                      f"so training needs training cameras at two or more places")
    if evaluate and (train_cfg.eval_every or train_cfg.eval_at_end) and not dataset.test:
        # Otherwise it trained, then failed at its first evaluation (with eval_every, before any checkpoint).
        raise DataError(dataset.root, "no test views to evaluate on (data.test_cameras): name some, or train "
                                      "without evaluating (train.eval_at_end=false, train.eval_every=0)")
    try:  # a backend the trainer's device (the CPU) cannot run
        select_backend(train_cfg.backend, torch.device("cpu"))
    except ValueError as exc:
        raise ConfigError(f"train.backend: {exc}") from None


def check_rate_aware_window(train_cfg: TrainConfig, compaction_cfg: CompactionConfig | None) -> None:
    """Refuse, before training (and before the run's folder is written), a rate-aware window that overlaps what
    cannot share it: ST-KNN compaction that renders the float model to decide (a probe-measured budget, prune
    trials, the weight order or the importance criterion), while the window trains the model as the codec stores it
    (its damage budget would hold for another model than the one pruned), and, with the learned
    mask, which keeps one logit per row, anything else that may add or remove Gaussians inside the window (the mask
    would lose track of its rows mid-run). `train_cfg`'s densification options must be resolved."""
    window = train_cfg.quantization_aware
    if not (window.iterations > 0 and window.simulate):
        return
    sched = resolve_schedule(train_cfg)
    first = sched.iterations - window.iterations + 1
    step = sched.first_densify_step(first)  # clone/split, opacity and floater pruning act only at these steps
    overlapping = []
    # A controller on the training loss alone reads the window's own (quantized) renders; a probe, trial or
    # blending-weight render (`renders_model`) measures the float model.
    if compaction_cfg is not None and compaction_cfg.method == "st-knn" and (
            window.mask or compaction_cfg.renders_model):
        pruning = resolve_compaction_schedule(compaction_cfg, sched.iterations)
        last_prune = pruning.iterations()[-1] if pruning.num_steps else 0
        if last_prune >= first:
            overlapping.append(f"ST-KNN compaction (it prunes until iteration {last_prune}; compact first, then "
                               "fine-tune the pruned run: stgc finetune RUN --out NEW ...)")
    if window.mask:
        if train_cfg.ems.enabled:
            overlapping.append("error-guided sampling (turn it off for the window: train.ems.enabled=false)")
        if step is not None and sched.densify_end >= step:
            overlapping.append(f"clone/split rounds (until iteration {sched.densify_end}; fine-tune the finished "
                               "run instead: stgc finetune RUN --out NEW ...)")
        if step is not None and sched.prune_until > step:
            overlapping.append(f"low-opacity pruning (until iteration {sched.prune_until}; fine-tune the finished "
                               "run instead: stgc finetune RUN --out NEW ...)")
    if overlapping:
        why = "they change the Gaussians the mask learns over" if window.mask else \
            ("the compaction's renders (its probe, trials or blending weights) would measure the float model while "
             "the window trains the quantized one")
        raise ConfigError(
            f"train.quantization_aware{'.mask' if window.mask else ''}: the rate-aware window (iterations "
            f"{first}-{sched.iterations}) overlaps {'; '.join(overlapping)}: {why}")


def views_by_camera(views: Sequence[Camera]) -> list[list[Camera]]:
    """`views` grouped by camera (cameras by name, each camera's views by frame)."""
    by_name: dict[str, list[Camera]] = {}
    for cam in views:
        by_name.setdefault(str(cam.name), []).append(cam)
    return [sorted(by_name[name], key=lambda c: c.frame) for name in sorted(by_name)]


def importance_views(views: Sequence[Camera]) -> list[Camera]:
    """The training views a Gaussian's blending weight is summed over (the importance criterion, pair_order
    weight): every camera and every frame, at max(#cameras, #frames) renders instead of (#cameras x #frames), the
    cameras taking the frames in turn. With one view per camera (as before 2026-11-28) a Gaussian whose lifetime
    falls between the sampled frames scored 0 however much it showed, and lost every pair it was in."""
    by_camera = views_by_camera(views)
    frames = sorted({cam.frame for cams in by_camera for cam in cams})
    count = max(len(by_camera), len(frames))
    picked = []
    for k in range(count):
        target = frames[(k * len(frames)) // count]
        picked.append(min(by_camera[k % len(by_camera)], key=lambda cam: (abs(cam.frame - target), cam.frame)))
    return picked


def blending_weights(model: STGModel, views: Sequence[Camera], background: torch.Tensor,
                     backend: str = "auto") -> torch.Tensor:
    """[N] float64: each Gaussian's blending weight (alpha x transmittance, summed over every pixel) summed over
    `views`, each rendered at its own time."""
    weights = torch.zeros(model.num_gaussians, dtype=torch.float64)
    with torch.no_grad():
        for cam in views:
            out = model.render(cam, t=float(cam.time), background=background, backend=backend, return_weights=True)
            if out.raster.weights is not None:
                weights.index_add_(0, out.index, out.raster.weights.to(torch.float64))
    return weights


class Trainer:
    """Holds the state of one run. `train()` is the public entry point; tests drive `Trainer` directly.

    It holds the run folder's lock (RunLock) from its construction until `run()` ends (or `close()`)."""

    def __init__(
        self,
        dataset: Dataset,
        data_cfg: DataConfig | None,
        model_cfg: ModelConfig | None,
        train_cfg: TrainConfig,
        compaction_cfg: CompactionConfig | None,
        out_dir: str | Path,
        *,
        model: STGModel | None = None,
        resume: bool = False,
        overwrite: bool = False,
        callback: IterationCallback | None = None,
        evaluator: TestEvaluator | None = None,
    ):
        validate_config(train_cfg, "train")
        # The other sections' fixed choices too, before anything is written (their other checks run where each
        # section is used: the data's when it is opened, the compaction's in the compactor).
        for section, options in (("data", data_cfg), ("model", model_cfg), ("compaction", compaction_cfg)):
            check_choices(options, section)
        check_trainable(dataset, train_cfg, evaluate=evaluator is not None)
        model_options_given = model_cfg is not None
        if model is not None:
            model_cfg = _options_of_given_model(model, model_cfg)
        # Options left unset follow the data (resolved_options); the resolved values are what config.json records.
        train_cfg, model_cfg = resolved_options(dataset, data_cfg, model_cfg, train_cfg)
        self.dataset, self.data_cfg, self.model_cfg = dataset, data_cfg, model_cfg
        self.cfg, self.compaction_cfg = train_cfg, compaction_cfg
        self.schedule: Schedule = resolve_schedule(train_cfg)
        # Before the run's folder is touched: the compactor reads and checks a loss reference run's log.
        self.compactor = self._make_compactor()
        self._check_loss_reference()
        check_rate_aware_window(train_cfg, compaction_cfg)
        # Claimed before anything in the folder is removed, truncated or written (a folder yet to be made, once made).
        self.lock = RunLock(out_dir)
        if Path(out_dir).is_dir():
            self.lock.acquire()
        try:
            self.out_run = Run(out_dir)
            resuming = resume and self.out_run.checkpoint_path.exists()
            if not resuming:
                restart = resume and not overwrite
                if restart:
                    _refuse_restarting_a_model_of_value(self.out_run)
                # A resume with nothing to resume restarts the same run, so its own partial files may go; files
                # derived from some other model (bitstreams, their evaluations) are not this start's to remove.
                self.out_run = Run.create(out_dir, overwrite=overwrite or restart, derived=not restart)
            self.lock.acquire()  # a new folder: claimed now that it exists
            self.callback = callback
            self.evaluator = evaluator
            if evaluator is None and (train_cfg.eval_every or train_cfg.eval_at_end):
                log.info("no test evaluator handed to the trainer: the test views are not scored during or after "
                         "training")
            machine.use_threads(train_cfg.threads)  # a task asking for k CPUs uses k
            self.metrics_log = JsonLines(self.out_run.path / Run.METRICS)
            self.compaction_log = JsonLines(self.out_run.path / Run.COMPACTION_LOG)
            self.images = GroundTruth(dataset)
            self.masks = self._make_foreground_masks()
            self.frames = dataset.train_frames  # frames only a test image holds (monocular data) are never drawn
            self.train_centers = np.array([c.center for c in dataset.train], dtype=np.float64).reshape(-1, 3)
            self.background = torch.tensor(dataset.background, dtype=torch.float32)
            self.elapsed_before = 0.0
            self.start_iteration = 0
            # How each session of the run executed (resumes may change the threads or the backend): rounding follows
            # them, so a loss reference's check reads every session's, not only the last one's.
            self.executions: list[dict[str, Any]] = []

            checkpoint = None
            if resuming:
                checkpoint = self._load_checkpoint()
                check_same_data(self.out_run.read_config(strict=False), dataset, self.out_run.path)
                self.model = self._model_from_checkpoint(checkpoint)
                if not model_options_given:
                    # The model it continues is the checkpoint's: its variant and decoder activation are the run's,
                    # as a model handed in to start from gives its own.
                    model_cfg = _options_of_given_model(self.model, None).resolved(dataset.official_config)
                    self.model_cfg = model_cfg
            else:
                self.model = model if model is not None else build_initial_model(dataset, data_cfg, model_cfg)
                if model is not None:
                    # The learning rates, the clone/split size limit and the floater rules scale with the data's
                    # extent, which a model built or loaded elsewhere does not carry (STGModel.load says 1.0).
                    model.scene_extent = dataset.scene_extent()
                self.metrics_log.clear()
                self.compaction_log.clear()
                self._write_config()
            # What every checkpoint records, and what a resumed one must have been trained with.
            self.options = run_options(self._run_config())
            self.options_fingerprint = options_fingerprint(self.options)
            if checkpoint is not None:
                self._refuse_a_checkpoint_of_other_options(checkpoint)
            self.decoder_ray_origin = _chosen(model_cfg.decoder_ray_origin, dataset.synthetic)
            self.decoder_ray_direction = _chosen(model_cfg.decoder_ray_direction, dataset.view_dependent_colour)
            if self.model.decoder is not None:
                self.model.decoder.ignore_ray_inputs(origin=not self.decoder_ray_origin,
                                                     direction=not self.decoder_ray_direction)
            self.extent = float(self.model.scene_extent)
            self.optimizer = self.model.make_optimizer(
                learning_rates(train_cfg, self.extent, self.model.params), train_cfg.lr.decoder
            )
            self.density = DensityControl(train_cfg.densify, train_cfg.floaters, self.schedule,
                                          self.model.num_gaussians, self.train_centers)
            self.colour = self._make_colour_correction()
            self.ems = ErrorGuidedSampler(
                train_cfg.ems, self.schedule.ems_start, self.schedule.ems_min_gap,
                [str(c.name) for c in dataset.train], _resolved(model_cfg.trbf_scale_init), train_cfg.backend,
            )
            # After the optimizer step, in this order: density control, error-guided points, compaction.
            self.strategies: list[Strategy] = [DensityStrategy(self.density),
                                               ErrorGuidedStrategy(self.ems, self.density)]
            self.quantization = QuantizationSimulation(train_cfg.quantization_aware) if (
                train_cfg.quantization_aware.iterations > 0 and train_cfg.quantization_aware.simulate) else None
            if self.quantization is not None and train_cfg.quantization_aware.mask:
                window = train_cfg.quantization_aware.iterations
                settle = self.schedule.iterations - round(MASK_SETTLE_FRACTION * window)
                self.strategies.append(MaskStrategy(self.quantization, self.density, settle))
            if self.compactor is not None:
                self.strategies.append(CompactionStrategy(
                    self.compactor, lambda event: self.compaction_log.append(_jsonable(event)), self.density,
                    self.importance, self.probe,
                ))  # fmt: skip
            if checkpoint is not None:
                self._restore(checkpoint)
        except BaseException:
            self.lock.release()
            raise

    # ------------------------------------------------------------------------------------------- setup
    def _run_config(self) -> dict[str, Any]:
        configs = {"data": self.data_cfg, "model": self.model_cfg, "train": self.cfg, "compaction": self.compaction_cfg}
        return run_config(self.dataset, configs, self.schedule)

    def _write_config(self) -> None:
        self.out_run.write_config(self._run_config())

    def _check_loss_reference(self) -> None:
        """A damage budget held against a reference run is only meaningful when that run is this run unpruned: the
        same data, model and training options (all but how it executes) and the same pruning schedule and probe.
        Refuse, naming the differences, before anything is trained (the log's own checks cannot see them)."""
        cfg = self.compaction_cfg
        # A run that prunes nothing holds no budget: a continuation of a budgeted run keeps its compaction section
        # (method switched off), loss reference and all.
        if cfg is None or cfg.method == "none" or not cfg.loss_reference:
            return
        reference = Path(cfg.loss_reference)
        reference_dir = reference if reference.is_dir() else reference.parent
        theirs = Run(reference_dir).read_config()
        if theirs is None:
            raise DataError(reference_dir, "the loss reference has no config.json to check it against this run")
        mine = json.loads(json.dumps(self._run_config()))  # as config.json holds it: tuples read back as lists
        differences = []
        sections = {"data": DataConfig, "model": ModelConfig, "train": TrainConfig, "compaction": CompactionConfig}
        their_train = {k: v for k, v in (theirs.get("train") or {}).items() if k != "resolved_schedule"}
        try:  # options that acted on nothing in either run (rate-aware ones without a window) are no difference
            idle = idle_window_options(self.cfg) & idle_window_options(from_saved(TrainConfig, their_train))
        except ValueError:  # ConfigError included: a reference this version cannot read differs anyway, below
            idle = set()
        for section, cls in sections.items():
            ours, saved = _flat(mine.get(section) or {}), _flat(theirs.get(section) or {})
            # A reference saved before an option existed trained as that option's SAVED_BEFORE value says; where
            # the class says nothing, the option is not compared (as the experiment runner's reuse check).
            before = getattr(cls, "SAVED_BEFORE", {})
            saved = {**{k: v for k, v in before.items() if k in ours}, **saved}
            for key in sorted(set(ours) | set(saved)):
                name = f"{section}.{key}"
                if (name in EXECUTION_OPTIONS or name in _PRUNED_RUN_ONLY or name in idle
                        or key.startswith("resolved_schedule")):
                    continue
                if key not in saved:
                    continue
                if not same_option_value(name, ours.get(key), saved.get(key)):
                    differences.append(f"{name}: this run {ours.get(key)!r}, the reference {saved.get(key)!r}")
        differences += self._rounding_differences(reference_dir, theirs)
        if differences:
            raise DataError(reference_dir / Run.CONFIG, "the loss reference is not this run's configuration "
                            "trained unpruned: " + "; ".join(differences))

    def _rounding_differences(self, reference_dir: Path, theirs: dict[str, Any]) -> list[str]:
        """How this run and its loss reference would execute differently enough to round differently: the numba
        rasterizer sums per-thread partial rows, so other thread counts (or another backend) drift apart within a
        few hundred iterations, and the budget would count that drift as pruning damage. The reference's threads
        are the counts its sessions trained with (its train_summary.json: a resume may have changed them), else its
        config's when that names one."""
        differences = []
        summary = Run(reference_dir).read_summary() or {}
        sessions = [s for s in summary.get("executions") or [] if isinstance(s, dict)]
        saved_threads = (theirs.get("train") or {}).get("threads")
        my_threads = self.cfg.threads or torch.get_num_threads()
        if sessions:
            # A session before the history was kept (a checkpoint of older code) trained with the config's count.
            config_threads = saved_threads if isinstance(saved_threads, int) and saved_threads > 0 else None
            their_counts = {s.get("threads") if s.get("threads") is not None else config_threads for s in sessions}
        else:  # a summary written before the sessions were recorded: its last session's, else the config's
            their_counts = {summary.get("threads") or saved_threads or None}
        if len(their_counts) > 1:
            known = [str(n) for n in sorted(n for n in their_counts if isinstance(n, int))]
            unrecorded = ", and an unrecorded one" if None in their_counts else ""
            differences.append(f"train.threads: the reference was resumed with another thread count ("
                               f"{' and '.join(known) or 'unknown'}{unrecorded}: its losses drifted from one session "
                               "to the next)")
        elif isinstance(their := next(iter(their_counts)), int) and their != my_threads:
            differences.append(f"train.threads: this run trains with {my_threads}, the reference trained with "
                               f"{their} (other thread counts round differently and drift apart)")
        cpu = torch.device("cpu")
        mine = select_backend(self.cfg.backend, cpu)
        their_backend = (theirs.get("train") or {}).get("backend")
        their_backends = {s.get("backend") for s in sessions} - {None} or (
            {select_backend(their_backend, cpu)} if isinstance(their_backend, str) and their_backend in BACKENDS
            else set())
        if their_backends - {mine}:
            differences.append(f"train.backend: this run renders with {mine!r}, the reference with "
                               f"{' and '.join(sorted(str(b) for b in their_backends))}")
        return differences

    def _make_compactor(self) -> STKNNCompactor | None:
        cfg = self.compaction_cfg
        if cfg is None or cfg.method == "none":
            return None
        return STKNNCompactor(cfg, total_iterations=self.schedule.iterations,
                              opacity_resets=self.schedule.opacity_resets())

    def _make_foreground_masks(self) -> ForegroundMasks | None:
        """The masks of the mask term, or None when the term is off or the data has no masks (said once)."""
        if self.cfg.mask_loss <= 0:
            return None
        ds = self.dataset
        if not ds.has_masks:
            log.warning("%s: train.mask_loss=%g, but the data has no foreground masks: training without the mask term",
                        ds.name, self.cfg.mask_loss)
            return None
        unmasked = sorted({str(c.name) for c in ds.train if ds.mask_path(c) is None})
        if unmasked:
            log.warning("%s: training views of cameras %s have no foreground mask and train without the mask term",
                        ds.name, ", ".join(unmasked))
        return ForegroundMasks(ds)

    def _make_colour_correction(self) -> ColourCorrection | None:
        if not _chosen(self.cfg.colour_correction, not self.dataset.synthetic):
            return None
        return ColourCorrection(self.dataset.train_views, self.cfg.lr.colour_correction)

    def _load_checkpoint(self) -> dict[str, Any]:
        """The checkpoint to resume, refused (DataError naming it) where no config.json says which options it belongs
        to: a fine-tuning killed while it copied its source's checkpoint left one so, and `stgc train --resume`
        then trained it with the command line's defaults, another training's."""
        if not self.out_run.has_config():
            raise DataError(self.out_run.checkpoint_path, f"no {Run.CONFIG} beside it records the options it was "
                            "trained with (a fine-tuning stopped while it was started?), so resuming would continue "
                            "it under other ones; start the run again (stgc finetune or stgc train with --overwrite)")
        return load_checkpoint(self.out_run.path)

    def _refuse_a_checkpoint_of_other_options(self, ckpt: dict[str, Any]) -> None:
        """Refuse (DataError naming the checkpoint, and the options that differ) to continue a checkpoint trained with
        other options than this run's (`run_options`): it would silently become the rest of another training. A
        checkpoint written before the options were recorded carries none: the run's config.json, which a resume
        trains with, is all there is to go by."""
        recorded = ckpt.get(OPTIONS_FINGERPRINT)
        if recorded is None or recorded == self.options_fingerprint:
            return
        recorded_options = ckpt.get(OPTIONS)
        theirs: dict[str, Any] = {}
        if isinstance(recorded_options, dict):
            # An option added since the checkpoint was written: it trained as the option's SAVED_BEFORE says (never
            # as a value given now), as config.json is read back.
            theirs = {**_saved_before_options(), **recorded_options}
            if options_fingerprint(theirs) == self.options_fingerprint:
                return
        missing = object()
        differences = [f"{name}: the checkpoint's {theirs.get(name)!r}, this run's {self.options.get(name)!r}"
                       for name in sorted(set(theirs) | set(self.options))
                       if theirs.get(name, missing) != self.options.get(name, missing)]
        shown = "; ".join(differences[:6]) + ("; ..." if len(differences) > 6 else "")
        raise DataError(self.out_run.checkpoint_path, f"was trained with other options than this run's "
                        f"({shown or 'they differ'}); resuming it would continue that training under these: resume "
                        "the run with its own options (stgc train --out RUN --resume, giving only options of how it "
                        "runs, such as threads), or train into a new folder")

    def _model_from_checkpoint(self, ckpt: dict[str, Any]) -> STGModel:
        return STGModel.from_state_dict(ckpt["model"])

    def _restore(self, ckpt: dict[str, Any]) -> None:
        self.optimizer.load_state_dict(ckpt["optimizer"])
        for strategy in self.strategies:
            strategy.load_state_dict(ckpt)
        self.start_iteration = int(ckpt["iteration"])
        self.elapsed_before = float(ckpt["elapsed_s"])
        # A checkpoint written before the history was kept: its sessions' execution is unknown (None).
        self.executions = list(ckpt.get("executions") or [{"from_iteration": 0, "threads": None, "backend": None}])
        if self.colour is not None and ckpt.get("colour_correction") is not None:
            self.colour.load_state_dict(ckpt["colour_correction"])
        if self.quantization is not None and self.in_quantization_window(self.start_iteration):
            # Only a resume inside this run's window continues its bit depths and mask; a fine-tuning's checkpoint
            # (its source's end, before the window) may hold another window's, at another quality and options.
            self.quantization.load_state_dict(ckpt.get("quantization_aware"))
        restore_rng_states(ckpt["rng"])
        self.metrics_log.truncate_after(self.start_iteration)
        self.compaction_log.truncate_after(self.start_iteration)

    def checkpoint_payload(self, iteration: int, elapsed: float) -> dict[str, Any]:
        model = self.model
        return {
            "iteration": iteration,
            "elapsed_s": elapsed,
            "model": model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "compactor": None,  # replaced by the compaction strategy's state when there is one
            **{key: value for strategy in self.strategies for key, value in strategy.state_dict().items()},
            "colour_correction": None if self.colour is None else self.colour.state_dict(),
            "quantization_aware": None if self.quantization is None else self.quantization.state_dict(),
            "executions": self.executions,
            OPTIONS_FINGERPRINT: self.options_fingerprint,
            OPTIONS: self.options,
        }

    # ------------------------------------------------------------------------------------------- one step
    def _set_learning_rates(self, iteration: int) -> float:
        """The iteration's learning rates: xyz on its decay, the others (the colour correction's too) constant, all
        times quantization_aware.lr_scale inside the rate-aware window. Returns the xyz rate."""
        scale = self.cfg.quantization_aware.lr_scale if self.in_quantization_window(iteration) else 1.0
        base = {**learning_rates(self.cfg, self.extent), "decoder": self.cfg.lr.decoder,
                "xyz": xyz_learning_rate(self.cfg, self.extent, iteration, self.schedule.iterations)}
        for group in self.optimizer.param_groups:
            if group.get("name") in base:
                group["lr"] = base[group["name"]] * scale
        if self.colour is not None:
            self.colour.scale_learning_rate(scale)
        return base["xyz"] * scale

    def in_quantization_window(self, iteration: int) -> bool:
        """Whether `iteration` is one of the run's last quantization_aware.iterations (stgc.train.quantization)."""
        window = self.cfg.quantization_aware.iterations
        return window > 0 and iteration > self.schedule.iterations - window

    def view_loss(self, render_rgb: torch.Tensor, gt: torch.Tensor, camera: Camera,
                  need_ssim: bool = False) -> tuple[torch.Tensor, float]:
        """(loss, SSIM value) of one training view; the SSIM is NaN when the loss has no SSIM term, unless
        `need_ssim`."""
        lam = self.cfg.lambda_dssim
        error = (render_rgb - gt).abs()
        loss = error.mean()
        ssim_value = float("nan")
        if lam > 0:
            s = ssim(render_rgb, gt)
            loss, ssim_value = (1.0 - lam) * loss + lam * (1.0 - s), float(s.detach())
        elif need_ssim:
            with torch.no_grad():
                ssim_value = float(ssim(render_rgb, gt))
        foreground = None if self.masks is None else self.masks.get(camera)
        if foreground is not None and bool(foreground.any()):
            loss = loss + self.cfg.mask_loss * error[foreground].mean()
        return loss, ssim_value

    def train_step(self, iteration: int) -> dict[str, Any]:
        """Render, backpropagate and update once; returns the iteration's numbers."""
        rng = np.random.default_rng(_derive_seed(self.cfg.seed, iteration, 0))
        frame = self.frames[int(rng.integers(len(self.frames)))]
        cameras = list(self.dataset.train_at(frame))
        batch = self.cfg.batch
        picks = rng.choice(len(cameras), size=batch, replace=len(cameras) < batch)
        views = [cameras[int(i)] for i in picks]
        t = float(views[0].time)
        lr_xyz = self._set_learning_rates(iteration)

        total_loss, total_mse = 0.0, 0.0
        ems_view = None
        seen, rate_bits = self.quantized_params(iteration)
        mask = None if seen is None or self.quantization is None else self.quantization.mask
        # The learned mask keeps one logit per row: nothing may remove one while it learns (not even a row gone
        # non-finite: its render stops the run, as before the density control removed such rows between rounds).
        self.density.rows_fixed = mask is not None
        # The batch's views share t: the Gaussians at t are computed once, and the summed loss goes back through
        # them once (render_views).
        with self.model.params_replaced(seen):
            renders = self.model.render_views(views, t, background=self.background, backend=self.cfg.backend,
                                              opacity_scale=None if mask is None else mask.keep_factor())
        losses = []
        for k, (cam, out) in enumerate(zip(views, renders)):
            gt = self.images.get(cam)
            rgb = out.rgb if self.colour is None else self.colour.apply(out.rgb, cam.name)
            # Error-guided sampling picks its views by their SSIM, whether or not the loss has an SSIM term.
            loss, ssim_value = self.view_loss(rgb, gt, cam, need_ssim=self.ems.listening(iteration))
            losses.append(loss)
            if self.ems.observe(iteration, cam, ssim_value, last_of_batch=k == batch - 1):
                ems_view = (cam, rgb.detach(), gt)
            total_loss += float(loss.detach())
            total_mse += float(((rgb.detach().clamp(0, 1) - gt) ** 2).mean())
        if not math.isfinite(total_loss):
            # Its gradients would make every Gaussian it reached non-finite, and the non-finite pruning would then
            # remove them all without a word.
            raise StgcError(f"{self.out_run.path}: training diverged at iteration {iteration}: the loss is "
                            f"{total_loss} (frame {frame}, views {', '.join(str(c.name) for c in views)})")
        objective = torch.stack(losses).sum() / batch
        if rate_bits is not None:
            objective = objective + self.cfg.quantization_aware.rate_weight * rate_bits
        objective.backward()
        for k, (cam, out) in enumerate(zip(views, renders)):
            self.density.observe(out, k, batch, self.model, cam, t)
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        if mask is not None:
            mask.step()
        if self.colour is not None:
            self.colour.step()
        mean_loss = total_loss / batch
        mean_mse = total_mse / batch
        step = {"t": t, "frame": frame, "loss": mean_loss, "psnr": psnr_of_mse(max(mean_mse, 1e-12)),
                "lr_xyz": lr_xyz, "ems_view": ems_view}
        if seen is not None:
            step["quantized"] = True
        if rate_bits is not None:
            step["rate_bits"] = float(rate_bits.detach())
        return step

    def quantized_params(self, iteration: int) -> tuple[dict[str, torch.Tensor] | None, torch.Tensor | None]:
        """In the rate-aware window (the run's last quantization_aware.iterations): the parameters as the codec
        stores them, with straight-through gradients, and the rate term's bits per Gaussian when it is on
        (stgc.train.quantization); else (None, None): the float model."""
        if self.quantization is None or not self.in_quantization_window(iteration):
            return None, None
        if self.quantization.settings is None and self.cfg.quantization_aware.allocation == "optimised":
            log.info("rate-aware window: measuring the codec's bit allocation on the training views")
            self.quantization.prepare(self.model, self.dataset, None if self.colour is None else self.colour.as_dict())
            log.info("rate-aware window: depths %s", (self.quantization.allocation or {}).get("depths"))
        return self.quantization.quantized_params(self.model)

    def importance_views(self) -> list[Any]:
        """The views the blending weights are summed over (`importance_views` of the training views)."""
        return importance_views(self.dataset.train)

    def _one_view_per_camera(self) -> list[Any]:
        """One view per training camera, their frames spread evenly over the segment."""
        by_camera = views_by_camera(self.dataset.train)
        return [cams[(k * len(cams)) // max(len(by_camera), 1) % len(cams)] for k, cams in enumerate(by_camera)]

    def probe_views(self) -> list[Any]:
        """The compaction controller's fixed probe set (compaction.probe_views training views): cameras and frames
        spread evenly. With at most one per camera, a deterministic pick of one view per camera thinned to the count;
        with more (fewer cameras than probe views, e.g. one camera's video), several frames of each camera, spread
        over the segment, so that the probe sees the whole time range."""
        views = self._one_view_per_camera()
        count = self.compaction_cfg.probe_views if self.compaction_cfg else len(views)
        if count <= len(views):
            return [views[(k * len(views)) // count] for k in range(count)]
        by_camera = views_by_camera(self.dataset.train)
        picked = []
        for j, cams in enumerate(by_camera):
            share = min(len(cams), count // len(by_camera) + (1 if j < count % len(by_camera) else 0))
            phase = (j * len(cams)) // len(by_camera)  # importance_views' pick comes first
            picked += [cams[(phase + (i * len(cams)) // share) % len(cams)] for i in range(share)]
        return picked

    def probe(self, keep: torch.Tensor | None = None) -> ProbeResult:
        """The current model on the probe views, each at its own time: its training loss (as train_step computes it,
        colour correction included) and its mean squared error (of the render clamped to [0, 1] as evaluation
        scores it; geometric mean over the views). A signal of the model, free of which views an iteration drew.
        `keep` (bool per Gaussian): as if only those rows were kept (their render is the pruned model's: the others'
        opacity is scaled to 0, and rows that faint are culled before rasterization)."""
        total, log_mse = 0.0, 0.0
        views = self.probe_views()
        opacity_scale = None if keep is None else keep.to(torch.float32)
        with torch.no_grad():
            for cam in views:
                out = self.model.render(cam, t=float(cam.time), background=self.background, backend=self.cfg.backend,
                                        opacity_scale=opacity_scale)
                rgb = out.rgb if self.colour is None else self.colour.apply(out.rgb, cam.name)
                gt = self.images.get(cam)
                total += float(self.view_loss(rgb, gt, cam)[0])
                # A view rendered exactly (MSE 0) would make the mean -inf: floor it far below any 8-bit image's.
                log_mse += math.log(max(float(mse(rgb.clamp(0.0, 1.0), gt)), 1e-12))
        return ProbeResult(loss=total / len(views), mse=math.exp(log_mse / len(views)))

    def importance(self) -> torch.Tensor:
        """Accumulated blending weight of every Gaussian over the training views of `importance_views` (for the
        compaction criterion 'importance' and pair_order 'weight')."""
        return blending_weights(self.model, self.importance_views(), self.background, self.cfg.backend)

    # ------------------------------------------------------------------------------------------- the run
    def save_model(self, iteration: int) -> Path:
        iteration_dir = self.out_run.iteration_dir(iteration)
        self.model.save(iteration_dir)
        if self.colour is not None:
            write_json(iteration_dir / COLOUR_CORRECTION_NAME, self.colour.to_json())
        return iteration_dir

    def render_view(self, camera: Camera) -> torch.Tensor:
        """The model's render of one view at its own time, for scoring."""
        with torch.no_grad():
            return self.model.render(camera, t=float(camera.time), background=self.background,
                                     backend=self.cfg.backend).rgb

    def run(self) -> dict[str, Any]:
        """Train from the start (or the resumed checkpoint) to the end or train.stop_after; returns the summary. The
        run folder's lock is released when it returns or raises."""
        self.lock.acquire()  # held since the trainer was made, unless it ran before
        try:
            return self._train()
        finally:
            self.lock.release()

    def close(self) -> None:
        """Release the run folder without training (`run()` releases it when it ends)."""
        self.lock.release()

    def _train(self) -> dict[str, Any]:
        cfg, sched = self.cfg, self.schedule
        start = self.start_iteration
        end = sched.iterations
        if cfg.stop_after is not None:
            end = min(end, start + int(cfg.stop_after)) if start < end else end
        if start < end:
            # openmp_wait: each session's, since a resume may run under another setting (the times depend on it)
            self.executions.append({"from_iteration": start, "threads": torch.get_num_threads(),
                                    "backend": select_backend(cfg.backend, torch.device("cpu")),
                                    "openmp_wait": machine.openmp_wait()})
        progress = Progress(sched.iterations, start, cfg.progress)
        tb = TensorBoard(self.out_run.path / "tensorboard", cfg.tensorboard, first_step=start + 1)
        t0 = time.perf_counter()
        elapsed = self.elapsed_before
        last_log_time, last_log_it = t0, start
        try:
            for iteration in range(start + 1, end + 1):
                _seed_globals(_derive_seed(cfg.seed, iteration, 1))
                generator = torch.Generator().manual_seed(_derive_seed(cfg.seed, iteration, 2))
                step = self.train_step(iteration)
                context = StepContext(iteration, step["t"], step["loss"], self.model, generator, step.pop("ems_view"))
                control: dict[str, Any] = {}
                for strategy in self.strategies:
                    control.update(strategy.after_step(context))
                elapsed = self.elapsed_before + (time.perf_counter() - t0)
                progress.update(step["loss"], step["psnr"], self.model.num_gaussians)
                if self.callback is not None:
                    self.callback(iteration, {**step, **control})
                # An evaluation writes its metrics row whether or not the iteration is a logging one.
                evaluate_now = bool(self.evaluator is not None and cfg.eval_every and iteration % cfg.eval_every == 0
                                    and (iteration != sched.iterations or not cfg.eval_at_end))
                # Rows removed for being non-finite are logged whenever it happens (densify.py warns as well).
                if evaluate_now or (cfg.log_every and (any(key in control for key in ALWAYS_LOGGED)
                                                       or control.get("pruned_nonfinite", 0) > 0
                                                       or iteration % cfg.log_every == 0 or iteration == end)):
                    now = time.perf_counter()
                    row = {
                        "iteration": iteration,
                        "loss": step["loss"],
                        "psnr": step["psnr"],
                        "num_gaussians": self.model.num_gaussians,
                        "lr_xyz": step["lr_xyz"],
                        **({"quantized": True} if step.get("quantized") else {}),
                        **({"rate_bits": step["rate_bits"]} if "rate_bits" in step else {}),
                        "elapsed_s": round(elapsed, 3),
                        "it_per_s": (iteration - last_log_it) / max(now - last_log_time, 1e-9),
                        **control,
                    }
                    last_log_time, last_log_it = now, iteration
                    if evaluate_now:
                        assert self.evaluator is not None
                        e0 = time.perf_counter()
                        ev = self.evaluator.score(self.render_view, self.dataset)
                        row["test_psnr"], row["test_ssim"] = ev.psnr, ev.ssim
                        # Training time excludes evaluation: shift the clock by the evaluation's duration.
                        spent = time.perf_counter() - e0
                        t0 += spent
                        last_log_time += spent
                    self.metrics_log.append(row)
                    tb.scalars(iteration, {k: v for k, v in row.items() if k != "iteration"})
                if iteration in sched.save_iterations:
                    self.save_model(iteration)
                if iteration == end or (cfg.checkpoint_every and iteration % cfg.checkpoint_every == 0):
                    save_checkpoint(self.out_run.path, self.checkpoint_payload(iteration, elapsed))
        finally:
            progress.close()
            tb.close()
        finished = end >= sched.iterations
        done = max(end, start)
        summary: dict[str, Any] = {
            "iterations": done,
            "target_iterations": sched.iterations,
            "wall_seconds": round(elapsed, 3),
            "it_per_s": done / elapsed if elapsed > 0 else None,
            "num_gaussians": self.model.num_gaussians,
            "pruned_nonfinite": self.density.pruned_nonfinite,  # over the whole run (the checkpoint carries it)
            "variant": self.model.variant,
            "finished": finished,
            "started_from_iteration": start,  # > 0: this session resumed from a checkpoint
            "threads": torch.get_num_threads(),
            "executions": self.executions,  # every session's threads and backend, from the iteration it started at
            "machine": machine.describe(),  # the times above mean little without it
        }
        if self.colour is not None:
            summary["colour_correction"] = self.colour.summary()
        if self.quantization is not None and self.quantization.allocation is not None:
            summary["quantization_aware_allocation"] = self.quantization.allocation
        if finished:
            # The summary goes first: the evaluation record reads the training time from it.
            self.out_run.write_summary(summary)
        if finished and cfg.eval_at_end and self.evaluator is not None:
            e0 = time.perf_counter()
            result = self.evaluator.score_and_record(self.render_view, self.dataset, self.out_run, self.model)
            summary["test_psnr"], summary["test_ssim"] = result.psnr, result.ssim
            summary["eval_seconds"] = round(time.perf_counter() - e0, 3)
            self.out_run.write_summary(summary)
        return summary


# Compaction options that act only in the pruned run (the reference prunes nothing and only probes).
_PRUNED_RUN_ONLY = frozenset(f"compaction.{f.name}" for f in dataclasses.fields(CompactionConfig)
                             if f.name not in REFERENCE_RUN_OPTIONS)


def _flat(section: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """{"densify.interval": 100, ...}: a config section's nested options by dotted name."""
    out: dict[str, Any] = {}
    for key, value in section.items():
        if isinstance(value, dict):
            out.update(_flat(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def run_config(dataset: Dataset, configs: dict[str, Any], schedule: Schedule | None = None,
               data_path: str | Path | None = None) -> dict[str, Any]:
    """A run's config.json: the data section (the dataset's format and downscale where the data options leave them
    unset, then the data options as given, the frame window and the near plane as resolved, and the data's absolute
    path: `data_path` as the user gave it, else the dataset's folder), each other config section as given, and the
    training schedule in real iterations when there is one (a whole video's shared config has none: each segment
    resolves its own), and the behaviour changes this code has (stgc.train.behaviour)."""
    data = {"format": dataset.format, "downscale": dataset.downscale}
    data.update(_config_dict(configs["data"]) or {})
    # The frame window as resolved, never an unset option: reopened with the options alone, a reader's own default
    # (STG's colmap_<t> folder names its start) or frames added to the folder later would move it silently.
    for key, resolved in (("start", dataset.start), ("duration", dataset.duration)):
        if data.get(key) is None:
            data[key] = resolved
    data["near_plane"] = dataset.near_plane  # resolved: what every later verb must render with
    data["path"] = str(Path(dataset.root if data_path is None else data_path).resolve())
    train = _config_dict(configs["train"])
    if schedule is not None:
        train["resolved_schedule"] = schedule.to_dict()
    return {"data": _jsonable(data), "model": _config_dict(configs["model"]), "train": train,
            "compaction": _config_dict(configs["compaction"]), BEHAVIOUR_KEY: recorded_behaviour(),
            DATA_FINGERPRINT: dataset.fingerprint}


# config.json's record of the data a run trains on (`Dataset.fingerprint`; runs started before 2026-11-28 have none).
DATA_FINGERPRINT = "data_fingerprint"


def check_same_data(saved: Mapping[str, Any] | None, dataset: Dataset, run_path: Path) -> None:
    """Refuse (DataError naming the data folder) to continue the run at `run_path`, whose config.json is `saved`, on
    `dataset` when the data it recorded (`DATA_FINGERPRINT`) is other data: once its saved folder is gone any DATA
    is taken for it, and another capture (or the same one with other images) would be trained into the same model.
    A run that recorded none (started before the record existed) is taken as it is."""
    recorded = (saved or {}).get(DATA_FINGERPRINT)
    if recorded is None or recorded == dataset.fingerprint:
        return
    saved_data = (saved or {}).get("data")
    saved_path = saved_data.get("path") if isinstance(saved_data, dict) else None
    if saved_path and same_place(str(dataset.root), str(saved_path)):
        raise DataError(dataset.root, f"changed since {run_path} started training on it: its views, or the bytes of "
                                      f"its image or mask files, differ from those recorded in "
                                      f"{run_path / Run.CONFIG} (a re-rendered or re-encoded frame counts); put the "
                                      "data back as it was, or train it into a new --out")
    raise DataError(dataset.root, f"is not the data {run_path} trained on: its views, or the bytes of its image or "
                                  f"mask files, differ from those recorded in {run_path / Run.CONFIG}; continue the "
                                  "run on its own data, or train this data into a new --out")


def resolved_options(dataset: Dataset, data_cfg: DataConfig | None, model_cfg: ModelConfig | None,
                     train_cfg: TrainConfig) -> tuple[TrainConfig, ModelConfig]:
    """(train, model) options with those left unset resolved for `dataset` as the trainer trains and records them:
    the densification schedule for the initial cloud's kind (DensifyConfig.SPARSE_CLOUD), the model and learning
    rates for the data's official config family (stgc.official)."""
    sparse_cloud = not (data_cfg or DataConfig()).points_ship_with(dataset)
    return (train_cfg.resolved(sparse_cloud, dataset.official_config),
            (model_cfg or ModelConfig()).resolved(dataset.official_config))


def run_options(config: dict[str, Any]) -> dict[str, Any]:
    """The options of a run config (`run_config`'s) that decide what the run trains, by dotted name: each section
    read back as a resume reads config.json (`stgc.options.configs_from_run`), so that a start and its resume agree
    however their configs were given (a section left to the trainer's defaults, a tuple read back as a list). Left
    out: how the run executes (EXECUTION_OPTIONS: a resume may change them), where the data lies (data.path: it may
    move) and the behaviour record (an upgrade of stgc changes it)."""
    config = json.loads(json.dumps(config))
    data = {k: v for k, v in (config.get("data") or {}).items() if k != "path"}
    train = {k: v for k, v in (config.get("train") or {}).items() if k != "resolved_schedule"}
    schedule = (config.get("train") or {}).get("resolved_schedule")
    if isinstance(schedule, dict) and "iterations" in schedule:
        train["iterations"] = schedule["iterations"]  # as configs_from_run reads it (real iterations)
    compaction = config.get("compaction")
    sections = {
        "data": from_saved(DataConfig, data, "data"),
        "model": from_saved(ModelConfig, config.get("model") or {}, "model"),
        "train": from_saved(TrainConfig, train, "train"),
        # A run without compaction saves null, and is read back as one whose compaction prunes nothing.
        "compaction": (CompactionConfig(method="none") if compaction is None
                       else from_saved(CompactionConfig, compaction, "compaction")),
    }
    options = {f"{name}.{key}": value for name, section in sections.items()
               for key, value in _flat(json.loads(json.dumps(dataclasses.asdict(section)))).items()}
    return {name: value for name, value in options.items() if name not in EXECUTION_OPTIONS}


def _saved_before_options() -> dict[str, Any]:
    """Every section's SAVED_BEFORE (how a config saved before an option existed trained), as `run_options` names
    the options."""
    # The sections as `run_options` reads them (stgc.options.section_classes is a layer above training).
    return {f"{section}.{dotted}": value
            for section, cls in (("data", DataConfig), ("model", ModelConfig), ("train", TrainConfig),
                                 ("compaction", CompactionConfig))
            for dotted, value in json.loads(json.dumps(getattr(cls, "SAVED_BEFORE", {}))).items()}


def options_fingerprint(options: dict[str, Any]) -> str:
    """The sha256 of `run_options`' options, in canonical JSON."""
    return hashlib.sha256(json.dumps(options, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def _chosen(mode: str, auto: bool) -> bool:
    """An on/off/auto option of the real-capture rules: `auto` is what the data calls for."""
    return mode == "on" or (mode == "auto" and auto)


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, torch.Tensor):
        return obj.item() if obj.numel() == 1 else obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return obj


def train(
    dataset: Dataset,
    data_cfg: DataConfig | None,
    model_cfg: ModelConfig | None,
    train_cfg: TrainConfig,
    compaction_cfg: CompactionConfig | None,
    out_dir: str | Path,
    resume: bool = False,
    *,
    overwrite: bool = False,
    model: STGModel | None = None,
    callback: IterationCallback | None = None,
    evaluator: TestEvaluator | None = None,
) -> dict[str, Any]:
    """Train an STG model on `dataset` into the run directory `out_dir`; returns the summary.

    resume: continue from out_dir/checkpoint.pt when it exists (else start afresh). A fresh start refuses a
    directory that already holds a run unless overwrite (or resume) is given (`stgc.run`). model: start from this model
    instead of building one from the data config's initial points. callback(iteration, numbers) runs after every
    iteration. evaluator scores the test views (`train.eval_every`, `train.eval_at_end`; `stgc.eval.RunEvaluator`).
    Writes config.json, metrics.jsonl, compaction.jsonl, checkpoint.pt, point_cloud/iteration_<N>/,
    train_summary.json and, with an evaluator, eval.json and eval_per_view.csv (see docs/training.md)."""
    trainer = Trainer(dataset, data_cfg, model_cfg, train_cfg, compaction_cfg, out_dir,
                      model=model, resume=resume, overwrite=overwrite, callback=callback, evaluator=evaluator)
    return trainer.run()
