"""Spacetime Gaussians (Li et al., CVPR'24): parameters, evaluation at time t, rendering, topology edits, checkpoints.

All parameters are stored pre-activation exactly as the official code stores them (see `layout.py` and
docs/model.md). With Δ = t − μ_t and Δ' = Δ.detach() (as the official renderer):
    temporal opacity  α(t) = sigmoid(o) · exp(−(Δ / exp(s_t))²)        μ_t, s_t get gradient only through this
    position          x(t) = x + m[0:3]·Δ' + m[3:6]·Δ'² + m[6:9]·Δ'³
    rotation          q(t) = normalize(q + ω·Δ')
    features          full: [f_dc (6), Δ'·f_t (3)]   lite: f_dc (3) = RGB
    scale             exp(s), time independent
"""

from __future__ import annotations

import contextlib
import logging
import math
from collections import OrderedDict
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import nn
from torch.autograd.function import once_differentiable

from stgc import render as _render
from stgc.data.cameras import DEFAULT_NEAR_PLANE, Camera
from stgc.errors import DataError, FormatError
from stgc.fileio import read_json_object
from stgc.model import _numba_at_time as _at_time
from stgc.model import ply as _ply
from stgc.model.config import DecoderActivation, ModelConfig
from stgc.model.decoder import SandwichDecoder, camera_rays
from stgc.model.layout import NORMAL_FIELDS, VARIANTS, Variant, ply_fields
from stgc.model.optim import replace_group_param
from stgc.run import OFFICIAL_ARGS, Run, official_run_args

log = logging.getLogger(__name__)

PARAM_KEYS = (
    "xyz",
    "scaling",
    "rotation",
    "omega",
    "opacity",
    "trbf_center",
    "trbf_scale",
    "motion",
    "features_dc",
    "features_t",
)

# A Gaussian's composited alpha is min(alpha_max, opacity·exp(−σ)) with σ >= 0, and the rasterizer skips
# alpha < 1/255; so one whose temporal opacity is below this threshold cannot touch any pixel at that time.
MIN_VISIBLE_OPACITY = _render.ALPHA_MIN

# The official STG rasterizers (forward_full, forward_lite, gaussian_rasterization_ch3/ch9: cuda_rasterizer/
# auxiliary.h, in_frustum) drop every Gaussian whose view-space depth is <= 0.2 scene units, in training and at
# test time. It matters on captures whose cameras sit inside the scene (a dome): Gaussians that reconstruct the
# wall next to a held-out camera would otherwise fill its whole view with haze (panoptic_basketball, trained
# model: 21.62 dB with gsplat's 0.01 near plane, 22.76 dB with 0.2). Every camera carries its near plane
# (`Camera.near`: this value unless the format or data.near_plane says otherwise); render(..., near_plane=x)
# overrides it for one call.
NEAR_PLANE = DEFAULT_NEAR_PLANE

# Official clamp of the initial log scale (oursfull/ourslite create_from_pcd) and floor of the squared distance.
INIT_LOG_SCALE_RANGE = (-10.0, 1.0)
INIT_MIN_SQUARED_DISTANCE = 1e-7

_CAMERA_CACHE_SIZE = 128


def param_widths(variant: str) -> dict[str, int]:
    """Columns per Gaussian of every parameter of `variant` (full sums to 35, lite to 29)."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown STG variant {variant!r}; expected one of {VARIANTS}")
    widths = {
        "xyz": 3,
        "scaling": 3,
        "rotation": 4,
        "omega": 4,
        "opacity": 1,
        "trbf_center": 1,
        "trbf_scale": 1,
        "motion": 9,
        "features_dc": 6 if variant == "full" else 3,
        "features_t": 3,
    }
    if variant == "lite":
        del widths["features_t"]
    return widths


def ply_columns(variant: str) -> dict[str, list[str]]:
    """Official PLY field names of each parameter's columns."""
    widths = param_widths(variant)
    columns = {
        "xyz": ["x", "y", "z"],
        "trbf_center": ["trbf_center"],
        "trbf_scale": ["trbf_scale"],
        "motion": [f"motion_{i}" for i in range(9)],
        "features_dc": [f"f_dc_{i}" for i in range(widths["features_dc"])],
        "opacity": ["opacity"],
        "scaling": [f"scale_{i}" for i in range(3)],
        "rotation": [f"rot_{i}" for i in range(4)],
        "omega": [f"omega_{i}" for i in range(4)],
    }
    if variant == "full":
        columns["features_t"] = [f"f_t_{i}" for i in range(3)]
    return columns


