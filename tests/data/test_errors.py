"""Bad input gives a DataError that names the offending file and the problem (never a deep traceback)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from stgc.data import open_dataset
from stgc.errors import DataError

from scenes import write_n3dv_scene as make_n3dv

W, H = 16, 12
rng = np.random.default_rng(0)


def _image(path: Path, size=(W, H)) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(rng.integers(0, 256, size=(size[1], size[0], 3), dtype=np.uint8)).save(path)


def _w2c(k: int) -> np.ndarray:
    w2c = np.eye(4)
    w2c[:3, 3] = [0.3 * k, 0.0, 4.0]
    return w2c


def make_panoptic(root: Path, frames: int = 2, cams: tuple[int, ...] = (0, 1, 2, 3)) -> Path:
    K = [[20.0, 0, 7.5], [0, 20.0, 5.5], [0, 0, 1]]
    for name, ids in (("train_meta.json", cams[1:]), ("test_meta.json", cams[:1])):
        meta = {"w": W, "h": H, "k": [], "w2c": [], "fn": [], "cam_id": []}
        for t in range(frames):
            meta["k"].append([K for _ in ids])
            meta["w2c"].append([_w2c(c).tolist() for c in ids])
            meta["fn"].append([f"{c}/{t:06d}.jpg" for c in ids])
            meta["cam_id"].append(list(ids))
            for c in ids:
                _image(root / "ims" / f"{c}/{t:06d}.jpg")
        (root / name).write_text(json.dumps(meta))
    return root


def expect_error(path_part: str, match: str, fn, *args, **kwargs) -> DataError:
    with pytest.raises(DataError, match=match) as info:
        fn(*args, **kwargs)
    assert path_part in str(info.value.path), (info.value.path, path_part)
    return info.value


def test_fixtures_are_valid(tmp_path):
    data = open_dataset(make_panoptic(tmp_path / "p"))
    assert data.test_views == ["0"] and len(data.train_views) == 3 and data.frames == [0, 1]
    data = open_dataset(make_n3dv(tmp_path / "n"))
    assert data.test_views == ["cam00"] and data.train_views == ["cam01", "cam02"]


def test_missing_image(tmp_path):
    root = make_panoptic(tmp_path)
    (root / "ims" / "2" / "000001.jpg").unlink()
    expect_error("2/000001.jpg", "missing", open_dataset, root)
    root = make_n3dv(tmp_path / "n")
    (root / "cam01" / "0001.png").unlink()
    expect_error("poses_bounds.npy", "cam01 has no image for frame.*1", open_dataset, root)


def test_extra_images(tmp_path):
    root = make_panoptic(tmp_path)
    _image(root / "ims" / "1" / "000002.jpg")
    expect_error("1/000002.jpg", "extra image", open_dataset, root)
    root = make_n3dv(tmp_path / "n")
    _image(root / "cam03" / "0000.png")
    _image(root / "cam03" / "0001.png")
    expect_error("poses_bounds.npy", "images without a camera pose: 3 poses but 4 cameras", open_dataset, root)


def test_cameras_without_images(tmp_path):
    root = make_n3dv(tmp_path, cams=3)
    for f in (root / "cam02").iterdir():
        f.unlink()
    (root / "cam02").rmdir()
    expect_error("poses_bounds.npy", "cameras without images: 3 poses but 2 cameras", open_dataset, root)


def test_unreadable_image(tmp_path):
    root = make_n3dv(tmp_path)
    (root / "cam01" / "0001.png").write_bytes(b"this is not a png")
    expect_error("cam01/0001.png", "unreadable image", open_dataset, root)
    # Without the up-front header check, the error comes when the image is loaded.
    data = open_dataset(root, check_images=False)
    cam = next(c for c in data.train if c.name == "cam01" and c.frame == 1)
    expect_error("cam01/0001.png", "unreadable image", data.load_image, cam)


def test_wrong_image_size(tmp_path):
    root = make_panoptic(tmp_path)
    _image(root / "ims" / "3" / "000001.jpg", size=(W + 2, H))
    error = expect_error("3/000001.jpg", "image is 18x12 but 16x12 was expected", open_dataset, root)
    assert "train_meta.json" in str(error)
    data = open_dataset(root, check_images=False)
    cam = next(c for c in data.train if c.name == "3" and c.frame == 1)
    expect_error("3/000001.jpg", "18x12", data.load_image, cam)


def test_nan_in_poses(tmp_path):
    root = make_panoptic(tmp_path)
    meta = json.loads((root / "train_meta.json").read_text())
    meta["w2c"][1][0][0][3] = float("nan")
    (root / "train_meta.json").write_text(json.dumps(meta))
    expect_error("train_meta.json", "camera 1 frame 1: non-finite", open_dataset, root)
    root = make_n3dv(tmp_path / "n")
    rows = np.load(root / "poses_bounds.npy")
    rows[2, 3] = np.nan
    np.save(root / "poses_bounds.npy", rows)
    expect_error("poses_bounds.npy", "cam02: non-finite", open_dataset, root)


def test_non_rotation_pose(tmp_path):
    root = make_panoptic(tmp_path)
    meta = json.loads((root / "train_meta.json").read_text())
    meta["w2c"][0][1][0][0] = 2.0
    (root / "train_meta.json").write_text(json.dumps(meta))
    expect_error("train_meta.json", "not orthonormal", open_dataset, root)


def test_unknown_layout_and_bad_files(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    expect_error(tmp_path.name, "unknown layout", open_dataset, tmp_path)
    expect_error("nowhere", "does not exist", open_dataset, tmp_path / "nowhere")
    expect_error(tmp_path.name, "unknown format", open_dataset, tmp_path, format="vrml")
    root = make_panoptic(tmp_path / "p")
    (root / "train_meta.json").write_text("{not json")
    expect_error("train_meta.json", "not valid JSON", open_dataset, root)


def test_empty_frame_range_and_unknown_test_camera(tmp_path):
    root = make_n3dv(tmp_path)
    expect_error(tmp_path.name, "empty frame range", open_dataset, root, duration=0)
    expect_error(tmp_path.name, "empty frame range", open_dataset, root, start=5)
    expect_error(tmp_path.name, r"frames 2-3 of the range \[0, 4\) are not in the data", open_dataset, root,
                 duration=4)
    expect_error("poses_bounds.npy", "test camera.*cam07", open_dataset, root, test_cameras=["cam07"])


def test_miv_camera_without_yuv(tmp_path):
    entry = {"Name": "v00", "Position": [0, 0, 0], "Rotation": [0, 0, 0], "Projection": "Perspective",
             "Focal": [10, 10], "Principle_point": [8, 6], "Resolution": [16, 12]}
    (tmp_path / "seq.json").write_text(json.dumps({"cameras": [entry]}))
    expect_error("seq.json", "v00 has no YUV file", open_dataset, tmp_path)
    (tmp_path / "v00.yuv").write_bytes(b"\0" * 100)
    expect_error("v00.yuv", "not a whole number", open_dataset, tmp_path)


def _blender(root: Path, **lens) -> Path:
    """A two-camera Blender/NeRF transforms scene with `lens` keys (nerfstudio's camera_model, k1.., p1..)."""
    for split, name in (("train", "a"), ("test", "b")):
        _image(root / f"{name}.png")
        c2w = np.linalg.inv(_w2c(len(name)))
        frame = {"file_path": f"{name}.png", "transform_matrix": c2w.tolist(), "time": 0.0}
        meta = {"fl_x": 20.0, "fl_y": 20.0, "cx": 8.0, "cy": 6.0, "w": W, "h": H, **lens, "frames": [frame]}
        (root / f"transforms_{split}.json").write_text(json.dumps(meta))
    return root


def test_distorted_transforms_cameras_are_refused_not_read_as_pinholes(tmp_path):
    """nerfstudio and instant-ngp write the lens model into transforms files: reading distorted images as pinhole
    cameras trained them off by pixels toward their edges, silently."""
    assert open_dataset(_blender(tmp_path / "plain", camera_model="OPENCV", k1=0.0, p1=0.0)).format == "blender"
    expect_error("transforms_train.json", r"lens distortion \(k1=-0.25, p2=0.001\) is not modelled", open_dataset,
                 _blender(tmp_path / "k", camera_model="OPENCV", k1=-0.25, k2=0.0, p2=0.001))
    expect_error("transforms_train.json", "camera model OPENCV_FISHEYE: only pinhole cameras", open_dataset,
                 _blender(tmp_path / "fisheye", camera_model="OPENCV_FISHEYE"))
    expect_error("transforms_train.json", "camera model fisheye", open_dataset,
                 _blender(tmp_path / "ngp", is_fisheye=True))
    expect_error("transforms_train.json", "not a number", open_dataset, _blender(tmp_path / "text", k1="strong"))


def _blender_multiview(root: Path, test: set[tuple[str, int]]) -> Path:
    """Three cameras x two frames in transforms_{train,test}.json, (camera, frame) pairs in `test` in the test file."""
    frames: dict[str, list] = {"train": [], "test": []}
    for k, name in enumerate(("camA", "camB", "camC")):
        for t in range(2):
            _image(root / f"{name}_{t}.png")
            frame = {"file_path": f"{name}_{t}.png", "transform_matrix": np.linalg.inv(_w2c(k)).tolist(),
                     "time": t / 2, "camera": name, "frame_index": t}
            frames["test" if (name, t) in test else "train"].append(frame)
    for split, entries in frames.items():
        meta = {"fl_x": 20.0, "cx": 8.0, "cy": 6.0, "w": W, "h": H, "frames": entries}
        (root / f"transforms_{split}.json").write_text(json.dumps(meta))
    return root


def test_a_camera_in_both_blender_files_is_refused_not_held_out_whole(tmp_path):
    """Multi-view scenes hold out whole cameras: camA's training image (frame 0) was silently held out with its
    test image (frame 1)."""
    data = open_dataset(_blender_multiview(tmp_path / "ok", {("camC", 0), ("camC", 1)}))
    assert sorted({c.name for c in data.train}) == ["camA", "camB"] and {c.name for c in data.test} == {"camC"}
    expect_error("transforms_test.json", "camera.s. camA also in transforms_train.json", open_dataset,
                 _blender_multiview(tmp_path / "both", {("camA", 1), ("camC", 0), ("camC", 1)}))


def test_a_blender_frame_without_the_camera_the_others_name_is_refused_as_such(tmp_path):
    """One entry without 'camera' read the whole scene as monocular, and the error named another cause (a camera
    "appears twice")."""
    root = _blender_multiview(tmp_path, {("camC", 0), ("camC", 1)})
    meta = json.loads((root / "transforms_train.json").read_text())
    del meta["frames"][2]["camera"]
    (root / "transforms_train.json").write_text(json.dumps(meta))
    expect_error("transforms_train.json", "frame 'camB_0.png' names no camera while other frames do",
                 open_dataset, root)


@pytest.mark.parametrize("key, value, match", [
    ("fl_x", "abc", "a value cannot be read"), ("time", "abc", "time 'abc' is not a number"),
    ("time", float("inf"), "time inf is not a finite number"), ("frame_index", "x", "a value cannot be read")])
def test_unreadable_values_of_a_blender_frame_name_the_file(tmp_path, key, value, match):
    root = _blender_multiview(tmp_path, {("camC", 0), ("camC", 1)})
    meta = json.loads((root / "transforms_train.json").read_text())
    meta["frames"][0][key] = value
    (root / "transforms_train.json").write_text(json.dumps(meta))
    expect_error("transforms_train.json", match, open_dataset, root)
    meta["frames"][0] = "camA_0.png"
    (root / "transforms_train.json").write_text(json.dumps(meta))
    expect_error("transforms_train.json", r"frames\[0\] is str", open_dataset, root)


def test_malformed_metadata_values_name_the_file(tmp_path):
    """Each was a TypeError, KeyError, ZeroDivisionError or UnicodeDecodeError from inside a reader."""
    root = make_panoptic(tmp_path / "p")
    meta = json.loads((root / "train_meta.json").read_text())
    meta["k"] = 5
    (root / "train_meta.json").write_text(json.dumps(meta))
    expect_error("train_meta.json", "must be lists", open_dataset, root)

    root = make_panoptic(tmp_path / "p2")
    np.savez(root / "init_pt_cld.npz", points=np.zeros((5, 7)))
    expect_error("init_pt_cld.npz", "no 'data' array", open_dataset(root).data_points, 0)
    np.savez(root / "init_pt_cld.npz", data=np.zeros((5, 3)))
    expect_error("init_pt_cld.npz", r"'data' is \[5, 3\]", open_dataset(root).data_points, 0)

    root = make_n3dv(tmp_path / "n")
    rows = np.load(root / "poses_bounds.npy")
    rows[1, 4] = 0.0  # the height of camera 1 (column 4 of the 3x5 block's first row)
    np.save(root / "poses_bounds.npy", rows)
    expect_error("poses_bounds.npy", "camera cam01: height 0", open_dataset, root)

    (tmp_path / "t").mkdir()
    (tmp_path / "t" / "cameras_parameters.txt").write_bytes("header\n\xe9t\xe9\n".encode("latin-1"))
    expect_error("cameras_parameters.txt", "not a text file of numbers", open_dataset, tmp_path / "t")

    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "seq.json").write_text(json.dumps({"sequence": "not miv"}))
    expect_error("seq.json", "not an MIV sequence JSON", open_dataset, tmp_path / "m" / "seq.json", format="miv")


