"""Exports to the tools people use: one static 3D Gaussian Splatting PLY per frame (`stgc export --format
ply-frames`), in the INRIA layout that SuperSplat, gsplat, nerfstudio and the 3DGS viewers read; and the whole
model as one `.splatv` file for splaTV, the browser viewer the official STG README points to (`--format splatv`).

A Spacetime Gaussian at time t is a static 3D Gaussian: its polynomial motion gives the position, its angular
velocity the rotation, and its temporal radial basis scales the opacity (`sigmoid(o) exp(-((t - mu_t) / exp(s_t))^2)`).
Those three are exact. Gaussians whose opacity at t is below 1/255 cannot touch a pixel and are left out.

Colour is where a static splat loses something:
- lite model: the splatted colour is the Gaussian's own RGB, written as the degree-0 SH coefficient
  (f_dc = (rgb - 0.5) / C0); exact where the colour is not negative. Readers of the INRIA layout clamp each
  Gaussian's colour at 0, and stgc (like STG lite) splats it unclamped, so a Gaussian with a negative channel
  (nothing bounds the lite colours) renders brighter there than here. The same holds for a full model whose
  decoder has no output activation.
- full model: STG splats 9 features and decodes them per *pixel* with a small MLP that also sees the viewing
  direction. A static splat needs one colour per *Gaussian*: the decoder is applied to each Gaussian's own
  features, with the ray from the training cameras' centroid to the Gaussian (the average training view).
  What is lost: view dependence (the colour is frozen to that direction), and the decoder's nonlinearity acts on
  each Gaussian instead of on the composited features, so where Gaussians overlap the colours differ.
Higher SH bands are written as zeros (45 `f_rest_*` fields, degree 3) because readers of the INRIA layout expect
them.

The near plane: stgc culls a Gaussian whose centre is closer to the camera than the camera's near plane (1.0 on
Panoptic data, STG's 0.2 by default), and a model is trained and evaluated so. The tools that read the exports cull
nearer (gsplat and nerfstudio at 0.01, the INRIA viewers at 0.2, splaTV at about 0.09-0.2), so Gaussians that the
model never showed to a camera, in front of it, can fog that camera's view there. Each export records the model's
near plane (`near_plane` in export.json and in the .splatv header), and a warning says so when it is above 0.2.
"""

from __future__ import annotations

import json
import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from stgc.compaction.matching import canonical_quaternions
from stgc.data.dataset import Dataset
from stgc.errors import DataError
from stgc.eval.video import ModelSource, frame_selection, load_model_and_dataset
from stgc.fileio import atomic_folder, atomic_path, write_json
from stgc.model import MIN_VISIBLE_OPACITY, STGModel, rows_at

log = logging.getLogger(__name__)

SH_C0 = 0.28209479177387814  # the degree-0 real spherical harmonic, 1 / (2 sqrt(pi))
SH_REST = 45  # degree-3 bands 1-3, three colours
INRIA_FIELDS = (
    ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    + [f"f_rest_{i}" for i in range(SH_REST)]
    + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
)
EXPORT_FORMATS = ("ply-frames", "splatv")
# Opacity logits of (almost) transparent or opaque Gaussians stay finite.
_OPACITY_EPS = 1e-6
# The largest near plane among the tools that read the exports (the INRIA viewers'; gsplat and nerfstudio use 0.01,
# splaTV about 0.09-0.2): a model that culls farther than this shows them Gaussians it never showed its cameras.
VIEWER_NEAR_PLANE = 0.2


@dataclass
class StaticGaussians:
    """Gaussians of one instant, activated: positions, unit quaternions (w, x, y, z), log-scales, opacity and RGB."""

    means: np.ndarray  # [M, 3]
    quats: np.ndarray  # [M, 4]
    log_scales: np.ndarray  # [M, 3]
    opacity: np.ndarray  # [M]
    rgb: np.ndarray  # [M, 3], the colour a static splat shows (see the module docstring)

    def __len__(self) -> int:
        return int(self.means.shape[0])


