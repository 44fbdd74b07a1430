"""Layouts built in the test from blender_toys frames are read back with the same cameras and images:
MPEG immersive video (JSON + YUV 4:2:0), N3DV mp4, STG COLMAP (text and binary), Technicolor."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from stgc.data import open_dataset
from stgc.data.cameras import colmap_to_w2c, rotmat_to_qvec, w2c_to_omaf
from stgc.data.colmap_io import (
    ColmapCamera,
    ColmapImage,
    ColmapModel,
    read_model,
    write_model,
)
from stgc.data.yuv import detect_bit_depth, write_yuv420
from stgc.errors import DataError

VIEWS = ["cam00", "cam03", "cam06", "cam09"]
FRAMES = [0, 1, 2]


@pytest.fixture(scope="module")
def toys(blender_toys):
    return open_dataset(blender_toys, duration=len(FRAMES))


def _cams(toys):
    return {(c.name, c.frame): c for c in toys.cameras if c.name in VIEWS}


def _same_cameras(a, b, tol=1e-9):
    assert (a.width, a.height) == (b.width, b.height)
    assert np.abs(a.K - b.K).max() < tol, (a.K, b.K)
    assert np.abs(a.w2c - b.w2c).max() < tol, (a.w2c, b.w2c)


def _blocky(image: np.ndarray) -> np.ndarray:
    """Colour constant over 2x2 blocks, so that 4:2:0 chroma subsampling loses nothing."""
    h, w = image.shape[:2]
    mean = image.reshape(h // 2, 2, w // 2, 2, 3).mean(axis=(1, 3)).round().astype(np.uint8)
    return np.repeat(np.repeat(mean, 2, 0), 2, 1)


def _write_miv(toys, folder: Path, bit_depth: int, named: bool) -> dict:
    cams = _cams(toys)
    entries, originals = [], {}
    for i, view in enumerate(VIEWS):
        cam = cams[(view, 0)]
        position, ypr = w2c_to_omaf(cam.w2c)
        name = f"v{i:02d}"
        entries.append({"Name": name, "Position": position.tolist(), "Rotation": ypr.tolist(),
                        "Projection": "Perspective", "Focal": [cam.K[0, 0], cam.K[1, 1]],
                        "Principle_point": [cam.K[0, 2], cam.K[1, 2]], "Resolution": [cam.width, cam.height],
                        "Depth_range": [0.5, 20.0], "BitDepthColor": bit_depth})
        frames = [_blocky(toys.load_image(cams[(view, f)])) for f in FRAMES]
        originals[name] = (cam, frames)
        file_name = f"{name}_texture_160x120_yuv420p10le.yuv" if named else f"{name}.yuv"
        write_yuv420(folder / file_name, frames, bit_depth=bit_depth)
    if not named:
        for e in entries:
            del e["BitDepthColor"]  # force detection from size and content
    (folder / "Toys.json").write_text(json.dumps({"Version": "4.0", "Content_name": "Toys", "Fps": 32,
                                                  "Frames_number": len(FRAMES), "cameras": entries}))
    return originals


@pytest.mark.parametrize("bit_depth,named", [(10, True), (8, False)])
def test_miv_round_trip(toys, tmp_path, bit_depth, named):
    originals = _write_miv(toys, tmp_path, bit_depth, named)
    data = open_dataset(tmp_path, test_cameras=["v01"])
    assert data.format == "miv" and data.name == "Toys" and data.fps == 32
    assert data.frames == FRAMES and data.test_views == ["v01"]
    for name, (cam, frames) in originals.items():
        for f in FRAMES:
            got = (data.train_at(f) + data.test_at(f))
            got = next(c for c in got if c.name == name)
            _same_cameras(got, cam, tol=1e-6)
            diff = np.abs(data.load_image(got).astype(int) - frames[f].astype(int)).max()
            assert diff <= (1 if bit_depth == 10 else 3), (name, f, diff)
    if not named:
        assert detect_bit_depth(tmp_path / "v00.yuv", 160, 120) == 8


def test_a_declared_bit_depth_wins_over_a_name_that_reads_otherwise(tmp_path, caplog):
    path = tmp_path / "A_10_texture.yuv"  # the name's pattern reads "_10_" as 10-bit
    write_yuv420(path, [np.zeros((8, 8, 3), np.uint8)], bit_depth=8)
    assert detect_bit_depth(path, 8, 8) == 10
    with caplog.at_level("WARNING"):
        assert detect_bit_depth(path, 8, 8, declared=8) == 8
    assert "declares BitDepthColor 8" in caplog.text


def test_yuv_luma_survives_on_real_edges(toys, tmp_path):
    """Without 2x2-constant colour, chroma is lossy at colour edges but luma is kept to 10-bit precision."""
    from stgc.data.yuv import KB, KG, KR, read_frame

    image = toys.load_image(toys.test_at(0)[0])
    write_yuv420(tmp_path / "v00_texture_160x120_yuv420p10le.yuv", [image])
    back = read_frame(tmp_path / "v00_texture_160x120_yuv420p10le.yuv", 160, 120, 0, 10)
    luma = lambda x: x.astype(np.float64) @ np.array([KR, KG, KB])
    assert np.abs(luma(back) - luma(image)).max() <= 1.0


def test_miv_default_test_views_follow_the_paper(toys, tmp_path):
    originals = _write_miv(toys, tmp_path, 10, True)
    text = (tmp_path / "Toys.json").read_text()
    (tmp_path / "Toys.json").write_text(text.replace('"v02"', '"v06"').replace('"v03"', '"v08"'))
    for old, new in (("v02", "v06"), ("v03", "v08")):
        (tmp_path / f"{old}_texture_160x120_yuv420p10le.yuv").rename(tmp_path / f"{new}_texture_160x120_yuv420p10le.yuv")
    assert open_dataset(tmp_path / "Toys.json").test_views == ["v06", "v08"]
    assert originals


def test_n3dv_mp4_round_trip(toys, blender_toys, tmp_path):
    import imageio.v2 as imageio

    cams = _cams(toys)
    rows = np.load(blender_toys / "poses_bounds.npy")
    np.save(tmp_path / "poses_bounds.npy", rows[[int(v[3:]) for v in VIEWS]])
    originals = {}
    for view in VIEWS:
        frames = [toys.load_image(cams[(view, f)]) for f in FRAMES]
        originals[view] = frames
        with imageio.get_writer(tmp_path / f"{view}.mp4", fps=30, codec="libx264", macro_block_size=8,
                                ffmpeg_params=["-crf", "10"], ffmpeg_log_level="error") as writer:
            for frame in frames:
                writer.append_data(frame)
    data = open_dataset(tmp_path)
    assert data.format == "n3dv" and data.test_views == ["cam00"] and data.fps == pytest.approx(30)
    assert data.view_dependent_colour and not data.synthetic  # a real rig, STG's own: the decoder sees directions
    assert data.frames == FRAMES
    for cam in data.cameras:
        _same_cameras(cam, cams[(cam.name, cam.frame)], tol=1e-5)
        decoded = data.load_image(cam).astype(float)
        errors = [np.abs(decoded - o.astype(float)).mean() for o in originals[cam.name]]
        # Lossy codec (H.264 crf 10, 4:2:0 chroma): mean error under 3/255, and each decoded frame is closest
        # to its own original (frame order and indexing are right).
        assert errors[cam.frame] < 3.0, errors
        assert int(np.argmin(errors)) == cam.frame


def _write_stg_colmap(toys, root, ext, views=VIEWS):
    """STG's layout (colmap_<t>/images + sparse/0) of `views` of toys; returns {frame: (xyz, rgb)} written."""
    cams = {(c.name, c.frame): c for c in toys.cameras if c.name in views}
    model = ColmapModel()
    for i, view in enumerate(views, start=1):
        cam = cams[(view, 0)]
        K = cam.K
        model.cameras[i] = ColmapCamera(i, "PINHOLE", cam.width, cam.height, np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]]))
        model.images[i] = ColmapImage(i, rotmat_to_qvec(cam.w2c[:3, :3]), cam.w2c[:3, 3].copy(), i, f"{view}.png")
    points = {}
    for f in FRAMES:
        folder = root / f"colmap_{f}"
        (folder / "images").mkdir(parents=True)
        for view in views:
            shutil.copy(cams[(view, f)].image, folder / "images" / f"{view}.png")
        xyz, rgb = toys.data_points(f)
        model.xyz = xyz[:100].astype(np.float64)
        model.rgb = (rgb[:100] * 255).round().astype(np.uint8)
        model.error = np.zeros(100)
        points[f] = (model.xyz.copy(), model.rgb.copy())
        write_model(folder / "sparse" / "0", model, ext)
    return points


