"""Initial points: shipped data, random, triangulation (pycolmap), and the two preprocessing rules."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from stgc.data import (
    DataConfig,
    PointCloud,
    initial_points,
    open_dataset,
    preprocess_points,
)
from stgc.errors import DataError

# Points on a line at gaps 1, 2, ..., 7: nearest-neighbour distances are 1, 1, 2, 3, 4, 5, 6, 7.
LINE = np.array([0, 1, 3, 6, 10, 15, 21, 28], dtype=np.float64)


def line_cloud(times: list[float], offset: float = 100.0) -> PointCloud:
    xyz = np.concatenate([np.stack([LINE + k * offset, np.zeros(8), np.zeros(8)], 1) for k in range(len(times))])
    return PointCloud(xyz, np.zeros_like(xyz), np.repeat(times, 8))


def test_stg_isolated_counts_replicate_the_official_rule():
    cloud, report = preprocess_points(line_cloud([0.0, 0.5]), "stg-isolated", 0.25)
    # First frame kept whole; second: num_take = int(0.25 * 8) = 2, threshold = 2nd largest distance = 6,
    # strictly greater -> only the point at 28 (distance 7): num_take - 1 points (the official off-by-one).
    assert [r["after"] for r in report.per_frame] == [8, 1]
    assert np.allclose(cloud.xyz[8:, 0], [128.0])
    # fraction 0.5: num_take = 4, threshold 4 -> distances 5, 6, 7 kept.
    assert preprocess_points(line_cloud([0.0, 0.5]), "stg-isolated", 0.5)[1].after == 8 + 3
    # num_take = 0 (fraction 0.1 of 8): official s[-0] = s[0] = 1 -> drops the two points at distance 1.
    assert preprocess_points(line_cloud([0.0, 0.5]), "stg-isolated", 0.1)[1].after == 8 + 6


def test_closest_pairs_counts_and_never_drops_both_of_a_pair():
    # Pairs (dedup): {0,1} d1, {1,3} d2, {3,6} d3, {6,10} d4, {10,15} d5, {15,21} d6, {21,28} d7 -> 7 pairs.
    cloud, report = preprocess_points(line_cloud([0.0, 0.5]), "closest-pairs", 0.25)
    # int(0.25 * 7) = 1 pair in every frame (the first too): drop the larger index of {0, 1}.
    assert [r["after"] for r in report.per_frame] == [7, 7]
    assert 1.0 not in cloud.xyz[:, 0] and 0.0 in cloud.xyz[:, 0]
    # fraction 0.5: int(3.5) = 3 pairs {0,1}, {1,3}, {3,6}. Dropping 1 protects 0 and 3; {1,3} has lost 1
    # already; {3,6}: 3 is protected, so 6 goes. Kept: 0, 3, 10, 15, 21, 28.
    cloud, report = preprocess_points(line_cloud([0.3]), "closest-pairs", 0.5)
    assert sorted(cloud.xyz[:, 0]) == [0, 3, 10, 15, 21, 28]
    # Every selected pair keeps a member, also on random clouds with many chains.
    rng = np.random.default_rng(1)
    xyz = rng.uniform(size=(500, 3))
    kept, report = preprocess_points(PointCloud(xyz, xyz, np.zeros(500)), "closest-pairs", 1.0)
    from stgc.data.preprocess import nearest_neighbours

    _, nn = nearest_neighbours(xyz)
    survivors = {tuple(p) for p in kept.xyz.round(9)}
    alive = np.array([tuple(p) in survivors for p in xyz.astype(np.float32).round(9)])
    assert np.all(alive | alive[nn])  # for every pair (i, NN(i)), at least one member survives
    assert report.after < 500


def test_none_keeps_everything_and_counts_per_frame():
    cloud, report = preprocess_points(line_cloud([0.0, 0.2, 0.4]), "none")
    assert len(cloud) == 24 and report.as_dict()["per_frame"][2] == {"time": pytest.approx(0.4), "before": 8, "after": 8}


def test_data_points_on_blender_toys(blender_toys):
    data = open_dataset(blender_toys, start=4, duration=4)
    cloud = initial_points(data, "auto", frames=[4, 6], max_points_per_frame=500)
    assert len(cloud) == 1000
    assert cloud.counts_per_time() == {0.0: 500, 0.5: 500}
    assert cloud.xyz.dtype == np.float32 and 0 <= cloud.rgb.min() and cloud.rgb.max() <= 1
    raw = np.load(blender_toys / "points3d" / "0006.npy")
    # Subsampled points are a subset of the frame's shipped points.
    assert set(map(tuple, cloud.xyz[cloud.time == 0.5])) <= set(map(tuple, raw[:, :3]))
    with pytest.raises(DataError, match="not in the segment"):
        initial_points(data, "data", frames=[20])
    # The rule sees each frame's whole cloud; the cap then thins its output by cap / raw count.
    cfg = DataConfig(init_frames_every=2, max_points_per_frame=100, preprocess="stg-isolated")
    cloud, report = cfg.initial_points(data)
    whole = len(raw)
    assert [r["before"] for r in report.per_frame] == [len(np.load(blender_toys / "points3d" / "0004.npy")), whole]
    assert 0.24 * whole <= report.per_frame[1]["after"] <= int(0.25 * whole) - 1  # official strict threshold
    assert cloud.counts_per_time() == {0.0: 100, 0.5: round(report.per_frame[1]["after"] * 100 / whole)}
    from stgc.data.preprocess import preprocess_points
    isolated, _ = preprocess_points(initial_points(data, "data", frames=[4, 6]), "stg-isolated")
    # The capped run's frame-6 points are drawn from the most isolated quarter of the whole frame-6 cloud
    # (capping first would have picked other points, isolated only because of the sampling).
    assert set(map(tuple, cloud.xyz[cloud.time == 0.5])) <= set(map(tuple, isolated.xyz[isolated.time == 0.5]))


def test_random_points_are_seen_by_two_cameras(panoptic_basketball):
    data = open_dataset(panoptic_basketball, duration=2)
    with pytest.warns(UserWarning, match="random points"):
        cloud = initial_points(data, "random", frames=[1], max_points_per_frame=300, seed=5)
    assert len(cloud) == 300 and np.all(cloud.time == 0.5)
    seen = np.zeros(300, int)
    for cam in data.train_at(1):
        uv, depth = cam.project(cloud.xyz)
        seen += (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    assert seen.min() >= 2
    with pytest.raises(DataError, match="no initial points ship"):
        initial_points(data, "data")


@pytest.mark.slow
def test_triangulation_reprojects_below_one_pixel(panoptic_basketball, tmp_path, monkeypatch):
    """pycolmap SIFT triangulation with the known cameras, ONE frame and 9 of the 27 training views (~3 s)."""
    pytest.importorskip("pycolmap")
    from stgc.data.triangulate import triangulate_frame

    data = open_dataset(panoptic_basketball, duration=1)
    views = data.train_views[::3]
    monkeypatch.setenv("STGC_CACHE_DIR", str(tmp_path))
    result = triangulate_frame(data, 0, views=views)
    again = triangulate_frame(data, 0, views=views)  # from the disk cache, identical
    assert again.stats.get("cached") and "cached" not in result.stats
    assert np.array_equal(again.xyz, result.xyz) and np.array_equal(again.errors, result.errors)
    print("triangulation stats:", result.stats)
    assert result.stats["points"] >= 20
    assert np.all(result.track_length >= 3)
    # Independent check: reproject with our own cameras (not COLMAP's) against the SIFT keypoints.
    assert result.median_error < 1.0
    assert np.percentile(result.errors, 90) < 2.0
    cams = {c.name: c for c in data.train_at(0)}
    in_front = np.zeros(len(result.xyz), int)
    for view in views:
        in_front += cams[view].project(result.xyz)[1] > 0
    assert in_front.min() >= 3


@pytest.mark.slow
def test_triangulated_points_lie_on_the_true_surfaces(blender_toys):
    """blender_toys ships true surface samples: triangulated points (ONE frame, 8 neighbouring views, ~2 s) must lie near them.
    The samples' own nearest-neighbour spacing has median 0.054 m (p90 0.165), so 0.2 m bounds the median."""
    pytest.importorskip("pycolmap")
    from scipy.spatial import cKDTree

    from stgc.data.triangulate import triangulate_frame

    data = open_dataset(blender_toys, duration=1)
    result = triangulate_frame(data, 0, views=data.train_views[4:12], use_cache=False)
    truth = data.data_points(0)[0]
    distance, _ = cKDTree(truth).query(result.xyz)
    print("toys triangulation:", result.stats, "nearest true sample median", np.median(distance))
    assert result.stats["points"] >= 100
    assert np.median(distance) < 0.2
    assert np.mean(distance > 0.5) < 0.02
    assert result.median_error < 0.5