@torch.no_grad()
def gaussians_at(model: STGModel, t: float, view_origin: np.ndarray) -> StaticGaussians:
    """The model's Gaussians visible at time t as static 3D Gaussians; a full model's colour is decoded along the
    ray from `view_origin` to each Gaussian."""
    rows = rows_at(model.params, t)  # the rows a render at t keeps, by the same cut
    rgb = _colour_per_gaussian(model, rows.features, rows.means, view_origin)
    return StaticGaussians(
        means=rows.means.numpy().astype(np.float32),
        # Unit, and a zero one (an official error-guided insertion never trained, at t = mu_t) as (1, 0, 0, 0), as
        # the renderers draw it: a reader that divides by the norm made it NaN.
        quats=canonical_quaternions(rows.quats.numpy()).astype(np.float32),
        log_scales=model.params["scaling"].detach()[rows.index].numpy().astype(np.float32),
        opacity=rows.opacity.numpy().astype(np.float32),
        rgb=rgb.numpy().astype(np.float32),
    )


def _colour_per_gaussian(model: STGModel, features: torch.Tensor, means: torch.Tensor,
                         view_origin: np.ndarray) -> torch.Tensor:
    """[M, 3] RGB of Gaussians with these splatted features: a lite model's features are its colour; a full model's
    decoder is applied to each Gaussian's own features along the ray from `view_origin` to its mean."""
    if model.decoder is None:
        return features
    origin = torch.as_tensor(np.asarray(view_origin, np.float32).reshape(1, 3)).expand_as(means)
    directions = torch.nn.functional.normalize(means - origin, dim=1)
    return model.decoder(features, torch.cat([origin, directions], dim=1))


def write_inria_ply(path: str | Path, gaussians: StaticGaussians) -> Path:
    """Binary little-endian PLY in the INRIA 3DGS layout (pre-activation values, as its readers expect)."""
    count = len(gaussians)
    rows = np.zeros(count, dtype=[(name, "<f4") for name in INRIA_FIELDS])
    for i, axis in enumerate("xyz"):
        rows[axis] = gaussians.means[:, i]
    dc = (gaussians.rgb.astype(np.float64) - 0.5) / SH_C0
    for i in range(3):
        rows[f"f_dc_{i}"] = dc[:, i]
        rows[f"scale_{i}"] = gaussians.log_scales[:, i]
    o = np.clip(gaussians.opacity.astype(np.float64), _OPACITY_EPS, 1.0 - _OPACITY_EPS)
    rows["opacity"] = np.log(o / (1.0 - o))
    for i in range(4):
        rows[f"rot_{i}"] = gaussians.quats[:, i]
    path = Path(path)
    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(rows, "vertex")], text=False, byte_order="<").write(str(tmp))
    return path


def read_inria_ply(path: str | Path) -> StaticGaussians:
    """The activated Gaussians of an INRIA-layout PLY (degree-0 colour: 0.5 + C0 f_dc; higher bands ignored)."""
    try:
        vertex = PlyData.read(str(path))["vertex"]
        col = {name: np.asarray(vertex[name], np.float64) for name in INRIA_FIELDS if name not in ("nx", "ny", "nz")}
    except (OSError, KeyError, ValueError) as exc:
        raise DataError(Path(path), f"not an INRIA-layout 3DGS PLY ({type(exc).__name__}: {exc})") from None
    quats = np.stack([col[f"rot_{i}"] for i in range(4)], axis=1)
    return StaticGaussians(
        means=np.stack([col[a] for a in "xyz"], axis=1),
        quats=quats / np.linalg.norm(quats, axis=1, keepdims=True),
        log_scales=np.stack([col[f"scale_{i}"] for i in range(3)], axis=1),
        opacity=1.0 / (1.0 + np.exp(-col["opacity"])),
        rgb=0.5 + SH_C0 * np.stack([col[f"f_dc_{i}"] for i in range(3)], axis=1),
    )