@pytest.mark.parametrize("ext", ["txt", "bin"])
def test_stg_colmap_round_trip(toys, tmp_path, ext, caplog):
    cams = _cams(toys)
    points = _write_stg_colmap(toys, tmp_path, ext)
    data = open_dataset(tmp_path)
    assert data.format == "stg-colmap" and data.test_views == ["cam00"] and data.frames == FRAMES
    for cam in data.cameras:
        _same_cameras(cam, cams[(cam.name, cam.frame)], tol=1e-6)  # float32 source rotations re-orthonormalised by the quaternion
        assert np.array_equal(data.load_image(cam), toys.load_image(cams[(cam.name, cam.frame)]))
    for f in FRAMES:
        xyz, rgb = data.data_points(f)
        assert np.allclose(xyz, points[f][0], atol=1e-6) and np.allclose(rgb * 255, points[f][1])
    # STG passes one colmap_<t> folder: that sets the default start frame.
    assert open_dataset(tmp_path / "colmap_1").frames == [1, 2]
    # A frame whose points3D is missing starts without points of its own: said, not silent.
    from stgc.data.points import initial_points

    (tmp_path / f"colmap_{FRAMES[-1]}" / "sparse" / "0" / f"points3D.{ext}").unlink()
    with caplog.at_level("WARNING"):
        cloud = initial_points(open_dataset(tmp_path), source="data")
    assert f"frames {FRAMES[-1]} ship no points" in caplog.text and len(cloud) == 100 * (len(FRAMES) - 1)
    # Without a points3D anywhere it ships no points: init_source=auto triangulates instead of failing on "data".
    for f in FRAMES[:-1]:
        (tmp_path / f"colmap_{f}" / "sparse" / "0" / f"points3D.{ext}").unlink()
    assert not open_dataset(tmp_path).has_points


