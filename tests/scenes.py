"""Tiny generated multi-camera scenes, written in a real format, so tests need no files from outside the repository.

`write_panoptic_scene` renders a known static STG model (a textured shell of Gaussians around a small solid
ball) from cameras on a ring and writes the Dynamic 3D Gaussians layout: train_meta.json, test_meta.json,
ims/<cam>/<frame>.png and, optionally, seg/<cam>/<frame>.png foreground masks of the ball.
`write_n3dv_scene` writes a Neural 3D Video layout of noise images, for what only needs a valid dataset;
`write_dnerf_scene` a monocular D-NeRF one whose test images lie between the training images' times.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch
from PIL import Image

from stgc.data.cameras import Camera, w2c_to_llff
from stgc.model import STGModel

BALL_CENTRE = np.array([0.0, 0.0, 0.0])
BALL_RADIUS = 0.5


@dataclass
class SyntheticScene:
    root: Path
    model: STGModel  # the model the images were rendered from (before any colour distortion)
    cameras: list[Camera]  # every (view, frame), time filled in
    test_names: list[str]
    gains: dict[str, np.ndarray]  # per camera: the RGB gain applied to its images
    offsets: dict[str, np.ndarray]  # per camera: the RGB offset applied after the gain


def ring_camera(name: str, angle: float, frame: int, width: int, height: int, radius: float = 3.0) -> Camera:
    """A camera on a horizontal ring of `radius`, looking at the origin (OpenCV axes, y down)."""
    centre = np.array([radius * np.sin(angle), 0.3 * np.cos(3 * angle), -radius * np.cos(angle)])
    forward = -centre / np.linalg.norm(centre)
    right = np.cross(forward, [0.0, -1.0, 0.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    R = np.stack([right, down, forward])  # rows: camera axes in world coordinates
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, -R @ centre
    focal = 0.9 * width
    K = np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
    return Camera(name, frame, 0.0, K, w2c, width, height)


def scene_model(seed: int = 0, shell: int = 600, ball: int = 150) -> STGModel:
    """Static lite model: a textured shell (radius 1.6, seen from inside the camera ring's centre side) and a ball."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(shell, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    shell_xyz = 1.6 * d
    shell_rgb = 0.5 + 0.4 * np.sign(np.sin(6 * d[:, :1]) * np.sin(6 * d[:, 1:2])) * np.array([[1.0, 0.6, 0.2]])
    b = rng.normal(size=(ball, 3))
    b = BALL_CENTRE + BALL_RADIUS * 0.8 * b / np.linalg.norm(b, axis=1, keepdims=True) * rng.random((ball, 1)) ** 0.3
    ball_rgb = np.tile([[0.9, 0.2, 0.1]], (ball, 1))
    cloud = SimpleNamespace(xyz=np.concatenate([shell_xyz, b]).astype(np.float32),
                            rgb=np.clip(np.concatenate([shell_rgb, ball_rgb]), 0, 1).astype(np.float32),
                            time=np.full(shell + ball, 0.5, np.float32))
    model = STGModel.from_points(cloud, variant="lite", scene_extent=3.3)
    with torch.no_grad():
        model.params["opacity"].fill_(3.0)
        model.params["trbf_scale"].fill_(3.0)  # effectively static over [0, 1]
        model.params["scaling"].clamp_(max=float(np.log(0.12)))
    return model


def write_panoptic_scene(root: Path, *, views: int = 7, frames: int = 3, width: int = 40, height: int = 30,
                         test_views: tuple[int, ...] = (0,), gains: dict[int, tuple] | None = None,
                         offsets: dict[int, tuple] | None = None, masks: bool = False, seed: int = 0) -> SyntheticScene:
    """Render `scene_model` from `views` ring cameras x `frames` frames into a Panoptic-layout folder.

    gains/offsets: per view index, an RGB gain and offset applied to that camera's images (a real rig's colour
    disagreement); the images are rounded to 8 bits after it."""
    root = Path(root)
    model = scene_model(seed)
    gains, offsets = gains or {}, offsets or {}
    metas = {"train": {"k": [], "w2c": [], "fn": [], "cam_id": []}, "test": {"k": [], "w2c": [], "fn": [], "cam_id": []}}
    cameras = []
    for f in range(frames):
        rows = {"train": {k: [] for k in metas["train"]}, "test": {k: [] for k in metas["test"]}}
        for v in range(views):
            cam = ring_camera(str(v), 2 * np.pi * v / views, f, width, height)
            cam = Camera(cam.name, f, f / frames, cam.K, cam.w2c, width, height)
            with torch.no_grad():
                rgb = model.render(cam, t=cam.time, background=torch.zeros(3), backend="torch").rgb.numpy()
            rgb = rgb * np.asarray(gains.get(v, (1, 1, 1))) + np.asarray(offsets.get(v, (0, 0, 0)))
            fn = f"{v}/{f:06d}.png"
            (root / "ims" / str(v)).mkdir(parents=True, exist_ok=True)
            Image.fromarray(np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)).save(root / "ims" / fn)
            if masks and v not in test_views:
                (root / "seg" / str(v)).mkdir(parents=True, exist_ok=True)
                Image.fromarray(ball_mask(cam)).save(root / "seg" / fn)
            split = "test" if v in test_views else "train"
            # Panoptic K is OpenCV (pixel centres at integers); ours is corner-convention.
            K = cam.K.copy()
            K[0, 2] -= 0.5
            K[1, 2] -= 0.5
            rows[split]["k"].append(K.tolist())
            rows[split]["w2c"].append(cam.w2c.tolist())
            rows[split]["fn"].append(fn)
            rows[split]["cam_id"].append(v)
            cameras.append(cam)
        for split in metas:
            for k in metas[split]:
                metas[split][k].append(rows[split][k])
    for split, meta in metas.items():
        (root / f"{split}_meta.json").write_text(json.dumps({"w": width, "h": height, **meta}))
    return SyntheticScene(root, model, cameras, [str(v) for v in test_views],
                          {str(v): np.asarray(g, float) for v, g in gains.items()},
                          {str(v): np.asarray(c, float) for v, c in offsets.items()})