def test_a_metadata_file_is_detected_as_its_folder_is(tmp_path):
    """The readers take a format's own metadata file; detection refused it ('unknown layout')."""
    root = make_n3dv(tmp_path / "n")
    assert open_dataset(root / "poses_bounds.npy").format == "n3dv"
    assert open_dataset(make_panoptic(tmp_path / "p") / "train_meta.json").format == "panoptic"


def _miv(root: Path, names=("v00", "v01", "v02", "v06"), frames: int = 2, **sequence) -> Path:
    """An MIV sequence: seq.json and one 10-bit 16x12 texture of `frames` frames per view in `names`."""
    from stgc.data.yuv import write_yuv420

    root.mkdir(parents=True, exist_ok=True)
    entries = []
    for i, name in enumerate(names):
        entries.append({"Name": name, "Position": [0, 0.1 * i, 0], "Rotation": [0, 0, 0], "Projection": "Perspective",
                        "Focal": [10, 10], "Principle_point": [8, 6], "Resolution": [W, H], "BitDepthColor": 10})
        write_yuv420(root / f"{name}_texture_{W}x{H}_yuv420p10le.yuv", [np.full((H, W, 3), 100, np.uint8)] * frames)
    (root / "seq.json").write_text(json.dumps({"Fps": 30, "Frames_number": frames, "cameras": entries, **sequence}))
    return root