def test_the_triangulation_cache_key_changes_with_how_images_decode(tmp_path):
    """Two runs that decode the same files differently (RGBA over another background, a YUV file read as another
    range) must not share a cached triangulation."""
    from stgc.data.cameras import Camera
    from stgc.data.dataset import YuvFrame
    from stgc.data.triangulate import _cache_key

    png = tmp_path / "a.png"
    png.write_bytes(b"x")
    yuv = tmp_path / "a.yuv"
    yuv.write_bytes(b"x")

    def key(image, background=(0.0, 0.0, 0.0)):
        cams = [Camera("a", 0, 0.0, np.eye(3), np.eye(4), 4, 4, image=image)]
        return _cache_key(cams, 2.0, 3, background)

    assert key(png) == key(png) and key(png) != key(png, (1.0, 1.0, 1.0))
    limited, full = YuvFrame(yuv, 0, 4, 4, 8, "limited"), YuvFrame(yuv, 0, 4, 4, 8, "full")
    assert key(limited) != key(full) and key(limited) != key(YuvFrame(yuv, 1, 4, 4, 8, "limited"))


def test_auto_points_of_two_training_views_are_random_not_an_empty_triangulation(tmp_path, monkeypatch):
    """COLMAP keeps no track of two views unless asked, and min_track_length 3 drops them anyway: 'auto' on a rig of
    two training views triangulated nothing and failed ("no initial points found")."""
    from scenes import write_n3dv_scene

    pytest.importorskip("pycolmap")  # (without it 'auto' was random anyway)
    from stgc.data import points

    data = open_dataset(write_n3dv_scene(tmp_path, cams=3))  # cam00 held out: two training views
    assert len(data.train_views) == 2
    monkeypatch.setattr(points, "triangulate_frame", lambda *a, **k: pytest.fail("triangulated two views"))
    with pytest.warns(UserWarning, match="random points"):
        auto = initial_points(data, random_points_per_frame=50)
        drawn = initial_points(data, source="random", random_points_per_frame=50)
    assert len(auto) and np.array_equal(auto.xyz, drawn.xyz)