def test_stg_colmap_holds_out_cam10_of_a_prepared_technicolor_scene(toys, tmp_path):
    # STG's pre_technicolor.py writes colmap_<t> beside the source's cameras_parameters.txt; STG holds out cam10 there.
    _write_stg_colmap(toys, tmp_path, "txt", views=[*VIEWS, "cam10"])
    assert open_dataset(tmp_path).test_views == ["cam00"]  # Neural 3D Video's
    (tmp_path / "cameras_parameters.txt").write_text("header\n")
    data = open_dataset(tmp_path)
    assert data.format == "stg-colmap" and data.test_views == ["cam10"]


@pytest.mark.parametrize("ext", ["txt", "bin"])
def test_colmap_files_agree_with_pycolmap(tmp_path, ext):
    """Our writer's files read by pycolmap, and pycolmap's files read by our reader, give the same model."""
    pycolmap = pytest.importorskip("pycolmap")
    rng = np.random.default_rng(0)
    model = ColmapModel()
    model.cameras[1] = ColmapCamera(1, "PINHOLE", 160, 120, np.array([100.0, 101.0, 80.0, 60.0]))
    model.cameras[2] = ColmapCamera(2, "SIMPLE_PINHOLE", 320, 240, np.array([200.0, 160.0, 120.0]))
    for image_id, cam_id in ((3, 1), (7, 2)):
        q = rng.normal(size=4)
        q = q / np.linalg.norm(q) * np.sign(q[0])
        model.images[image_id] = ColmapImage(image_id, q, rng.normal(size=3), cam_id, f"im{image_id}.png")
    model.xyz = rng.normal(size=(20, 3))
    model.rgb = rng.integers(0, 256, size=(20, 3)).astype(np.uint8)
    model.error = np.zeros(20)
    write_model(tmp_path / "ours", model, ext)
    rec = pycolmap.Reconstruction(str(tmp_path / "ours"))
    for image_id, im in model.images.items():
        expected = colmap_to_w2c(im.qvec, im.tvec)[:3]
        assert np.allclose(rec.images[image_id].cam_from_world().matrix(), expected, atol=1e-12)
    assert np.allclose(rec.cameras[2].params, model.cameras[2].params)
    assert np.allclose(sorted(p.xyz[0] for p in rec.points3D.values()), sorted(model.xyz[:, 0]))
    out = tmp_path / "theirs"
    out.mkdir()
    rec.write_binary(str(out)) if ext == "bin" else rec.write_text(str(out))
    back = read_model(out)
    for image_id, im in model.images.items():
        assert back.images[image_id].name == im.name
        assert np.allclose(back.images[image_id].tvec, im.tvec)
        assert np.allclose(colmap_to_w2c(back.images[image_id].qvec, back.images[image_id].tvec),
                           colmap_to_w2c(im.qvec, im.tvec), atol=1e-12)
    assert back.cameras[2].model == "SIMPLE_PINHOLE" and np.allclose(back.cameras[1].params, model.cameras[1].params)
    assert np.allclose(np.sort(back.xyz[:, 0]), np.sort(model.xyz[:, 0]))