def test_an_empty_miv_texture_is_refused_not_dropped_with_its_view(tmp_path):
    """A 0-byte texture (an interrupted copy) counted 0 frames: its view vanished from the data without a word, and
    where it was v06 the default test view moved to v00, a training view."""
    root = _miv(tmp_path)
    assert open_dataset(root).test_views == ["v06"]
    (root / f"v06_texture_{W}x{H}_yuv420p10le.yuv").write_bytes(b"")
    expect_error("v06_texture", "holds no frames", open_dataset, root)
    # A texture named without its bit depth and declared without one: the same refusal, not a size puzzle.
    plain = _miv(tmp_path / "plain", names=("v00", "v01"))
    sequence = json.loads((plain / "seq.json").read_text())
    for entry in sequence["cameras"]:
        del entry["BitDepthColor"]
        (plain / f"{entry['Name']}_texture_{W}x{H}_yuv420p10le.yuv").rename(plain / f"{entry['Name']}.yuv")
    (plain / "seq.json").write_text(json.dumps(sequence))
    assert open_dataset(plain).train_views == ["v01"]
    (plain / "v01.yuv").write_bytes(b"")
    expect_error("v01.yuv", "holds no frames", open_dataset, plain)


def test_a_camera_in_both_panoptic_files_is_refused_not_held_out_whole(tmp_path):
    """Camera 1 in train_meta.json and test_meta.json was held out whole (its training images too) and listed twice
    among the test views of every frame."""
    root = make_panoptic(tmp_path)
    test = json.loads((root / "test_meta.json").read_text())
    train = json.loads((root / "train_meta.json").read_text())
    for key in ("k", "w2c", "fn", "cam_id"):
        for t in range(len(test[key])):
            test[key][t].append(train[key][t][0])
    (root / "test_meta.json").write_text(json.dumps(test))
    expect_error("test_meta.json", "camera.s. 1 also in train_meta.json", open_dataset, root)