def model_near_plane(dataset: Dataset, written: str | Path) -> float:
    """The near plane the model renders with (its dataset's cameras'); a warning, naming `written`, when the tools
    that read the export cull nearer than it (see the module docstring)."""
    near = float(dataset.near_plane)
    if near > VIEWER_NEAR_PLANE:
        log.warning("%s: the model culls Gaussians closer than %g to a camera (its near plane), and the viewers of "
                    "this export cull nearer (gsplat and nerfstudio at 0.01, the INRIA viewers at 0.2, splaTV at "
                    "about 0.09-0.2): Gaussians the model never showed to a camera can fog the views from near its "
                    "cameras. Set the viewer's near plane to %g where it has one (recorded as near_plane in %s), or "
                    "look from farther in front of the cameras", written, near, near, written)
    return near


def training_view_origin(dataset: Dataset) -> np.ndarray:
    """The centroid of the training cameras' centres (the viewpoint a full model's static colours are decoded for)."""
    return np.mean([np.asarray(c.center, np.float64) for c in dataset.train], axis=0)


def export_ply_frames(source: ModelSource, out_dir: str | Path, frames: Any = None,
                      dataset: Dataset | None = None, data_path: str | Path | None = None) -> list[Path]:
    """Write OUT/frame_<NNNNNN>.ply (one static 3DGS per selected frame, at that frame's time) and OUT/export.json
    (times, counts, the colour approximation); returns the PLY paths."""
    model, dataset = load_model_and_dataset(source, dataset, data_path)
    # One file per frame: a frame listed twice is written once, at its first place (a repeat replaced the file and
    # was counted and listed twice).
    chosen = list(dict.fromkeys(frame_selection(frames, list(dataset.frames))))
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise DataError(out, "exists and is not a directory")
    foreign = sorted(p.name for p in out.iterdir() if not _written_by_export(p)) if out.is_dir() else []
    if foreign:  # the folder is replaced as a whole: never with someone's files in it
        raise DataError(out, f"holds files that are not an earlier export ({', '.join(foreign[:3])}"
                             f"{', ...' if len(foreign) > 3 else ''}); choose a new or empty folder")
    origin = training_view_origin(dataset)
    near = model_near_plane(dataset, out / "export.json")
    entries: list[dict[str, Any]] = []
    with atomic_folder(out) as tmp:  # an earlier export's frames are not left beside this one's
        for frame in chosen:
            t = float(dataset.time_of(frame))
            gaussians = gaussians_at(model, t, origin)
            path = write_inria_ply(tmp / f"frame_{frame:06d}.ply", gaussians)
            entries.append({"frame": frame, "time": t, "file": path.name, "gaussians": len(gaussians)})
        colour = ("exact: the lite model's own RGB as degree-0 SH" if model.decoder is None else
                  "the full model's decoder applied per Gaussian along the ray from the training cameras' centroid "
                  f"{[round(float(v), 6) for v in origin]}: no view dependence, and decoded per Gaussian instead "
                  "of per pixel")
        write_json(tmp / "export.json", {
            "format": "ply-frames", "layout": "INRIA 3DGS (SH degree 3, bands 1-3 zero)",
            "source": str(source) if isinstance(source, (str, Path)) else "in-memory model",
            "variant": model.variant, "colour": colour, "frames": entries,
            "sh_c0": SH_C0, "min_opacity": float(MIN_VISIBLE_OPACITY), "near_plane": near})
    return [out / str(entry["file"]) for entry in entries]


def _written_by_export(path: Path) -> bool:
    return path.is_file() and (path.name == "export.json" or re.fullmatch(r"frame_\d+\.ply", path.name) is not None)


