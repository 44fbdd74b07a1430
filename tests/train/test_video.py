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