def test_a_view_listed_twice_for_one_frame_is_refused_in_every_format(tmp_path):
    """Only the multi-view Blender reader refused a (view, frame) listed twice; elsewhere the view trained twice on
    that frame, or was tested twice, and both copies shared one cache entry."""
    root = make_panoptic(tmp_path / "p")
    train = json.loads((root / "train_meta.json").read_text())
    for key in ("k", "w2c", "fn", "cam_id"):
        train[key][0].append(train[key][0][0])
    (root / "train_meta.json").write_text(json.dumps(train))
    expect_error("train_meta.json", "camera 1 frame 0 appears twice", open_dataset, root)

    root = _miv(tmp_path / "m")
    sequence = json.loads((root / "seq.json").read_text())
    sequence["cameras"].append(dict(sequence["cameras"][1]))
    (root / "seq.json").write_text(json.dumps(sequence))
    expect_error("seq.json", "camera v01 frame 0 appears twice", open_dataset, root)

    root = _blender_multiview(tmp_path / "b", {("camC", 0), ("camC", 1)})
    meta = json.loads((root / "transforms_train.json").read_text())
    meta["frames"].append(meta["frames"][0])
    (root / "transforms_train.json").write_text(json.dumps(meta))
    expect_error("transforms_train.json", "camera camA frame 0 appears twice", open_dataset, root)