def test_technicolor_round_trip(toys, blender_toys, tmp_path):
    full = open_dataset(blender_toys, duration=2)
    lines = ["header f cx cy a b qw qx qy qz tx ty tz"]
    names = [f"cam{i:02d}" for i in range(11)]
    for i, view in enumerate(names):
        cam = next(c for c in full.cameras if c.name == view and c.frame == 0)
        q = rotmat_to_qvec(cam.w2c[:3, :3])
        values = [cam.K[0, 0], cam.K[0, 2], cam.K[1, 2], 1.0, 0.0, *q, *cam.w2c[:3, 3]]
        lines.append(" ".join(repr(float(v)) for v in values))
        for f in (0, 1):
            src = next(c for c in full.cameras if c.name == view and c.frame == f).image
            shutil.copy(src, tmp_path / f"Toys_undist_{f + 151:05d}_{i:02d}.png")
    (tmp_path / "cameras_parameters.txt").write_text("\n".join(lines) + "\n")
    data = open_dataset(tmp_path)
    assert data.format == "technicolor" and data.test_views == ["cam10"] and data.frames == [151, 152]
    assert data.view_dependent_colour and not data.synthetic
    assert data.time_of(152) == pytest.approx(0.5)
    for cam in data.cameras:
        ref = next(c for c in full.cameras if c.name == cam.name and c.frame == cam.frame - 151)
        _same_cameras(cam, ref, tol=1e-6)
    # Parameters of images twice the size (the file states none): refused, not read with K unscaled.
    doubled = [lines[0]] + [" ".join(repr(float(v) * (2 if k < 3 else 1)) for k, v in enumerate(line.split()))
                            for line in lines[1:]]
    (tmp_path / "cameras_parameters.txt").write_text("\n".join(doubled) + "\n")
    with pytest.raises(DataError, match=r"line 2 \(camera cam00\): principal point .* far from the middle of its "
                                         r"\d+x\d+ images \(Toys_undist_00151_00.png\)") as info:
        open_dataset(tmp_path)
    assert info.value.path == tmp_path / "cameras_parameters.txt"


def test_dnerf_monocular(tmp_path):
    """D-NeRF: camera_angle_x only, file_path without extension, RGBA images, one view per image."""
    from scenes import write_dnerf_scene

    from stgc.data.cameras import fov_to_focal

    data = open_dataset(write_dnerf_scene(tmp_path), background="white")
    assert data.format == "blender" and data.frames == [0, 1, 2, 3, 4] and data.duration == 5
    assert [c.name for c in data.test] == ["test_r_000", "test_r_001"]
    assert [c.frame for c in data.test] == [1, 3]  # ranks of the distinct times 0, .25, .5, .75, 1
    cam = data.train_at(2)[0]
    assert cam.name == "train_r_001" and cam.w2c[2, 3] == pytest.approx(3.5)
    assert cam.K[0, 0] == pytest.approx(fov_to_focal(0.8, 10)) and cam.K[0, 2] == 5 and cam.K[1, 2] == 4
    image = data.load_image(cam)
    assert (image[:, :5] == [200, 100, 50]).all() and (image[:, 5:] == 255).all()


def test_inspect_states_the_time_rule_the_dataset_applies(tmp_path):
    """Where a monocular scene's frames are ranks of unevenly spaced times, time follows the JSON's time values
    (SourceScene.frame_positions); inspect stated t = (frame - start) / duration there too."""
    from scenes import write_dnerf_scene

    from stgc.data import inspect_text

    def frames_row(root):
        text = " ".join(inspect_text(root).replace("│", " ").split())  # the table wraps long rows
        return text[text.index(" frames "):text.index(" cameras ")]

    root = write_dnerf_scene(tmp_path / "uneven", {"train": [0.0, 0.1, 1.0], "test": [0.5]})
    assert [round(t, 4) for t in open_dataset(root).times] == [0.0, 0.075, 0.375, 0.75]
    row = frames_row(root)
    assert "t from the transforms' time values" in row and "t = 0..0.75" in row and "(frame -" not in row
    evenly = write_dnerf_scene(tmp_path / "even")  # times 0, 0.25, .., 1: the ranks are the positions
    assert "t = (frame - 0) / 5" in frames_row(evenly)