def static_render_inputs(gaussians: StaticGaussians) -> dict[str, torch.Tensor]:
    """Tensors that `stgc.render.rasterize` takes for a static splat (means, quats, scales, opacities, features)."""
    return {
        "means": torch.as_tensor(gaussians.means, dtype=torch.float32),
        "quats": torch.as_tensor(gaussians.quats, dtype=torch.float32),
        "scales": torch.exp(torch.as_tensor(gaussians.log_scales, dtype=torch.float32)),
        "opacities": torch.as_tensor(gaussians.opacity, dtype=torch.float32),
        "features": torch.as_tensor(gaussians.rgb, dtype=torch.float32),
    }


# splaTV's file (its viewer's description of the format, hybrid.js): two little-endian uint32, the magic 0x674B and
# the length of a UTF-8 JSON list of chunks; then the chunk, an RGBA32UI texture 4096 texels wide holding 4 texels
# (16 uint32) per Gaussian:
#   0-2  position x, y, z (float32)            8-12 motion: (m0, m1) (m2, m3) (m4, m5) (m6, m7) (m8, 0), half floats
#   3-4  quaternion (w, x) (y, z), half floats  13-14 angular velocity (w, x) (y, z), half floats
#   5-6  scale (sx, sy) (sz, 0), half floats    15   (temporal centre mu_t, temporal scale exp(s_t)), half floats
#   7    R, G, B, opacity as bytes
# A pair (a, b) packs a into the low 16 bits (GLSL packHalf2x16). At time t the viewer places a Gaussian at
# x + m(0:3) dt + m(3:6) dt^2 + m(6:9) dt^3 and rotates it by normalize(q + omega dt), dt = t - mu_t, and scales
# its opacity by exp(-(dt / scale_t)^2): STG's formulas.
SPLATV_MAGIC = 0x674B
SPLATV_TEXWIDTH = 4096