def _edit_json(path: Path, edit) -> None:
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


@pytest.mark.parametrize("edit, file, match", [
    (lambda m: m.update(fps="30fps"), "transforms_train.json", "fps '30fps' is not a positive number"),
    (lambda m: m.update(fps=-30), "transforms_train.json", "fps -30 is not a positive number"),
    (lambda m: m.update(fps=float("inf")), "transforms_train.json", "fps inf is not a positive number"),
    (lambda m: m.update(fps=[30]), "transforms_train.json", r"fps \[30\] is not a positive number"),
], ids=["fps-text", "fps-negative", "fps-infinite", "fps-list"])
def test_bad_blender_metadata_values_name_the_file(tmp_path, edit, file, match):
    """fps '30fps' was a ValueError traceback; a negative or infinite fps was accepted, and failed (or misled) later
    where a duration is computed from it."""
    root = _blender_multiview(tmp_path, {("camC", 0), ("camC", 1)})
    _edit_json(root / file, edit)
    expect_error(file, match, open_dataset, root)


def test_a_metadata_file_that_is_not_a_json_object_names_the_file(tmp_path):
    """A top-level list or string was an AttributeError traceback from the reader's first `.get`."""
    root = _blender_multiview(tmp_path / "b", {("camC", 0), ("camC", 1)})
    (root / "transforms_test.json").write_text("[]")
    expect_error("transforms_test.json", "top level is not a JSON object", open_dataset, root)
    root = make_panoptic(tmp_path / "p")
    (root / "train_meta.json").write_text('"train"')
    expect_error("train_meta.json", "top level is not a JSON object", open_dataset, root)


@pytest.mark.parametrize("edit, match", [
    (lambda s: s.update(Fps="abc"), "Fps 'abc' is not a positive number"),
    (lambda s: s.update(Fps=[[1, 2]]), "Fps .* is not a positive number"),
    (lambda s: s.update(Fps=0), "Fps 0 is not a positive number"),
    (lambda s: s["cameras"][1].update(Position=[1, 2]), "camera v01: Position and Rotation must be 3 numbers"),
    (lambda s: s["cameras"][1].update(Rotation=[]), "camera v01: Position and Rotation must be 3 numbers"),
    (lambda s: s["cameras"][1].update(Resolution=[W, H, 3]), "camera v01: Resolution .* is not a size"),
    (lambda s: s["cameras"][1].update(BitDepthColor="abc"), "camera v01: BitDepthColor 'abc' is not a bit depth"),
    (lambda s: s["cameras"][1].update(BitDepthColor=-3), "camera v01: BitDepthColor -3 is not a bit depth"),
    (lambda s: s.update(sourceCameraNames=-3), "sourceCameraNames -3 is not a list of camera names"),
    (lambda s: s.update(sourceCameraNames=["v00", "v09"]), "sourceCameraNames lists v09, which no camera entry"),
    (lambda s: s["cameras"].__setitem__(1, "x"), r"cameras\[1\] is a string, not an object"),
    (lambda s: s.update(Frames_number="abc"), "Frames_number 'abc' is not a positive whole number"),
], ids=["fps-text", "fps-list", "fps-zero", "position-2", "rotation-empty", "resolution-3", "bit-depth-text",
        "bit-depth-negative", "source-names-number", "source-names-unknown", "camera-string", "frames-text"])