def ball_mask(camera: Camera) -> np.ndarray:
    """uint8 [H, W]: 255 where the ray of the pixel centre hits the ball, else 0."""
    ys, xs = np.mgrid[0:camera.height, 0:camera.width] + 0.5
    pix = np.stack([xs, ys, np.ones_like(xs)], axis=-1).reshape(-1, 3)
    dirs = pix @ np.linalg.inv(camera.K).T @ camera.w2c[:3, :3]  # world directions (R^T d)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    o = camera.center - BALL_CENTRE
    b = dirs @ o
    disc = b**2 - (o @ o - BALL_RADIUS**2)
    hit = (disc >= 0) & (-b - np.sqrt(np.maximum(disc, 0)) > 0)
    return (hit.reshape(camera.height, camera.width) * 255).astype(np.uint8)


def add_blender_transforms(scene: SyntheticScene) -> Path:
    """Describe the same images and cameras as a Blender/D-NeRF multi-view scene (transforms_train/test.json, c2w
    in OpenGL axes) in the scene's folder; returns the folder. A synthetic render, so the Blender reader's
    defaults apply (no colour correction, the official near plane)."""
    splits: dict[str, list] = {"train": [], "test": []}
    frames = sorted({c.frame for c in scene.cameras})
    for cam in scene.cameras:
        c2w = np.linalg.inv(cam.w2c)
        c2w[:3, 1:3] *= -1  # OpenCV (y down, z forward) -> OpenGL (y up, z backward)
        split = "test" if cam.name in scene.test_names else "train"
        splits[split].append({"file_path": f"ims/{cam.name}/{cam.frame:06d}.png", "camera": cam.name,
                              "frame_index": cam.frame, "time": cam.frame / len(frames),
                              "transform_matrix": c2w.tolist()})
    cam = scene.cameras[0]
    for split, entries in splits.items():
        meta = {"fl_x": cam.K[0, 0], "fl_y": cam.K[1, 1], "cx": cam.K[0, 2], "cy": cam.K[1, 2], "w": cam.width,
                "h": cam.height, "frames": entries}
        (scene.root / f"transforms_{split}.json").write_text(json.dumps(meta))
    return scene.root