def initial_log_scales(xyz: np.ndarray, neighbours: int = 3, among: np.ndarray | None = None) -> np.ndarray:
    """log(sqrt(mean squared distance to the `neighbours` nearest other points)), clamped as the official init.
    The other points are `among` (which holds the rows of `xyz`), by default `xyz` itself.

    The official code uses simple-knn's distCUDA2 (an approximate 3-NN); this is the exact KNN from a k-d tree.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    pool = xyz if among is None else np.asarray(among, dtype=np.float64)
    count = pool.shape[0]
    if count < 2:
        return np.full(xyz.shape[0], INIT_LOG_SCALE_RANGE[1], dtype=np.float32)
    k = min(neighbours, count - 1)
    distances, _ = cKDTree(pool).query(xyz, k=k + 1)  # column 0 is the point itself (distance 0)
    mean_sq = np.mean(np.square(distances[:, 1:]), axis=1)
    log_scale = np.log(np.sqrt(np.maximum(mean_sq, INIT_MIN_SQUARED_DISTANCE)))
    return cast(np.ndarray, np.clip(log_scale, *INIT_LOG_SCALE_RANGE).astype(np.float32))


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


@dataclass
class ModelRender:
    """One rendered view.

    rgb:    [H, W, 3] colour, not clamped (full: decoder output; lite: splatted f_dc).
    alpha:  [H, W] accumulated opacity.
    depth:  [H, W] or None (when requested; what the rasterizer returns).
    raster: the rasterizer's RenderOutput for the Gaussians in `index` (its per-Gaussian outputs — radii,
            visible, means2d, weights — are rows of `index`, not of the model).
    index:  LongTensor [M] of model rows that were rasterized (temporal opacity >= 1/255 at t).
    features: [H, W, C] the raw splatted feature image (equal to rgb for lite).
    """

    rgb: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor | None
    raster: Any
    index: torch.Tensor
    features: torch.Tensor


class STGModel:
    """A set of Spacetime Gaussians plus (full variant) the colour decoder.

    params: {key: nn.Parameter [N, width]} pre-activation, keys in PARAM_KEYS (lite has no features_t).
    After `make_optimizer`, `prune`, `extend`, `reset_opacity` and `replace_param` keep the attached Adam state
    aligned with the rows.
    """

    def __init__(
        self,
        params: Mapping[str, torch.Tensor],
        variant: str,
        scene_extent: float = 1.0,
        decoder: SandwichDecoder | None = None,
    ):
        widths = param_widths(variant)
        if set(params) != set(widths):
            raise ValueError(f"{variant} model needs params {sorted(widths)}, got {sorted(params)}")
        count = params["xyz"].shape[0]
        for key, width in widths.items():
            if tuple(params[key].shape) != (count, width):
                raise ValueError(f"param {key!r} has shape {tuple(params[key].shape)}, expected ({count}, {width})")
        if (variant == "full") != (decoder is not None):
            raise ValueError("the full variant needs a decoder and the lite variant has none")
        self.variant = variant
        self.scene_extent = float(scene_extent)
        device = params["xyz"].device
        self.params: dict[str, nn.Parameter] = {
            key: nn.Parameter(params[key].detach().to(device=device, dtype=torch.float32).contiguous().clone())
            for key in widths
        }
        self.decoder = decoder.to(device) if decoder is not None else None
        self.optimizer: torch.optim.Adam | None = None
        self._camera_cache: OrderedDict[tuple[bytes, bytes, int, int, str], dict[str, torch.Tensor]] = OrderedDict()

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_points(
        cls,
        cloud: Any,
        variant: Variant = "full",
        scene_extent: float = 1.0,
        trbf_scale_init: float = 0.0,
        *,
        decoder_activation: DecoderActivation = "sigmoid",
        opacity_init: float = 0.1,
        init_neighbours: int = 3,
        decoder_seed: int = 0,
        device: str | torch.device | None = None,
    ) -> STGModel:
        """Official initialisation from a point cloud with .xyz [N,3], .rgb [N,3] in [0,1] and .time [N]."""
        config = ModelConfig(
            variant=variant,
            decoder_activation=decoder_activation,
            trbf_scale_init=trbf_scale_init,
            opacity_init=opacity_init,
            init_neighbours=init_neighbours,
            decoder_seed=decoder_seed,
        )
        return cls.from_config(cloud, config, scene_extent=scene_extent, device=device)

    @classmethod
    def from_config(
        cls,
        cloud: Any,
        config: ModelConfig,
        scene_extent: float = 1.0,
        device: str | torch.device | None = None,
    ) -> STGModel:
        if not config.is_resolved:
            raise ValueError("the model config has options left to the data (model.decoder_activation, "
                             "model.trbf_scale_init): resolve them with ModelConfig.resolved(family) first")
        xyz, rgb, time = _cloud_arrays(cloud)
        count = xyz.shape[0]
        log_scale = initial_log_scales(xyz, config.init_neighbours)
        rotation = np.zeros((count, 4), dtype=np.float32)
        rotation[:, 0] = 1.0
        params = {
            "xyz": xyz,
            "scaling": np.repeat(log_scale[:, None], 3, axis=1),
            "rotation": rotation,
            "omega": np.zeros((count, 4), np.float32),
            "opacity": np.full((count, 1), _logit(config.opacity_init), np.float32),
            "trbf_center": time[:, None],
            "trbf_scale": np.full((count, 1), config.trbf_scale_init, np.float32),
            "motion": np.zeros((count, 9), np.float32),
            "features_dc": np.concatenate([rgb, rgb], axis=1) if config.variant == "full" else rgb,
        }
        if config.variant == "full":
            params["features_t"] = np.zeros((count, 3), np.float32)
        tensors = {key: torch.as_tensor(np.ascontiguousarray(value), dtype=torch.float32) for key, value in params.items()}
        if device is not None:
            tensors = {key: value.to(device) for key, value in tensors.items()}
        decoder = None
        if config.variant == "full":
            generator = torch.Generator().manual_seed(config.decoder_seed)
            decoder = SandwichDecoder(str(config.decoder_activation), generator=generator)
        return cls(tensors, config.variant, scene_extent=scene_extent, decoder=decoder)

    # ------------------------------------------------------------------ basic properties
    @property
    def num_gaussians(self) -> int:
        return int(self.params["xyz"].shape[0])

    @property
    def device(self) -> torch.device:
        return self.params["xyz"].device

    @property
    def decoder_activation(self) -> str | None:
        return None if self.decoder is None else self.decoder.activation

    @property
    def scales(self) -> torch.Tensor:
        return torch.exp(self.params["scaling"])

    @property
    def opacity(self) -> torch.Tensor:
        """Base opacity sigmoid(o), [N] (before the temporal factor)."""
        return torch.sigmoid(self.params["opacity"][:, 0])

    def __repr__(self) -> str:
        return f"STGModel(variant={self.variant!r}, num_gaussians={self.num_gaussians}, device={self.device})"

    # ------------------------------------------------------------------ evaluation at time t
    def temporal_opacity(self, t: float) -> torch.Tensor:
        """sigmoid(o) · exp(−((t − μ_t) / exp(s_t))²), [N]; differentiable in o, μ_t and s_t."""
        return _temporal_opacity(self.params, t)

    def peak_temporal_opacity(self, start: float = 0.0, end: float = 1.0) -> torch.Tensor:
        """The largest temporal opacity each Gaussian reaches for t in [start, end] (at t = μ_t clamped), [N].
        Below MIN_VISIBLE_OPACITY a Gaussian is culled from every render in that interval."""
        nearest = self.params["trbf_center"].detach().clamp(start, end)
        return _temporal_opacity({k: v.detach() for k, v in self.params.items()}, nearest)

    def means_at(self, t: float) -> torch.Tensor:
        return _means_at(self.params, _detached_delta(self.params, t))

    def rotations_at(self, t: float) -> torch.Tensor:
        return torch.nn.functional.normalize(_quaternions_at(self.params, _detached_delta(self.params, t)), dim=1)

    def features_at(self, t: float) -> torch.Tensor:
        return _features_at(self.params, _detached_delta(self.params, t))

    # ------------------------------------------------------------------ rendering
    @contextlib.contextmanager
    def params_replaced(self, params: Mapping[str, torch.Tensor] | None) -> Iterator[None]:
        """Within the block, render with `params` (the same keys and shapes; typically a differentiable function of
        the model's own, such as the codec's quantization of them) instead of the model's parameters. None: no
        change."""
        if params is None:
            yield
            return
        if set(params) != set(self.params) or any(params[k].shape != self.params[k].shape for k in params):
            raise ValueError("replacement params must have the model's keys and shapes")
        own = self.params
        self.params = cast(dict[str, nn.Parameter], dict(params))  # tensors standing in for the parameters
        try:
            yield
        finally:
            self.params = own

    def render(
        self,
        camera: Camera,
        t: float | None = None,
        background: torch.Tensor | Sequence[float] | None = None,
        backend: str = "auto",
        return_depth: bool = False,
        return_weights: bool = False,
        opacity_scale: torch.Tensor | None = None,
        **raster_options: Any,
    ) -> ModelRender:
        """Render `camera` at time t (default camera.time).

        background is in the splatted feature space: 3 values for lite; for full either 9 values or 3 (taken as the
        albedo channels, the rest zero). opacity_scale [N] multiplies every Gaussian's temporal opacity (a learned
        keep/drop mask: rows scaled to 0 are culled). Extra keyword arguments go to `stgc.render.rasterize`.
        """
        t = float(camera.time if t is None else t)
        return self.render_views([camera], t, background, backend, return_depth, return_weights, opacity_scale,
                                 **raster_options)[0]  # fmt: skip

    def render_views(
        self,
        cameras: Sequence[Camera],
        t: float,
        background: torch.Tensor | Sequence[float] | None = None,
        backend: str = "auto",
        return_depth: bool = False,
        return_weights: bool = False,
        opacity_scale: torch.Tensor | None = None,
        **raster_options: Any,
    ) -> list[ModelRender]:
        """Render several cameras at one time t (a training batch: its views share the timestamp), as `render` would
        one by one, with the Gaussians at t computed once for all of them: one pass of the per-Gaussian formulas
        forward and, when a loss over every view is backpropagated at once, one backward through them instead of one
        per view."""
        if opacity_scale is not None and tuple(opacity_scale.shape) != (self.num_gaussians,):
            raise ValueError(f"opacity_scale must have shape ({self.num_gaussians},), got {tuple(opacity_scale.shape)}")
        rows = rows_at(self.params, float(t), opacity_scale)
        bg = self._background(background)
        renders = []
        for camera in cameras:
            cached = self._camera_tensors(camera)
            raster = _render.rasterize(
                rows.means,
                rows.quats,
                rows.scales,
                rows.opacity,
                rows.features,
                cached["K"],
                cached["viewmat"],
                int(camera.width),
                int(camera.height),
                bg,
                backend=backend,
                return_depth=return_depth,
                return_weights=return_weights,
                **{"near_plane": float(camera.near), **raster_options},
            )
            features = raster.image
            rgb = features if self.decoder is None else self.decoder(features, self._rays(camera, cached))
            renders.append(ModelRender(rgb=rgb, alpha=raster.alpha, depth=raster.depth if return_depth else None,
                                       raster=raster, index=rows.index, features=features))  # fmt: skip
        return renders

    def _background(self, background: torch.Tensor | Sequence[float] | None) -> torch.Tensor | None:
        if background is None:
            return None
        bg = torch.as_tensor(background, dtype=torch.float32, device=self.device).reshape(-1)
        channels = self.params["features_dc"].shape[1] + (3 if self.variant == "full" else 0)
        if bg.numel() == 3 and channels == 9:
            bg = torch.cat([bg, bg.new_zeros(6)])
        if bg.numel() != channels:
            raise ValueError(f"background has {bg.numel()} values; the {self.variant} model splats {channels} channels")
        return bg

    def _camera_tensors(self, camera: Camera) -> dict[str, torch.Tensor]:
        K = np.asarray(camera.K, dtype=np.float64)
        w2c = np.asarray(camera.w2c, dtype=np.float64)
        key = (K.tobytes(), w2c.tobytes(), int(camera.width), int(camera.height), str(self.device))
        cached = self._camera_cache.get(key)
        if cached is None:
            cached = {
                "K": torch.as_tensor(K, dtype=torch.float32, device=self.device),
                "viewmat": torch.as_tensor(w2c, dtype=torch.float32, device=self.device),
            }
            self._camera_cache[key] = cached
            while len(self._camera_cache) > _CAMERA_CACHE_SIZE:
                self._camera_cache.popitem(last=False)
        else:
            self._camera_cache.move_to_end(key)
        return cached

    def _rays(self, camera: Camera, cached: dict[str, torch.Tensor]) -> torch.Tensor:
        if "rays" not in cached:
            rays = camera_rays(camera.K, camera.w2c, int(camera.width), int(camera.height))
            cached["rays"] = rays.to(self.device)
        return cached["rays"]

    # ------------------------------------------------------------------ optimizer and topology
    def make_optimizer(self, lrs: dict[str, float], decoder_lr: float = 1e-4) -> torch.optim.Adam:
        """Adam (eps 1e-15) with one group per param named by its key, plus a 'decoder' group (full)."""
        missing = [key for key in self.params if key not in lrs]
        unknown = [key for key in lrs if key not in self.params and key != "decoder"]
        if missing or unknown:
            raise ValueError(f"learning rates: missing {missing}, unknown {unknown}; keys are {list(self.params)}")
        groups = [{"params": [param], "lr": float(lrs[key]), "name": key} for key, param in self.params.items()]
        if self.decoder is not None:
            lr = float(lrs.get("decoder", decoder_lr))
            groups.append({"params": list(self.decoder.parameters()), "lr": lr, "name": "decoder"})
        # Fused: one kernel per parameter instead of about eight elementwise ops, each a parallel region whose
        # threads must be woken (6-12 % of a blender_toys iteration at 2 threads, benchmarks/RESULTS.md session 45).
        # A resumed run keeps the optimizer it started with: load_state_dict restores the checkpoint's `fused`.
        fused = self.device.type in ("cpu", "cuda")
        self.optimizer = torch.optim.Adam(groups, lr=0.0, eps=1e-15, fused=fused)
        return self.optimizer

    def prune(self, keep: torch.Tensor) -> None:
        """Keep only the rows where `keep` is True; their Adam moments move with them."""
        keep = torch.as_tensor(keep, device=self.device)
        if keep.dtype != torch.bool or tuple(keep.shape) != (self.num_gaussians,):
            raise ValueError(f"keep must be a bool tensor of shape ({self.num_gaussians},), got {keep.dtype} {tuple(keep.shape)}")
        for key in list(self.params):
            self._swap(key, self.params[key].detach()[keep], lambda state: state[keep])

    def extend(self, new: dict[str, torch.Tensor]) -> None:
        """Append Gaussians (all params, pre-activation); their Adam moments start at zero."""
        widths = param_widths(self.variant)
        if set(new) != set(widths):
            raise ValueError(f"extend needs exactly the params {sorted(widths)}, got {sorted(new)}")
        count = int(torch.as_tensor(new["xyz"]).shape[0])
        rows = {}
        for key, width in widths.items():
            value = torch.as_tensor(new[key], dtype=torch.float32, device=self.device).detach()
            if tuple(value.shape) != (count, width):
                raise ValueError(f"extend: {key!r} has shape {tuple(value.shape)}, expected ({count}, {width})")
            rows[key] = value
        def with_zero_rows(state: torch.Tensor) -> torch.Tensor:
            return torch.cat([state, state.new_zeros((count,) + state.shape[1:])])

        for key, value in rows.items():
            self._swap(key, torch.cat([self.params[key].detach(), value]), with_zero_rows)

    def gather(self, selection: torch.Tensor) -> dict[str, torch.Tensor]:
        """Detached copies of the selected rows (bool mask or indices), e.g. to clone Gaussians via extend()."""
        return {key: value.detach()[selection].clone() for key, value in self.params.items()}

    def replace_param(self, key: str, value: torch.Tensor, reset_moments: bool = True) -> None:
        """Overwrite one parameter (same shape); its Adam moments are zeroed unless reset_moments is False."""
        if key not in self.params:
            raise KeyError(f"no param {key!r}; keys are {list(self.params)}")
        value = torch.as_tensor(value, dtype=torch.float32, device=self.device).detach()
        if value.shape != self.params[key].shape:
            raise ValueError(f"{key!r} must keep shape {tuple(self.params[key].shape)}, got {tuple(value.shape)}")
        self._swap(key, value, None if reset_moments else (lambda state: state))

    def reset_opacity(self, max_value: float = 0.01) -> None:
        """3DGS opacity reset: sigmoid(o) <- min(sigmoid(o), max_value), with the opacity moments zeroed."""
        with torch.no_grad():
            # min(o, logit(max_value)) as sigmoid is monotonic: the round trip through sigmoid underflows to 0 for
            # o below about -88.7, whose log is -inf (a model that no longer saves). The cap is computed in the
            # parameter's dtype on its device, as the round trip computed it, so capped rows keep their values.
            opacity = self.params["opacity"]
            cap = torch.tensor(max_value, dtype=opacity.dtype, device=opacity.device)
            self.replace_param("opacity", torch.clamp(opacity, max=torch.log(cap / (1.0 - cap))), reset_moments=True)

    def _swap(self, key: str, value: torch.Tensor,
              edit_rows: Callable[[torch.Tensor], torch.Tensor] | None) -> None:
        old = self.params[key]
        new = nn.Parameter(value.contiguous().clone() if value.data_ptr() == old.data_ptr() else value.contiguous())
        if self.optimizer is not None:
            replace_group_param(self.optimizer, old, new, edit_rows)
        self.params[key] = new

    def to(self, device: str | torch.device) -> STGModel:
        """Move to `device` in place (before make_optimizer)."""
        if self.optimizer is not None:
            raise RuntimeError("move the model before make_optimizer(); the optimizer holds the old tensors")
        self.params = {key: nn.Parameter(value.detach().to(device)) for key, value in self.params.items()}
        if self.decoder is not None:
            self.decoder.to(device)
        self._camera_cache.clear()
        return self

    # ------------------------------------------------------------------ serialisation
    def to_ply_arrays(self) -> dict[str, np.ndarray]:
        """{official field name: float32 [N]} in layout order; the normals are zeros."""
        columns = ply_columns(self.variant)
        arrays: dict[str, np.ndarray] = {}
        for key, names in columns.items():
            values = self.params[key].detach().cpu().numpy().astype(np.float32, copy=False)
            for i, name in enumerate(names):
                arrays[name] = np.ascontiguousarray(values[:, i])
        for name in NORMAL_FIELDS:
            arrays[name] = np.zeros(self.num_gaussians, dtype=np.float32)
        return {name: arrays[name] for name in ply_fields(self.variant)}

    @classmethod
    def from_ply_arrays(
        cls,
        arrays: dict[str, np.ndarray],
        variant: str,
        decoder_state: dict[str, Any] | None,
        scene_extent: float = 1.0,
        decoder_activation: str = "sigmoid",
        device: str | torch.device | None = None,
    ) -> STGModel:
        """Inverse of to_ply_arrays (+ decoder_state for full). Raises FormatError on missing/NaN/non-float32."""
        _ply.validate_arrays(arrays, variant)
        params = {}
        for key, names in ply_columns(variant).items():
            stacked = np.stack([np.asarray(arrays[name]) for name in names], axis=1)
            params[key] = torch.from_numpy(np.ascontiguousarray(stacked))
        if device is not None:
            params = {key: value.to(device) for key, value in params.items()}
        decoder = None
        if variant == "full":
            if decoder_state is None:
                raise FormatError(None, "a full-variant model needs decoder_state (mlp1.weight, mlp2.weight)")
            weights = _ply.validate_decoder_state(decoder_state)
            decoder = SandwichDecoder(decoder_activation)
            decoder.load_state_dict({key: torch.from_numpy(value) for key, value in weights.items()})
        return cls(params, variant, scene_extent=scene_extent, decoder=decoder)

    def decoder_state(self) -> dict[str, np.ndarray] | None:
        """The decoder weights under the official names and shapes, or None for lite."""
        if self.decoder is None:
            return None
        return {key: value.detach().cpu().numpy().copy() for key, value in self.decoder.state_dict().items()}

    def save(self, iteration_dir: str | Path) -> Path:
        """Write iteration_dir/point_cloud.ply (+ point_cloud.pt for full); return the PLY path.

        Each file is replaced atomically. Everything is checked before anything is written, so a model the files
        cannot hold (NaN or inf) leaves the folder's earlier pair as it was; only a write error between the two
        files (disk full) leaves the new decoder beside the old PLY."""
        iteration_dir = Path(iteration_dir)
        ply_path = iteration_dir / _ply.PLY_NAME
        decoder_path = iteration_dir / _ply.DECODER_NAME
        arrays = self.to_ply_arrays()
        decoder_state = None if self.decoder is None else self.decoder.state_dict()
        _ply.validate_arrays(arrays, self.variant, ply_path)
        if decoder_state is not None:
            _ply.validate_decoder_state(decoder_state, decoder_path)
            # Decoder first: readers find a checkpoint through its PLY, which then never pairs with a stale decoder.
            _ply.write_decoder(decoder_path, decoder_state)
        _ply.write_ply(ply_path, arrays, self.variant)
        return ply_path

    @classmethod
    def load(
        cls,
        path: str | Path,
        scene_extent: float = 1.0,
        decoder_activation: str | None = None,
        device: str | torch.device | None = None,
    ) -> STGModel:
        """Load a run dir (its highest iteration), an iteration dir or a .ply file; full/lite from the fields.

        The decoder activation is not stored in the official files: it comes from the argument, else from the run the
        PLY sits in (`_activation_from_run_config`: the nearest config.json, restored_from.json or official
        cfg_args), else 'sigmoid', with a warning.
        """
        ply_path = _ply.resolve_ply_path(path)
        arrays, variant = _ply.read_ply(ply_path)
        decoder_state = None
        if variant == "full":
            decoder_state = _ply.read_decoder(ply_path.with_suffix(".pt"))
            if decoder_activation is None:
                decoder_activation = _activation_from_run_config(ply_path)
            if decoder_activation is None:
                log.warning("%s: no run config or official cfg_args beside it says how its decoder ends: sigmoid "
                            "assumed (official N3DV; Technicolor's is a clamp, the immersive configs' none)", ply_path)
        return cls.from_ply_arrays(
            arrays,
            variant,
            decoder_state,
            scene_extent=scene_extent,
            decoder_activation=decoder_activation or "sigmoid",
            device=device,
        )

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to rebuild the model exactly (for training checkpoints)."""
        return {
            "variant": self.variant,
            "scene_extent": self.scene_extent,
            "params": {key: value.detach().cpu().clone() for key, value in self.params.items()},
            "decoder": None if self.decoder is None else {k: v.detach().cpu().clone() for k, v in self.decoder.state_dict().items()},
            "decoder_activation": self.decoder_activation,
        }

    @classmethod
    def from_state_dict(cls, state: dict[str, Any], device: str | torch.device | None = None) -> STGModel:
        params = {key: torch.as_tensor(value) for key, value in state["params"].items()}
        if device is not None:
            params = {key: value.to(device) for key, value in params.items()}
        decoder = None
        if state["decoder"] is not None:
            decoder = SandwichDecoder(state["decoder_activation"])
            decoder.load_state_dict(state["decoder"])
        return cls(params, state["variant"], scene_extent=state["scene_extent"], decoder=decoder)


