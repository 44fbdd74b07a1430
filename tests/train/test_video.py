"""Stills, videos and contact sheets have the right size and number of frames."""

from __future__ import annotations

import imageio.v3 as iio
import numpy as np
import pytest

from stgc.eval.video import contact_sheet, orbit_cameras, render_still, render_video


@pytest.fixture(scope="module")
def model(tiny_toys, make_model):
    return make_model(tiny_toys, 200)


def test_still_is_the_camera_size_and_matches_a_direct_render(tiny_toys, model, tmp_path):
    out = render_still(model, "cam00", 0.5, tmp_path / "still.png", dataset=tiny_toys)
    img = iio.imread(out)
    cam = tiny_toys.test[0]
    assert img.shape == (cam.height, cam.width, 3) and img.dtype == np.uint8
    direct = model.render(cam, t=0.5).rgb.detach().clamp(0, 1).numpy()
    assert np.abs(img / 255.0 - direct).max() <= 0.5 / 255 + 1e-6


def test_fixed_view_video_has_one_frame_per_selected_frame(tiny_toys, model, tmp_path):
    out = render_video(model, tmp_path / "v.mp4", dataset=tiny_toys, camera_name="cam00", frames="0:2", fps=10)
    frames = iio.imread(out)
    cam = tiny_toys.test[0]
    assert frames.shape == (2, cam.height, cam.width, 3)
    # Each video frame is the camera's render at that frame's time (H.264 costs a little; a wrong camera or
    # time costs far more).
    for k, frame in enumerate((0, 1)):
        view = next(c for c in tiny_toys.test_at(frame) if c.name == "cam00")
        direct = model.render(view, t=view.time).rgb.detach().clamp(0, 1).numpy()
        mse = np.mean((frames[k] / 255.0 - direct) ** 2)
        assert 10 * np.log10(1 / mse) > 30


def test_orbit_video_and_path(tiny_toys, model, tmp_path):
    cams = orbit_cameras(tiny_toys, 5)
    train_centres = np.array([c.center for c in tiny_toys.train_at(0)])
    # The path starts and ends on training cameras (the two ends of the arc) and stays near the rig.
    ends = [np.linalg.norm(train_centres - cams[i].center, axis=1).min() for i in (0, -1)]
    assert max(ends) < 1e-6
    assert all(abs(np.linalg.det(c.w2c[:3, :3]) - 1) < 1e-9 for c in cams)
    # tiny_toys holds frames 0-2 (t = 0, 1/3, 2/3): the sweep ends at the last frame's time, not past the data.
    assert [c.time for c in cams] == pytest.approx([0, 1 / 6, 1 / 3, 1 / 2, 2 / 3])
    gif = render_video(model, tmp_path / "orbit.gif", dataset=tiny_toys, orbit=True, num_frames=4, fps=8)
    assert iio.imread(gif).shape[0] == 4
    mp4 = render_video(model, tmp_path / "orbit.mp4", dataset=tiny_toys, orbit=True, num_frames=6)
    assert iio.imread(mp4).shape[:2] == (6, cams[0].height)


def test_contact_sheet_layout(tiny_toys, model, tmp_path):
    out = contact_sheet(model, tiny_toys, [0, 2], tmp_path / "sheet.png", gap=2)
    sheet = iio.imread(out)
    cam = tiny_toys.test[0]
    rows = 2 * len(tiny_toys.test_views)
    assert sheet.shape == (rows * cam.height + (rows - 1) * 2, 3 * cam.width + 2 * 2, 3)
    gt = tiny_toys.load_image(tiny_toys.test_at(0)[0])
    assert np.array_equal(sheet[: cam.height, : cam.width], gt)


def test_still_from_a_run_directory_reopens_its_dataset(tiny_toys, make_model, tmp_path):
    from stgc.train import TrainConfig, train

    model = make_model(tiny_toys, 100)
    cfg = TrainConfig(iterations=1, progress=False, tensorboard=False, eval_at_end=False, save_iterations=())
    train(tiny_toys, None, None, cfg, None, tmp_path / "run", model=model)
    out = render_still(tmp_path / "run", "cam00", 0.25, tmp_path / "s.png")
    img = iio.imread(out)
    direct = render_still(model, "cam00", 0.25, tmp_path / "d.png", dataset=tiny_toys)
    assert np.array_equal(img, iio.imread(direct))


def test_render_verb_writes_the_contact_sheet_of_the_first_and_last_frame(tiny_toys, make_model, tmp_path, capsys):
    from stgc.cli import main
    from stgc.train import TrainConfig, train

    model = make_model(tiny_toys, 100)
    cfg = TrainConfig(iterations=1, progress=False, tensorboard=False, eval_at_end=False, save_iterations=())
    train(tiny_toys, None, None, cfg, None, tmp_path / "run", model=model)
    assert main(["render", str(tmp_path / "run"), "--contact-sheet", "--out", str(tmp_path / "cli.png")]) == 0
    direct = contact_sheet(model, tiny_toys, [0, 2], tmp_path / "direct.png")
    assert np.array_equal(iio.imread(tmp_path / "cli.png"), iio.imread(direct))
    assert main(["render", str(tmp_path / "run"), "--contact-sheet", "--orbit", "--out", str(tmp_path / "x.png")]) == 2
    assert "contact sheet" in capsys.readouterr().err