def moving_model(model: STGModel) -> STGModel:
    """The scene's model with motion, rotation speed and a short temporal life, so time matters."""
    moving = STGModel.from_state_dict(model.state_dict())
    rng = np.random.default_rng(0)
    with torch.no_grad():
        moving.params["motion"][:, 0:3] = torch.from_numpy(rng.normal(0, 0.3, (moving.num_gaussians, 3))).float()
        moving.params["omega"].normal_(0, 0.5, generator=torch.Generator().manual_seed(1))
        moving.params["trbf_scale"].fill_(float(np.log(0.15)))
        moving.params["trbf_center"].uniform_(0, 1, generator=torch.Generator().manual_seed(2))
    return moving


def write_n3dv_scene(root: Path, cams: int = 3, frames: int = 2, width: int = 16, height: int = 12) -> Path:
    """poses_bounds.npy (camera k at x = 0.3k, 4 units from the origin, focal 20) + cam<k>/<frame>.png noise."""
    rng = np.random.default_rng(0)
    root.mkdir(parents=True, exist_ok=True)
    rows = []
    for k in range(cams):
        w2c = np.eye(4)
        w2c[:3, 3] = [0.3 * k, 0.0, 4.0]
        rows.append(np.concatenate([w2c_to_llff(w2c, height, width, 20.0).ravel(), [1.0, 10.0]]))
        for f in range(frames):
            path = root / f"cam{k:02d}" / f"{f:04d}.png"
            path.parent.mkdir(parents=True, exist_ok=True)
            Image.fromarray(rng.integers(0, 256, size=(height, width, 3), dtype=np.uint8)).save(path)
    np.save(root / "poses_bounds.npy", np.array(rows))
    return root


def write_dnerf_scene(root: Path, times: dict[str, list[float]] | None = None) -> Path:
    """transforms_train/test.json (camera_angle_x only, file_path without extension) + RGBA images whose left half
    is opaque orange, the right transparent; the camera at z = -(3 + t), looking at the origin. Default times:
    train 0, 0.5, 1; test 0.25, 0.75 (frames 1 and 3: only a test image holds them)."""
    from stgc.data.cameras import w2c_to_opengl_c2w

    times = times or {"train": [0.0, 0.5, 1.0], "test": [0.25, 0.75]}
    for split, ts in times.items():
        frames = []
        for i, t in enumerate(ts):
            rgba = np.zeros((8, 10, 4), np.uint8)
            rgba[:, :5] = [200, 100, 50, 255]
            (root / split).mkdir(parents=True, exist_ok=True)
            Image.fromarray(rgba).save(root / split / f"r_{i:03d}.png")
            w2c = np.eye(4)
            w2c[:3, 3] = [0, 0, 3 + t]
            frames.append({"file_path": f"./{split}/r_{i:03d}", "time": t,
                           "transform_matrix": w2c_to_opengl_c2w(w2c).tolist()})
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": 0.8, "frames": frames}))
    return root


def train_tiny_run(scene: SyntheticScene, run: Path, *extra: str) -> int:
    """`stgc train` of a scene for 20 iterations from random points, checkpointing every 5 (resume tests)."""
    from stgc.cli import main

    return main(["train", str(scene.root), "--out", str(run), "--set", "train.iterations=20",
                 "--set", "train.schedule_scale=0.01", "--set", "data.init_source=random",
                 "--set", "train.progress=false", "--set", "train.tensorboard=false",
                 "--set", "train.checkpoint_every=5", "--set", "train.log_every=1",
                 "--set", "train.densify.enabled=false", *extra])