# ---------------------------------------------------------------------- formulas on a dict of rows
def _gaussian_cutoff(dtype: torch.dtype) -> float:
    """A |x| beyond which exp(-x^2) is exactly 0 in `dtype`: 1 more than where it falls to the smallest subnormal
    (x^2 = -log(tiny * eps); 124.6 > 103.3 in float32). 11.2 for float32, 28.3 for float64."""
    info = torch.finfo(dtype)
    return math.sqrt(-math.log(info.tiny * info.eps)) + 1.0


def _temporal_opacity(params: Mapping[str, torch.Tensor], t: float | torch.Tensor) -> torch.Tensor:
    """sigmoid(o) exp(-x^2) with x = (t - mu_t) / exp(s_t), [N].

    A row far outside its lifetime (|x| beyond `_gaussian_cutoff`, where exp(-x^2) is already exactly 0; or exp(s_t)
    underflowed to 0 away from mu_t) gets that exact 0 without the formula: with s_t below about -44 the formula's
    forward overflows x^2 to inf, harmlessly, but its backward computes 0 * inf = NaN for s_t although the row is
    culled, and the optimizer step then makes the row NaN. At t = mu_t exactly, a row whose exp(s_t) underflowed
    to 0 gets x = 0 (the limit; the formula's 0/0 gave NaN). Every other row's value and gradients are the
    formula's, bit for bit; a row with a NaN parameter stays NaN. (Only a row with s_t below about -43 rendered
    within 11 exp(s_t) < 3e-18 of its mu_t can still overflow its own s_t gradient.)"""
    delta = t - params["trbf_center"]
    scale = torch.exp(params["trbf_scale"])
    with torch.no_grad():
        far = (delta / scale).abs() > _gaussian_cutoff(scale.dtype)  # (NaN: not far)
        unit = far | (scale == 0)
    # Neither branch of a where may hold an inf or NaN that its backward multiplies by the other's 0 ("double where").
    x = torch.where(far, torch.zeros_like(delta), delta) / torch.where(unit, torch.ones_like(scale), scale)
    factor = torch.where(far, torch.zeros_like(x), torch.exp(-torch.square(x)))
    return (torch.sigmoid(params["opacity"]) * factor)[:, 0]