def test_auto_points_of_two_masked_training_views_stay_the_visual_hull_s(tmp_path, monkeypatch):
    """With foreground masks the frame has its hull points: 'auto' still triangulates (what it did before two views
    fell back to random points), adding nothing but what triangulation finds."""
    pytest.importorskip("pycolmap")
    from scenes import write_panoptic_scene

    from stgc.data import points

    scene = write_panoptic_scene(tmp_path, views=3, frames=1, masks=True)  # view 0 held out
    data = open_dataset(scene.root)
    assert len(data.train_views) == 2 and data.has_masks
    calls = []
    nothing = SimpleNamespace(xyz=np.zeros((0, 3), np.float32), rgb=np.zeros((0, 3), np.float32), median_error=0.0)
    monkeypatch.setattr(points, "triangulate_frame", lambda *a, **k: calls.append(a) or nothing)
    cloud = initial_points(data, mask_points_per_frame=40)
    assert len(calls) == 1 and 0 < len(cloud) <= 40


def test_two_views_triangulate_at_min_track_length_2(blender_toys, tmp_path, monkeypatch):
    """Two views give tracks of two only, which COLMAP dropped unless told to keep them (~4 s)."""
    pytest.importorskip("pycolmap")
    from stgc.data.triangulate import triangulate_frame

    held_out = ",".join(f"cam{i:02d}" for i in range(16) if i not in (7, 8))
    data = open_dataset(blender_toys, duration=1, test_cameras=held_out, format="n3dv")
    monkeypatch.setenv("STGC_CACHE_DIR", str(tmp_path))
    pair = triangulate_frame(data, 0, min_track_length=2)
    assert len(pair.xyz) >= 50 and pair.median_error < 0.5