def test_images_txt_reads_pose_lines_with_and_without_their_keypoint_lines(tmp_path):
    from stgc.data.colmap_io import _read_images_txt

    pose = "{} 1 0 0 0 0.{} 0 0 1 cam{:02d}.png"
    keypoints = "10.5 20.5 -1 30.0 40.0 7 1.0 2.0 -1 3.0 4.0 5"  # all numbers, 12 tokens
    cases = {
        "with keypoint lines": [pose.format(i, i, i) + "\n" + keypoints for i in range(1, 5)],
        "with empty keypoint lines": [pose.format(i, i, i) + "\n" for i in range(1, 5)],
        "without keypoint lines": [pose.format(i, i, i) for i in range(1, 5)],  # every second image was lost
        # A name that is a number, where a pose line is due (it was taken for a keypoint line and refused).
        "numeric names": [pose.replace("cam{:02d}.png", "{:04d}").format(i, i, i) + "\n" + keypoints
                          for i in range(1, 5)],
    }
    for case, records in cases.items():
        path = tmp_path / f"{case}.txt"
        path.write_text("# Image list\n" + "\n".join(records) + "\n")
        images = _read_images_txt(path)
        names = [f"{i:04d}" if case == "numeric names" else f"cam{i:02d}.png" for i in range(1, 5)]
        assert [images[i].name for i in sorted(images)] == names, case
        assert images[3].tvec[0] == pytest.approx(0.3), case


def test_a_video_whose_stream_starts_late_decodes_every_coded_frame_once(tmp_path):
    """Frame k of a video is its k-th coded frame. A video stream that starts after the file does (here 0.1 s after
    an audio track) was padded by ffmpeg's constant-rate output with copies of its first frame, and its last frames
    were lost: the camera was out of step with the others."""
    import subprocess

    import imageio_ffmpeg
    from PIL import Image

    from stgc.data.dataset import decode_video

    exe = imageio_ffmpeg.get_ffmpeg_exe()
    for k in range(10):
        Image.fromarray(np.full((16, 16, 3), 20 * k + 10, np.uint8)).save(tmp_path / f"g{k}.png")
    run = dict(check=True, capture_output=True)
    subprocess.run([exe, "-y", "-framerate", "30", "-i", str(tmp_path / "g%d.png"), "-f", "lavfi", "-i",
                    "anullsrc=r=8000:cl=mono", "-t", "0.5", "-c:v", "libx264", "-pix_fmt", "yuv444p", "-qp", "0",
                    "-c:a", "aac", str(tmp_path / "plain.mp4")], **run)
    subprocess.run([exe, "-y", "-i", str(tmp_path / "plain.mp4"), "-itsoffset", "0.1", "-i", str(tmp_path / "plain.mp4"),
                    "-map", "1:v", "-map", "0:a", "-c", "copy", str(tmp_path / "late.mp4")], **run)
    frames = decode_video(tmp_path / "late.mp4", list(range(10)))
    assert [round((float(frames[k].mean()) - 10) / 20) for k in range(10)] == list(range(10))


@pytest.mark.parametrize("pixel_format, bit_depth", [("yuv420p10le", 10), ("yuv420p", 8)])
@pytest.mark.parametrize("yuv_range, ffmpeg_range", [("limited", "tv"), ("full", "pc")])
def test_yuv_files_that_ffmpeg_wrote_decode_to_their_colours(tmp_path, pixel_format, bit_depth, yuv_range,
                                                             ffmpeg_range):
    """An independent encoder (ffmpeg's BT.709 matrix) against our reader: a matrix, range or plane-order mistake
    would move these flat colours by tens of levels (the round trips through our own writer cannot see it)."""
    import subprocess

    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    from PIL import Image

    from stgc.data.yuv import read_frame

    colours = [(255, 0, 0), (0, 255, 0), (0, 0, 255), (200, 120, 40), (20, 200, 180), (255, 255, 255), (0, 0, 0)]
    for colour in colours:
        image = np.zeros((8, 12, 3), np.uint8) + np.array(colour, np.uint8)
        Image.fromarray(image).save(tmp_path / "rgb.png")
        subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-v", "error", "-y", "-i", str(tmp_path / "rgb.png"),
                        "-vf", f"scale=out_color_matrix=bt709:out_range={ffmpeg_range}", "-pix_fmt", pixel_format,
                        "-f", "rawvideo", str(tmp_path / "x.yuv")], check=True)
        decoded = read_frame(tmp_path / "x.yuv", 12, 8, 0, bit_depth, yuv_range)
        assert np.abs(decoded.astype(int) - image).max() <= 2, (colour, decoded[0, 0])