@dataclass(frozen=True)
class RowsAt:
    """The Gaussians visible at time t (temporal opacity >= MIN_VISIBLE_OPACITY), as the rasterizer takes them: their
    row ids [M] (ascending) and, per visible row, the position [M,3], unnormalised rotation [M,4], activated scales
    [M,3], temporal opacity [M] and features [M,C] at t, differentiable in the parameters."""

    index: torch.Tensor
    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacity: torch.Tensor
    features: torch.Tensor


def rows_at(params: Mapping[str, torch.Tensor], t: float, opacity_scale: torch.Tensor | None = None,
            fused: bool | None = None) -> RowsAt:  # fmt: skip
    """The visible rows at t and their state (`RowsAt`). opacity_scale [N] multiplies every temporal opacity before
    the cut. fused (default: every tensor on CPU, the parameters all float32 or all float64) computes them with the
    numba kernels of `_numba_at_time`: one parallel region per pass instead of one per torch op; otherwise with the
    torch formulas below. Both give the same values and gradients up to rounding (tests/model/test_rows_at.py)."""
    tensors = [*params.values(), *([] if opacity_scale is None else [opacity_scale])]
    fusable = (all(v.device.type == "cpu" for v in tensors)
               and {v.dtype for v in params.values()} in ({torch.float32}, {torch.float64}))  # fmt: skip
    if fused and not fusable:
        raise ValueError("rows_at(fused=True) needs every tensor on CPU and the parameters all float32 or all float64")
    if fused is None:
        fused = fusable
    if fused:
        side: dict[str, torch.Tensor] = {}
        keys = [k for k in PARAM_KEYS if k != "features_t"]
        outputs = _FusedRowsAt.apply(float(t), side, *(params[k] for k in keys), params.get("features_t"),  # type: ignore[no-untyped-call]
                                     opacity_scale)  # fmt: skip
        return RowsAt(side["index"], *outputs)
    opacity = _temporal_opacity(params, t)
    if opacity_scale is not None:
        opacity = opacity * opacity_scale
    index = torch.nonzero(opacity.detach() >= MIN_VISIBLE_OPACITY, as_tuple=False)[:, 0]
    rows: Mapping[str, torch.Tensor]
    if len(index) == len(opacity):  # nothing culled (e.g. early training): skip the row copies
        rows, visible_opacity = params, opacity
    else:
        rows = {key: _visible_rows(value, index) for key, value in params.items()}
        visible_opacity = _visible_rows(opacity, index)
    delta = _detached_delta(rows, t)
    return RowsAt(index, _means_at(rows, delta), _quaternions_at(rows, delta), torch.exp(rows["scaling"]),
                  visible_opacity, _features_at(rows, delta))  # fmt: skip