@pytest.mark.parametrize("damage", ["empty", "truncated"])
def test_a_damaged_triangulation_cache_entry_is_computed_again(tmp_path, monkeypatch, damage):
    """An empty or truncated cache file (a full disk, a killed copy) was an EOFError or BadZipFile on every later run
    of that frame, until someone found the file and deleted it."""
    from scenes import write_n3dv_scene

    from stgc.data import triangulate

    data = open_dataset(write_n3dv_scene(tmp_path / "scene"))
    computed = triangulate.TriangulationResult(np.ones((2, 3), np.float32), np.ones((2, 3), np.float32),
                                               np.full(2, 3), np.zeros(6), {"points": 2})
    calls = []
    monkeypatch.setattr(triangulate, "_triangulate", lambda *args: calls.append(args) or computed)
    monkeypatch.setenv("STGC_CACHE_DIR", str(tmp_path / "cache"))
    triangulate.triangulate_frame(data, 0)
    (entry,) = (tmp_path / "cache" / "triangulation").glob("*.npz")
    whole = entry.read_bytes()
    entry.write_bytes(b"" if damage == "empty" else whole[: len(whole) // 2])
    again = triangulate.triangulate_frame(data, 0)
    assert len(calls) == 2 and np.array_equal(again.xyz, computed.xyz)
    assert entry.read_bytes() == whole  # written again whole
    assert triangulate.triangulate_frame(data, 0).stats.get("cached") and len(calls) == 2


def test_shipped_colours_slightly_over_one_are_clipped_not_read_as_0_to_255():
    from stgc.data.readers._common import _rgb01

    renderer = np.array([[0.5, 0.25, 1.003], [0.2, 0.4, 0.6]])
    assert np.allclose(_rgb01(renderer), [[0.5, 0.25, 1.0], [0.2, 0.4, 0.6]])
    assert np.allclose(_rgb01(np.array([[255.0, 51.0, 0.0]])), [[1.0, 0.2, 0.0]])


def test_the_viewing_region_lies_ahead_of_a_rig_that_looks_outwards(tmp_path):
    """The point closest to the optical axes of cameras on a ring looking outwards is the ring's centre, behind
    every camera: random points and the hull box were centred there."""
    from scenes import ring_camera

    from stgc.data.cameras import Camera
    from stgc.data.points import viewing_region

    cameras = [ring_camera(f"c{k}", 2 * np.pi * k / 8, 0, 32, 24) for k in range(8)]
    focus, _ = viewing_region(SimpleNamespace(train=cameras, scene_extent=lambda: 3.3))
    assert np.linalg.norm(focus) < 1e-6  # looking in: the centre, in front of each camera
    # The same cameras turned around (the camera's z axis flipped, x too to stay right-handed).
    flip = np.diag([-1.0, 1.0, -1.0, 1.0])
    cameras = [Camera(c.name, 0, 0.0, c.K, flip @ c.w2c, c.width, c.height) for c in cameras]
    focus, radius = viewing_region(SimpleNamespace(train=cameras, scene_extent=lambda: 3.3))
    for cam in cameras:  # the region reaches well ahead of every camera (it was wholly behind them)
        ahead = cam.center + cam.c2w[:3, 2] * 3.0
        assert np.all(np.abs(ahead - focus) <= radius)


def test_a_damaged_or_non_finite_point_file_is_an_error_naming_it(tmp_path):
    import struct

    from stgc.data.colmap_io import read_points
    from stgc.data.readers.panoptic import _panoptic_points

    (tmp_path / "sparse").mkdir()
    (tmp_path / "sparse" / "points3D.bin").write_bytes(struct.pack("<Q", 10**12))  # a count no file holds
    for name in ("cameras.bin", "images.bin"):
        (tmp_path / "sparse" / name).write_bytes(struct.pack("<Q", 0))
    with pytest.raises(DataError, match="points3D.bin.*10+ points, more than its 8 bytes"):
        read_points(tmp_path / "sparse")
    data = np.zeros((5, 7))
    data[2, 1] = np.nan
    np.savez(tmp_path / "init_pt_cld.npz", data=data)
    with pytest.raises(DataError, match="init_pt_cld.npz.*non-finite"):
        _panoptic_points(tmp_path / "init_pt_cld.npz")


def test_auto_points_of_monocular_data_refuse_frames_only_a_test_image_holds(tmp_path):
    """source='auto' became 'random' after the check for frames without a training camera: such frames got points
    at their times with NaN colours."""
    from scenes import write_dnerf_scene

    dataset = open_dataset(write_dnerf_scene(tmp_path))
    assert dataset.frames != dataset.train_frames
    with pytest.raises(DataError, match="have no training camera"):
        initial_points(dataset, source="auto")
    cloud = initial_points(dataset, source="auto", frames=dataset.train_frames, random_points_per_frame=20)
    assert np.isfinite(cloud.rgb).all()


@pytest.mark.slow
def test_triangulation_gives_the_same_points_on_every_run(blender_toys):
    """COLMAP's RANSAC was seeded by the clock and its thread pools finished in any order: two runs on one machine
    triangulated 505 and 504 points of a panoptic frame, so every training started from another cloud."""
    pytest.importorskip("pycolmap")
    from stgc.data.triangulate import triangulate_frame

    data = open_dataset(blender_toys, duration=1)
    runs = [triangulate_frame(data, 0, views=data.train_views[4:12], use_cache=False) for _ in range(3)]
    for again in runs[1:]:
        assert np.array_equal(again.xyz, runs[0].xyz) and np.array_equal(again.errors, runs[0].errors)
