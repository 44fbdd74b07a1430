"""The two shared scenes load with the right counts, and independent readers agree on blender_toys."""

from __future__ import annotations

import json

import numpy as np
import pytest

from stgc.data import detect_format, inspect, inspect_text, open_dataset


@pytest.fixture(scope="module")
def toys(blender_toys):
    return open_dataset(blender_toys)


@pytest.fixture(scope="module")
def toys_llff(blender_toys):
    return open_dataset(blender_toys, format="n3dv")


def test_blender_toys_counts(toys, blender_toys):
    assert detect_format(blender_toys) == "blender"
    assert toys.format == "blender"
    assert toys.frames == list(range(30)) and toys.start == 0 and toys.duration == 30
    assert toys.train_views == [f"cam{i:02d}" for i in range(1, 16)]
    assert toys.test_views == ["cam00"]
    assert len(toys.train) == 15 * 30 and len(toys.test) == 30
    assert {(c.width, c.height) for c in toys.cameras} == {(160, 120)}
    assert toys.fps == 30
    assert [c.name for c in toys.train_at(7)] == toys.train_views
    assert toys.time_of(15) == 0.5 and toys.train_at(15)[0].time == 0.5
    image = toys.load_image(toys.test_at(3)[0])
    assert image.shape == (120, 160, 3) and image.dtype == np.uint8


def test_panoptic_counts(panoptic_basketball):
    data = open_dataset(panoptic_basketball)
    assert data.format == "panoptic"
    assert len(data.train_views) == 27
    assert data.test_views == ["0", "10", "15", "30"]
    assert data.frames == list(range(30))
    assert {(c.width, c.height) for c in data.cameras} == {(320, 180)}
    meta = json.loads((panoptic_basketball / "train_meta.json").read_text())
    cam = data.train_at(0)[0]
    # Panoptic K is OpenCV convention: our K has the principal point shifted by +0.5 px.
    assert cam.K[0, 2] == pytest.approx(meta["k"][0][0][0][2] + 0.5)
    assert cam.K[1, 2] == pytest.approx(meta["k"][0][0][1][2] + 0.5)
    assert np.allclose(cam.w2c, meta["w2c"][0][0])
    assert data.load_image(data.test_at(29)[3]).shape == (180, 320, 3)


def test_inspect_both_scenes(blender_toys, panoptic_basketball):
    info = inspect(blender_toys)
    assert info["points_per_frame"] == {"min": 14000, "max": 14000, "total": 420000}
    assert info["memory_uint8_bytes"] == 480 * 160 * 120 * 3
    assert info["memory_float32_bytes"] == 4 * info["memory_uint8_bytes"]
    text = inspect_text(panoptic_basketball)
    assert "27 train, 4 test" in text and "320x180" in text and "0, 10, 15, 30" in text


def test_transforms_and_poses_bounds_give_the_same_cameras(toys, toys_llff):
    assert len(toys.cameras) == len(toys_llff.cameras)
    for a, b in zip(toys.cameras, toys_llff.cameras):
        assert (a.name, a.frame, a.width, a.height) == (b.name, b.frame, b.width, b.height)
        assert np.abs(a.K - b.K).max() < 1e-5
        assert np.abs(a.w2c - b.w2c).max() < 1e-5
        assert a.image == b.image


def test_object_centres_project_identically(toys, toys_llff, blender_toys):
    centres = json.loads((blender_toys / "meta.json").read_text())["object_centres"]
    inside = total = 0
    for a, b in zip(toys.cameras, toys_llff.cameras):
        points = np.array(list(centres[str(a.frame)].values()))
        uv_a, depth_a = a.project(points)
        uv_b, depth_b = b.project(points)
        assert np.abs(uv_a - uv_b).max() < 1e-3
        assert np.all(depth_a > 0) and np.allclose(depth_a, depth_b, atol=1e-5)
        visible = (uv_a[:, 0] >= 0) & (uv_a[:, 0] < a.width) & (uv_a[:, 1] >= 0) & (uv_a[:, 1] < a.height)
        inside += int(visible.sum())
        total += len(points)
    # The four objects sit in the middle of a forward-facing arc: nearly all centres land in the images.
    assert inside / total > 0.9


def test_surface_colours_agree_with_images(toys):
    """Pixel-colour check independent of any reader: the shipped surface samples, projected with the correct
    cameras, match the image colours better than with a horizontally mirrored camera (wrong axes)."""
    xyz, rgb = toys.data_points(10)
    right, mirrored = [], []
    for cam in toys.train_at(10)[::3]:
        image = toys.load_image(cam) / 255.0
        uv, depth = cam.project(xyz)
        for flip, out in ((False, right), (True, mirrored)):
            u = cam.width - uv[:, 0] if flip else uv[:, 0]
            ok = (depth > 0) & (u >= 0) & (u < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
            px = np.stack([u[ok], uv[ok, 1]], 1).astype(int)
            out.append(np.abs(image[px[:, 1], px[:, 0]] - rgb[ok]).mean(axis=1))
    assert np.median(np.concatenate(right)) < np.median(np.concatenate(mirrored)) - 0.03


def test_segments_and_downscale(blender_toys, toys):
    from stgc.data import segments

    assert segments(300, 50) == [(0, 50), (50, 50), (100, 50), (150, 50), (200, 50), (250, 50)]
    assert segments(30, 12) == [(0, 12), (12, 12), (24, 6)]
    part = open_dataset(blender_toys, start=10, duration=5, downscale=2)
    assert part.frames == [10, 11, 12, 13, 14]
    assert part.train_at(12)[0].time == pytest.approx(0.4)
    cam = part.test_at(11)[0]
    assert (cam.width, cam.height) == (80, 60) and np.allclose(cam.K[:2], toys.test_at(11)[0].K[:2] / 2)
    small = part.load_image(cam).astype(np.float64)
    full = toys.load_image(toys.test_at(11)[0]).astype(np.float64)
    assert np.abs(small - full.reshape(60, 2, 80, 2, 3).mean(axis=(1, 3))).max() <= 0.5 + 1e-9
    nxt = part.segment(15, 5)
    assert nxt.frames == list(range(15, 20)) and nxt.test_views == ["cam00"]
    split = open_dataset(blender_toys, test_cameras="cam03,cam04", duration=5)
    assert split.test_views == ["cam03", "cam04"] and split.segment(5, 5).test_views == ["cam03", "cam04"]
    assert toys.scene_extent() == pytest.approx(
        1.1 * max(np.linalg.norm(c.center - np.mean([d.center for d in toys.train], axis=0)) for c in toys.train))