def _array(value: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(value.detach().numpy())


def _optional_columns(value: torch.Tensor | None, like: np.ndarray) -> np.ndarray:
    """A [N, k] parameter that may be absent (lite has no features_t) as an array; [N, 0] when absent."""
    return np.empty((like.shape[0], 0), like.dtype) if value is None else _array(value)


def _optional_rows(value: torch.Tensor | None, like: np.ndarray) -> np.ndarray:
    """opacity_scale [N] in the parameters' dtype; [0] when absent."""
    return np.empty(0, like.dtype) if value is None else _array(value).astype(like.dtype, copy=False)


class _FusedRowsAt(torch.autograd.Function):
    """`rows_at` by the numba kernels: (t, side, the parameters in PARAM_KEYS order without features_t, features_t
    or None, opacity_scale or None) -> (means, quats, scales, opacity, features); side["index"] gets the row ids."""

    @staticmethod
    def forward(ctx: Any, t: float, side: dict[str, torch.Tensor], *tensors: torch.Tensor | None) -> tuple[torch.Tensor, ...]:
        given, features_t_tensor, opacity_scale = tensors[:9], tensors[9], tensors[10]
        xyz, scaling, rotation, omega, opacity, trbf_center, trbf_scale, motion, features_dc = (
            _array(cast(torch.Tensor, v)) for v in given)
        dtype = xyz.dtype
        features_t = _optional_columns(features_t_tensor, xyz)
        scale_rows = _optional_rows(opacity_scale, xyz)
        cutoff = _gaussian_cutoff(cast(torch.Tensor, given[0]).dtype)
        time = dtype.type(t)  # the time in the storage dtype, as the torch formulas' t - mu_t rounds it
        values = np.empty(xyz.shape[0], dtype)
        slot = np.empty(xyz.shape[0], np.int64)
        m = _at_time.visible_rows(time, trbf_center, trbf_scale, opacity, scale_rows, opacity_scale is not None,
                                  cutoff, dtype.type(MIN_VISIBLE_OPACITY), values, slot)  # fmt: skip
        index = np.empty(m, np.int64)
        means, quats, scales = np.empty((m, 3), dtype), np.empty((m, 4), dtype), np.empty((m, 3), dtype)
        visible_opacity = np.empty(m, dtype)
        features = np.empty((m, features_dc.shape[1] + features_t.shape[1]), dtype)
        _at_time.rows_forward(time, slot, values, xyz, scaling, rotation, omega, trbf_center, motion, features_dc,
                              features_t, index, means, quats, scales, visible_opacity, features)  # fmt: skip
        # What the backward reads, saved as tensors, so that autograd refuses a backward after they were changed in
        # place (the other parameters enter the outputs linearly: their gradients need only the row's Delta').
        ctx.save_for_backward(given[1], given[4], given[5], given[6], opacity_scale)
        ctx.t, ctx.slot, ctx.cutoff, ctx.visible = time, slot, cutoff, m
        ctx.widths = (features_dc.shape[1], features_t.shape[1], features_t_tensor is not None)
        side["index"] = torch.from_numpy(index)
        return tuple(torch.from_numpy(a) for a in (means, quats, scales, visible_opacity, features))

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, *grads: torch.Tensor | None) -> tuple[torch.Tensor | None, ...]:
        scaling_tensor, opacity, trbf_center, trbf_scale, scale_tensor = ctx.saved_tensors
        scaling, opacity, trbf_center, trbf_scale = (_array(v) for v in (scaling_tensor, opacity, trbf_center, trbf_scale))
        scale_rows = _optional_rows(scale_tensor, scaling)
        dtype, n, m = scaling.dtype, scaling.shape[0], ctx.visible
        n_dc, n_t, has_features_t = ctx.widths
        shapes = ((m, 3), (m, 4), (m, 3), (m,), (m, n_dc + n_t))
        g_means, g_quats, g_scales, g_opacity, g_features = (
            np.zeros(shape, dtype) if g is None else np.ascontiguousarray(g.detach().numpy(), dtype)
            for g, shape in zip(grads, shapes))  # fmt: skip
        widths = (3, 3, 4, 4, 1, 1, 1, 9, n_dc, n_t)
        d = {key: np.empty((n, width), dtype) for key, width in zip(PARAM_KEYS, widths)}
        d_scale_rows = np.empty_like(scale_rows)
        _at_time.rows_backward(
            ctx.t, ctx.slot, scaling, opacity, trbf_center, trbf_scale, scale_rows, scale_tensor is not None,
            ctx.cutoff, g_means, g_quats, g_scales, g_opacity, g_features, d["xyz"], d["scaling"], d["rotation"],
            d["omega"], d["opacity"], d["trbf_center"], d["trbf_scale"], d["motion"], d["features_dc"],
            d["features_t"], d_scale_rows,
        )  # fmt: skip
        grad = [torch.from_numpy(d[key]) for key in PARAM_KEYS]
        return (None, None, *grad[:9], grad[9] if has_features_t else None,
                None if scale_tensor is None else torch.from_numpy(d_scale_rows).to(scale_tensor.dtype))