def _half_pairs(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    low = np.asarray(a, np.float32).astype(np.float16).view(np.uint16).astype(np.uint32)
    high = np.asarray(b, np.float32).astype(np.float16).view(np.uint16).astype(np.uint32)
    return low | (high << np.uint32(16))


@torch.no_grad()
def splatv_colours(model: STGModel, view_origin: np.ndarray) -> np.ndarray:
    """One RGB per Gaussian for the splatv viewer (which has no view dependence and no colour over time): the lite
    model's own; the full model's decoded at the Gaussian's most visible time mu_t (where its time feature is zero),
    along the ray from `view_origin`."""
    # At t = mu_t every Gaussian sits at its base position and its time feature (t - mu_t) features_t is zero.
    p = {k: v.detach() for k, v in model.params.items()}
    features = p["features_dc"] if "features_t" not in p else torch.cat([p["features_dc"], 0 * p["features_t"]], 1)
    return _colour_per_gaussian(model, features, p["xyz"], view_origin).numpy().astype(np.float32)


def splatv_cameras(dataset: Dataset) -> list[dict[str, Any]]:
    """The dataset's cameras (one per view, first frame) as splaTV's viewer reads them (the 3DGS cameras.json
    entries: centre `position`, camera-to-world `rotation` rows, focal lengths in pixels)."""
    seen: dict[str, dict[str, Any]] = {}
    for cam in [*dataset.test, *dataset.train]:
        if str(cam.name) in seen:
            continue
        c2w = np.linalg.inv(np.asarray(cam.w2c, np.float64))
        seen[str(cam.name)] = {"id": len(seen), "img_name": str(cam.name), "width": int(cam.width),
                               "height": int(cam.height), "position": [float(v) for v in cam.center],
                               "rotation": [[float(v) for v in row] for row in c2w[:3, :3]],
                               "fx": float(cam.K[0, 0]), "fy": float(cam.K[1, 1])}
    return list(seen.values())


def write_splatv(path: str | Path, model: STGModel, dataset: Dataset) -> Path:
    """The whole model as one splaTV file (layout above); atomically."""
    p = {k: v.detach().numpy().astype(np.float32) for k, v in model.params.items()}
    count = model.num_gaussians
    height = max(1, math.ceil(4 * count / SPLATV_TEXWIDTH))
    texels = np.zeros((SPLATV_TEXWIDTH * height * 4,), np.uint32)
    rows = texels[: 16 * count].reshape(count, 16)
    rows[:, 0:3] = p["xyz"].view(np.uint32)
    # The stored quaternion as it is: the viewer normalises q + omega dt, as STG does (normalising q first would not).
    # One that stays zero (no angular velocity either) is drawn unrotated by stgc: written as (1, 0, 0, 0), since the
    # viewer's normalisation would make it NaN.
    quats = p["rotation"].copy()
    quats[~(quats.any(axis=1) | p["omega"].any(axis=1))] = (1.0, 0.0, 0.0, 0.0)
    rows[:, 3], rows[:, 4] = _half_pairs(quats[:, 0], quats[:, 1]), _half_pairs(quats[:, 2], quats[:, 3])
    scales = np.exp(p["scaling"])
    rows[:, 5], rows[:, 6] = _half_pairs(scales[:, 0], scales[:, 1]), _half_pairs(scales[:, 2], np.zeros(count))
    rgb = np.clip(np.rint(splatv_colours(model, training_view_origin(dataset)) * 255.0), 0, 255).astype(np.uint32)
    alpha = np.clip(np.rint(1.0 / (1.0 + np.exp(-p["opacity"][:, 0])) * 255.0), 0, 255).astype(np.uint32)
    rows[:, 7] = rgb[:, 0] | (rgb[:, 1] << 8) | (rgb[:, 2] << 16) | (alpha << 24)
    motion = np.concatenate([p["motion"], np.zeros((count, 1), np.float32)], axis=1)
    for k in range(5):
        rows[:, 8 + k] = _half_pairs(motion[:, 2 * k], motion[:, 2 * k + 1])
    rows[:, 13], rows[:, 14] = _half_pairs(p["omega"][:, 0], p["omega"][:, 1]), _half_pairs(p["omega"][:, 2], p["omega"][:, 3])
    # A temporal scale beyond the largest half float (65504, e^11.09) would be written as inf; that large, the
    # temporal factor exp(-(dt / scale)^2) is 1 within 2.4e-10 for any |dt| <= 1 either way.
    temporal_scale = np.minimum(np.exp(p["trbf_scale"][:, 0].astype(np.float64)), float(np.finfo(np.float16).max))
    rows[:, 15] = _half_pairs(p["trbf_center"][:, 0], temporal_scale)
    payload = texels.astype("<u4").tobytes()
    path = Path(path)
    near = model_near_plane(dataset, path)  # splaTV reads type, size, texwidth, texheight, cameras: not this key
    header = json.dumps([{"type": "splat", "size": len(payload), "texwidth": SPLATV_TEXWIDTH, "texheight": height,
                          "cameras": splatv_cameras(dataset), "near_plane": near}]).encode("utf-8")
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(np.array([SPLATV_MAGIC, len(header)], "<u4").tobytes() + header + payload)
    return path


def export_splatv(source: ModelSource, out_path: str | Path, dataset: Dataset | None = None,
                  data_path: str | Path | None = None) -> Path:
    """`stgc export --format splatv`: the model (a run or a .stgc file) as one splaTV file."""
    model, dataset = load_model_and_dataset(source, dataset, data_path)
    if Path(out_path).suffix.lower() != ".splatv":
        raise DataError(Path(out_path), "a splaTV file is written as FILE.splatv")
    return write_splatv(out_path, model, dataset)


__all__ = ["EXPORT_FORMATS", "INRIA_FIELDS", "SH_C0", "VIEWER_NEAR_PLANE", "StaticGaussians", "export_ply_frames",
           "export_splatv", "gaussians_at", "model_near_plane", "read_inria_ply", "splatv_cameras", "splatv_colours",
           "static_render_inputs", "training_view_origin", "write_inria_ply", "write_splatv"]