def test_an_official_run_renders_exports_and_opens_in_the_viewer_on_the_data_it_is_given(tiny_toys, model, tmp_path,
                                                                                        capsys):
    """A model without stgc's run config (an official STG run) needs the dataset named: only `stgc eval` took
    --data, and the others' error named an option they did not have."""
    import json

    from stgc.cli import main
    from stgc.viewer import ViewerScene

    run = tmp_path / "official"
    model.save(run / "point_cloud" / "iteration_5")
    (run / "cfg_args").write_text("Namespace(duration=3, rgbfunction='sandwich')")  # its frames 0-2
    still = tmp_path / "still.png"
    assert main(["render", str(run), "--out", str(still)]) == 2
    assert "--data" in capsys.readouterr().err
    data = str(tiny_toys.root)
    assert main(["render", str(run), "--out", str(still), "--data", data]) == 0
    full = next(c for c in tiny_toys.test if c.frame == 0)
    assert iio.imread(still).shape == (2 * full.height, 2 * full.width, 3)  # opened at the data's own size
    assert main(["export", str(run), "--out", str(tmp_path / "frames"), "--data", data]) == 0
    assert len(json.loads((tmp_path / "frames" / "export.json").read_text())["frames"]) == 3
    scene = ViewerScene.open(run, data_path=data)
    assert [f for s in scene.segments for f in s.frames] == [0, 1, 2]


def test_monocular_data_renders_its_default_video_and_contact_sheet(tmp_path, capsys):
    """Each image of monocular data is its own view: a fixed camera keeps its pose through the frames' times, and
    the contact sheet shows each frame's own held-out views (both were refused: 'no view at frame 1')."""
    import json

    from PIL import Image

    from stgc.cli import main
    from stgc.data import open_dataset
    from stgc.data.cameras import w2c_to_opengl_c2w
    from stgc.model import STGModel
    from stgc.train import TrainConfig, train

    root = tmp_path / "mono"
    for split, times in {"train": [0.0, 0.5, 1.0], "test": [0.25, 0.75]}.items():
        frames = []
        for i, t in enumerate(times):
            (root / split).mkdir(parents=True, exist_ok=True)
            Image.fromarray(np.full((12, 16, 3), 40 + 50 * i, np.uint8)).save(root / split / f"r_{i:03d}.png")
            w2c = np.eye(4)
            w2c[:3, 3] = [0.1 * i, 0, 3]
            frames.append({"file_path": f"./{split}/r_{i:03d}", "time": t,
                           "transform_matrix": w2c_to_opengl_c2w(w2c).tolist()})
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": 0.8, "frames": frames}))
    dataset = open_dataset(root)
    rng = np.random.default_rng(0)
    cloud = type("Cloud", (), {"xyz": rng.normal(size=(50, 3)).astype(np.float32),
                               "rgb": rng.random((50, 3)).astype(np.float32),
                               "time": rng.random(50).astype(np.float32)})
    model = STGModel.from_points(cloud, variant="lite", scene_extent=1.0)
    cfg = TrainConfig(iterations=1, progress=False, tensorboard=False, eval_at_end=False, save_iterations=())
    train(dataset, None, None, cfg, None, tmp_path / "run", model=model)
    assert main(["render", str(tmp_path / "run"), "--out", str(tmp_path / "m.mp4")]) == 0
    assert iio.imread(tmp_path / "m.mp4").shape[:3] == (5, 12, 16)  # frames 0-4 (ranks of the five times)
    assert main(["render", str(tmp_path / "run"), "--contact-sheet", "--out", str(tmp_path / "cs.png")]) == 0
    assert iio.imread(tmp_path / "cs.png").shape[0] == 2 * 12 + 2  # frames 1 and 3, each its own test view


@pytest.mark.parametrize("fps, frames_kept, delays_allowed", [(30, 30, {30, 40}), (120, 40, {20, 30})])
def test_a_gif_plays_at_its_frame_rate_though_the_format_counts_hundredths(tmp_path, fps, frames_kept,
                                                                          delays_allowed):
    """One delay of 1000/fps ms rounded to hundredths: 30 fps played 11 % fast. Browsers play a delay of 10 ms or
    less as 100 ms: at 120 fps every delay was 0 or 10 ms, a clip ten times too slow, so one frame in three is kept
    there, at 40 fps. Both clips last their one second."""
    from PIL import Image

    from stgc.eval.video import write_video

    frames = [np.full((8, 8, 3), 2 * k, dtype=np.uint8) for k in range(fps)]
    path = write_video(tmp_path / "clip.gif", frames, fps=fps)
    with Image.open(path) as gif:
        delays = []
        for k in range(gif.n_frames):
            gif.seek(k)
            delays.append(gif.info["duration"])
    assert len(delays) == frames_kept and set(delays) <= delays_allowed
    assert sum(delays) == 1000


def test_a_whole_video_plays_a_frame_list_in_its_order_with_its_repeats_across_segments(monkeypatch, tmp_path):
    """frame_selection keeps a list's order and repeats; the whole video's player put it in a set and played the
    segments' frames in time order once each."""
    from types import SimpleNamespace

    from stgc.eval import video

    played = []
    monkeypatch.setattr(video, "_camera_at", lambda dataset, name, frame: (dataset.label, name, frame))
    monkeypatch.setattr(video, "render_image", lambda model, camera, t, background: camera)
    monkeypatch.setattr(video, "write_video", lambda out, images, rate: played.extend(images) or out)
    segments = [("m0", SimpleNamespace(label="s0", frames=[0, 1, 2], test=[SimpleNamespace(name="cam00")], fps=30,
                                       background=(0, 0, 0))),
                ("m1", SimpleNamespace(label="s1", frames=[3, 4, 5], test=[], fps=30, background=(0, 0, 0)))]
    video._render_across_segments(segments, tmp_path / "v.mp4", None, "4,1,4", None, None)
    assert played == [("s1", "cam00", 4), ("s0", "cam00", 1), ("s1", "cam00", 4)]
    played.clear()
    video._render_across_segments(segments, tmp_path / "v.mp4", "cam03", "2:4", None, None)
    assert played == [("s0", "cam03", 2), ("s1", "cam03", 3)]