def _visible_rows(value: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """value[index] (unique row ids). On CPU by index_select, whose backward (index_add_) took 3.5 ms against 5.0-7.5
    for indexing's (index_put_ with accumulate) on ten parameters of 30k rows, the same gradients; elsewhere as
    indexing, whose CUDA backward does not add atomically (index_select's does: it would make the gradients'
    rounding vary from run to run)."""
    return value.index_select(0, index) if value.device.type == "cpu" else value[index]


def _detached_delta(params: Mapping[str, torch.Tensor], t: float) -> torch.Tensor:
    return (t - params["trbf_center"]).detach()


# The state at time t from Delta' = (t - mu_t).detach() (`_detached_delta`), computed once per render.
def _means_at(params: Mapping[str, torch.Tensor], d: torch.Tensor) -> torch.Tensor:
    motion = params["motion"]
    return params["xyz"] + motion[:, 0:3] * d + motion[:, 3:6] * (d * d) + motion[:, 6:9] * (d * d * d)


def _quaternions_at(params: Mapping[str, torch.Tensor], d: torch.Tensor) -> torch.Tensor:
    """The rotation at time t as an unnormalised quaternion: what the rasterizer takes, since every backend
    normalises it itself (normalising here too would only add its forward and backward to every render)."""
    return params["rotation"] + d * params["omega"]


def _features_at(params: Mapping[str, torch.Tensor], d: torch.Tensor) -> torch.Tensor:
    if "features_t" not in params:
        return params["features_dc"]
    return torch.cat([params["features_dc"], d * params["features_t"]], dim=1)


def _cloud_arrays(cloud: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    try:
        xyz = np.asarray(cloud.xyz, dtype=np.float64)
        rgb = np.asarray(cloud.rgb)
        time = np.asarray(cloud.time, dtype=np.float64).reshape(-1)
    except AttributeError as exc:
        raise DataError(None, f"initial point cloud must have xyz, rgb and time ({exc})") from None
    count = xyz.shape[0] if xyz.ndim == 2 else -1
    if xyz.shape != (count, 3) or rgb.shape != (count, 3) or time.shape != (count,):
        raise DataError(
            None,
            f"initial point cloud shapes disagree: xyz {xyz.shape}, rgb {rgb.shape}, time {time.shape}",
        )
    if count == 0:
        raise DataError(None, "initial point cloud is empty")
    if np.issubdtype(rgb.dtype, np.integer):
        rgb = rgb / 255.0
    rgb = rgb.astype(np.float64)
    for name, values in (("xyz", xyz), ("rgb", rgb), ("time", time)):
        if not np.all(np.isfinite(values)):
            raise DataError(None, f"initial point cloud has non-finite {name}")
    return xyz.astype(np.float32), rgb.astype(np.float32), time.astype(np.float32)


# The official decoders (`rgbfunction`) by the output activation they end with.
OFFICIAL_DECODERS = {"sandwich": "sigmoid", "sandwichnoact": "clamp", "sandwichnoactss": "none"}


def _activation_from_run_config(ply_path: Path) -> str | None:
    """The decoder's output activation as the PLY's run saved it; None where none says.

    The run is the nearest of the PLY's folder and the three above it that holds stgc's config.json
    (model.decoder_activation), a restored run's restored_from.json (decoder_activation) or an official run's
    cfg_args (`rgbfunction`: N3DV's sandwich is a sigmoid, Technicolor's sandwichnoact a clamp, the immersive
    configs' sandwichnoactss none), in that order within one folder. Nearest wins: a run kept inside another run's
    folder is its own, whichever kinds the two are."""
    # Resolved: the parents of a relative path ('.', 'point_cloud.ply') stop at the working directory.
    start = ply_path.parent.resolve()
    for folder in [start, *start.parents][:4]:
        if (folder / Run.CONFIG).is_file():
            # Strict: a damaged config.json would otherwise read as one that says nothing (sigmoid assumed).
            model_section = (Run(folder).read_config() or {}).get("model")
            activation = model_section.get("decoder_activation") if isinstance(model_section, dict) else None
            return activation if isinstance(activation, str) else None
        if (folder / Run.RESTORED_FROM).is_file():  # a bitstream's model restored without its run config
            activation = (read_json_object(folder / Run.RESTORED_FROM) or {}).get("decoder_activation")
            return activation if isinstance(activation, str) else None
        if (folder / OFFICIAL_ARGS).is_file():
            return _official_activation(folder, ply_path)
    return None


def _official_activation(run_dir: Path, ply_path: Path) -> str | None:
    official = official_run_args(run_dir)
    if official is None or official.get("rgbfunction") is None:
        return None
    rgbfunction = str(official["rgbfunction"])
    if rgbfunction not in OFFICIAL_DECODERS:
        raise FormatError(ply_path, f"its official run's decoder rgbfunction={rgbfunction!r} is not one stgc "
                                    f"renders ({', '.join(OFFICIAL_DECODERS)})")
    return OFFICIAL_DECODERS[rgbfunction]