def test_bad_miv_metadata_values_name_the_file(tmp_path, edit, match):
    """Each was a raw ValueError, TypeError or AttributeError from inside the reader, or (a negative bit depth, an
    unknown source camera, a text frame count) accepted: a warning 'using -3', a view silently left out."""
    root = _miv(tmp_path, names=("v00", "v01"))
    _edit_json(root / "seq.json", edit)
    expect_error("seq.json", match, open_dataset, root)


def test_poses_bounds_of_text_values_name_the_file(tmp_path):
    """A poses_bounds.npy of strings was a TypeError from np.isfinite (and a complex one was read, its imaginary
    part dropped with a ComplexWarning)."""
    root = make_n3dv(tmp_path)
    rows = np.load(root / "poses_bounds.npy")
    np.save(root / "poses_bounds.npy", rows.astype(str))
    expect_error("poses_bounds.npy", "holds <U.* values, not real numbers", open_dataset, root)
    np.save(root / "poses_bounds.npy", rows.astype(complex))
    expect_error("poses_bounds.npy", "holds complex128 values, not real numbers", open_dataset, root)


def test_empty_or_truncated_numpy_files_name_the_file(tmp_path):
    """np.load raises EOFError on an empty file and BadZipFile on a truncated .npz: both were tracebacks that named
    no file."""
    root = make_n3dv(tmp_path / "n")
    (root / "poses_bounds.npy").write_bytes(b"")
    expect_error("poses_bounds.npy", "unreadable", open_dataset, root)

    root = make_panoptic(tmp_path / "p")
    np.savez(root / "init_pt_cld.npz", data=np.zeros((50, 7)))
    whole = (root / "init_pt_cld.npz").read_bytes()
    (root / "init_pt_cld.npz").write_bytes(whole[: len(whole) // 2])
    expect_error("init_pt_cld.npz", "unreadable point cloud", open_dataset(root).data_points, 0)
    (root / "init_pt_cld.npz").write_bytes(b"")
    expect_error("init_pt_cld.npz", "unreadable point cloud", open_dataset(root).data_points, 0)


@pytest.mark.parametrize("time", [float("inf"), float("nan")])
def test_a_non_finite_time_of_a_monocular_scene_is_refused_not_spread_over_every_camera(tmp_path, time):
    """JSON's Infinity and NaN parse as floats: one such time made every camera's time NaN (the frames are placed on
    the axis by their times), with no error."""
    from scenes import write_dnerf_scene

    root = write_dnerf_scene(tmp_path)
    _edit_json(root / "transforms_test.json", lambda m: m["frames"][1].update(time=time))
    expect_error("transforms_test.json", f"frame './test/r_001': time {time} is not a finite number", open_dataset,
                 root)


def _transposed(matrix: list) -> list:
    return np.array(matrix).T.tolist()


def test_matrices_written_transposed_are_refused_not_read_as_other_cameras(tmp_path):
    """A transposed rigid pose still has an orthonormal rotation: its translation went to the bottom row, which
    nothing read, so every camera sat at the origin; a transposed K put the principal point at (0, 0)."""
    root = make_panoptic(tmp_path / "w2c")
    _edit_json(root / "train_meta.json", lambda m: m["w2c"][1].__setitem__(2, _transposed(m["w2c"][1][2])))
    expect_error("train_meta.json", r"camera 3 frame 1: pose w2c bottom row is \[0.9, 0, 4, 1\], not \[0, 0, 0, 1\] "
                 r"\(written transposed\?", open_dataset, root)

    root = make_panoptic(tmp_path / "k")
    _edit_json(root / "test_meta.json", lambda m: m["k"][0].__setitem__(0, _transposed(m["k"][0][0])))
    expect_error("test_meta.json", r"camera 0 frame 0: intrinsics K bottom row is \[7.5, 5.5, 1\], not \[0, 0, 1\] "
                 r"\(written transposed\?", open_dataset, root)

    root = make_panoptic(tmp_path / "k10")
    _edit_json(root / "train_meta.json", lambda m: m["k"][0][0][1].__setitem__(0, 3.0))
    expect_error("train_meta.json", r"camera 1 frame 0: intrinsics K\[1, 0\] is 3, not 0", open_dataset, root)

    # The renderer ignores skew (fx, fy, cx, cy only): a skewed K would be drawn as another camera.
    root = make_panoptic(tmp_path / "skew")
    _edit_json(root / "train_meta.json", lambda m: m["k"][0][0][0].__setitem__(1, 0.5))
    expect_error("train_meta.json", r"camera 1 frame 0: intrinsics K has skew K\[0, 1\] = 0.5", open_dataset, root)

    # Blender's c2w is converted from its top three rows alone: checked before the conversion.
    root = _blender_multiview(tmp_path / "c2w", {("camC", 0), ("camC", 1)})
    _edit_json(root / "transforms_train.json",
               lambda m: m["frames"][2].update(transform_matrix=_transposed(m["frames"][2]["transform_matrix"])))
    expect_error("transforms_train.json", r"camera camB frame 0: transform_matrix bottom row is \[-0.3, 0, -4, 1\], "
                 r"not \[0, 0, 0, 1\] \(written transposed\?", open_dataset, root)


def test_an_image_used_by_two_views_is_refused_naming_the_file_and_both_views(tmp_path):
    """Only (view, frame) pairs were checked: a held-out view whose file_path was a training view's image (a slip
    copying metadata) was accepted, and the test scored a training image."""
    from stgc.data.dataset import SourceScene, VideoFrame, assemble

    for k, file_path in enumerate(("camA_0.png", "./camA_0.png", "camC/../camA_0.png")):
        root = _blender_multiview(tmp_path / str(k), {("camC", 0), ("camC", 1)})
        (root / "camC").mkdir()
        _edit_json(root / "transforms_test.json", lambda m: m["frames"][0].update(file_path=file_path))
        expect_error("camA_0.png", "this file is the image of two views: camera camA frame 0 and camera camC frame 0",
                     open_dataset, root)

    # A frame of a video (or of a YUV file) is one image too; another frame of the same file is another image.
    video = tmp_path / "cam.mp4"
    K, w2c = np.array([[20.0, 0, 8], [0, 20, 6], [0, 0, 1]]), _w2c(0)
    from stgc.data.cameras import Camera

    def scene(second_index: int) -> SourceScene:
        cameras = [Camera("a", 0, 0.0, K, w2c, W, H, VideoFrame(video, 0)),
                   Camera("b", 0, 0.0, K, _w2c(1), W, H, VideoFrame(video, second_index))]
        return SourceScene(name="v", format="n3dv", root=tmp_path, cameras=cameras, default_test=["a"],
                           meta_file=tmp_path / "poses_bounds.npy")

    assert assemble(scene(1), check_images=False).test_views == ["a"]
    expect_error("cam.mp4", "frame 0 of this file is the image of two views: camera a frame 0 and camera b frame 0",
                 assemble, scene(0), check_images=False)


def test_panoptic_camera_folders_that_no_metadata_names_are_refused(tmp_path):
    """Only folders some camera used were scanned for extra images: without test_meta.json (optional) the held-out
    cameras' folders were dropped without a word, and the dataset had no test views."""
    root = make_panoptic(tmp_path / "no_test")
    (root / "test_meta.json").unlink()
    expect_error("ims", r"camera folder.s. 0 hold images that no camera in train_meta.json refers to; "
                 "test_meta.json is missing", open_dataset, root)
    root = make_panoptic(tmp_path / "extra_camera")
    for t in range(2):
        _image(root / "ims" / f"12/{t:06d}.jpg")
    (root / "ims" / "notes").mkdir()  # a folder without images is not a camera's
    error = expect_error("ims", r"camera folder.s. 12 hold images that no camera in train_meta.json or "
                         "test_meta.json refers to$", open_dataset, root)
    assert "missing" not in str(error)


def _stg_colmap(root: Path, other_world: tuple[np.ndarray, float, np.ndarray] | None = None,
                image_names: tuple[str, ...] = ("cam00.png", "cam01.png", "cam02.png")) -> Path:
    """Two frames of three cameras in STG's layout (colmap_<t>/images, colmap_<t>/sparse/0 with points3D). Frame 1's
    model names `image_names` and, with `other_world` = (S, s, T), lies in the world x' = s S x + T (its own SfM
    run), cameras and points alike."""
    from stgc.data.cameras import rotmat_to_qvec
    from stgc.data.colmap_io import ColmapCamera, ColmapImage, ColmapModel, write_model

    S, s, T = other_world or (np.eye(3), 1.0, np.zeros(3))
    for frame in (0, 1):
        model = ColmapModel()
        for k, name in enumerate(("cam00.png", "cam01.png", "cam02.png")):
            _image(root / f"colmap_{frame}" / "images" / name)
            w2c = _w2c(k)
            R, t = w2c[:3, :3], w2c[:3, 3]
            if frame == 1:
                R, t = R @ S.T, s * t - R @ S.T @ T
            model.cameras[k + 1] = ColmapCamera(k + 1, "PINHOLE", W, H, np.array([20.0, 20.0, 8.0, 6.0]))
            model.images[k + 1] = ColmapImage(k + 1, rotmat_to_qvec(R), t, k + 1,
                                              name if frame == 0 else image_names[k])
        xyz = np.random.default_rng(frame).normal(0, 0.3, (20, 3))
        model.xyz = xyz if frame == 0 else s * xyz @ S.T + T
        model.rgb, model.error = np.full((20, 3), 128, np.uint8), np.zeros(20)
        write_model(root / f"colmap_{frame}" / "sparse" / "0", model, "bin")
    return root


def test_stg_colmap_frames_whose_models_lie_in_other_worlds_are_refused(tmp_path):
    """Every frame's cameras come from the first frame's model, each frame's points from its own: a frame
    reconstructed in another world frame put its points where no camera looks, silently."""
    from stgc.data.cameras import euler_zyx_deg

    data = open_dataset(_stg_colmap(tmp_path / "same"))
    assert [len(data.data_points(f)[0]) for f in data.frames] == [20, 20]
    # Rounding (a text model, a float32 copy) is no other world.
    data = open_dataset(_stg_colmap(tmp_path / "rounded", (euler_zyx_deg(1e-5, 0, 0), 1 + 1e-7, np.full(3, 1e-7))))
    assert len(data.data_points(1)[0]) == 20

    data = open_dataset(_stg_colmap(tmp_path / "other", (euler_zyx_deg(40, 10, -20), 2.5, np.array([5.0, -3, 1]))))
    assert len(data.data_points(0)[0]) == 20  # the first frame's model is the cameras' own
    expect_error("colmap_1/sparse/0", r"image cam00.png has another pose here than in .*colmap_0/sparse/0 \(its "
                 r"centre moved by .* of the cameras' spread, its rotation by 47.* degrees\)", data.data_points, 1)
    # A small shift alone (2 % of the cameras' 0.3-unit spread) is already another world.
    data = open_dataset(_stg_colmap(tmp_path / "shifted", (np.eye(3), 1.0, np.array([0.006, 0, 0]))))
    expect_error("colmap_1/sparse/0", "centre moved by 0.02 of the cameras' spread", data.data_points, 1)

    data = open_dataset(_stg_colmap(tmp_path / "renamed", image_names=("a.png", "b.png", "c.png")))
    expect_error("colmap_1/sparse/0", "names none of the images of", data.data_points, 1)


def test_a_missing_panoptic_camera_folder_names_the_folder_and_the_metadata_that_refers_to_it(tmp_path):
    """A camera's image folder (ims/<cam>) that is missing raised a bare FileNotFoundError ("[Errno 2] ... ims/0")
    while the reader looked for extra images in it; a file in its place, NotADirectoryError."""
    import shutil

    root = make_panoptic(tmp_path / "test_cam")
    shutil.rmtree(root / "ims" / "0")
    expect_error("ims/0", r"camera image folder is missing: test_meta.json refers to images in it \(000000.jpg",
                 open_dataset, root)
    root = make_panoptic(tmp_path / "train_cam")
    shutil.rmtree(root / "ims" / "2")
    (root / "ims" / "2").write_text("not a folder")
    expect_error("ims/2", r"camera image folder is not a folder: train_meta.json refers to images in it",
                 open_dataset, root)
