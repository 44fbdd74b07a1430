"""`stgc view`: the scene behind the viewer, and the viewer itself in a real browser (headless Chromium)."""

from __future__ import annotations

import errno
import json
import math
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request

import numpy as np
import pytest
import torch
from PIL import Image
from scenes import moving_model, write_panoptic_scene

from stgc.cli import main
from stgc.errors import StgcError
from stgc.metrics import psnr

viser = pytest.importorskip("viser", reason="the viewer extra (viser) is not installed")

from stgc.viewer import (  # noqa: E402  (after the skip: the module needs viser)
    ViewerScene,
    camera_from_view,
    check_port,
    free_port,
    letterbox,
    view_of_camera,
)


def _write_run(root, model, data_root, iteration: int = 1):
    model.save(root / "point_cloud" / f"iteration_{iteration}")
    (root / "config.json").write_text(json.dumps({"data": {"path": str(data_root)}}))
    (root / "train_summary.json").write_text(json.dumps({"iterations": iteration, "finished": True}))
    return root


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return write_panoptic_scene(tmp_path_factory.mktemp("viewer"), views=5, frames=3, width=64, height=48)


@pytest.fixture(scope="module")
def run(scene, tmp_path_factory):
    """A run whose model moves (so the frame matters) and is not the one that drew the images (so PSNR is finite)."""
    return _write_run(tmp_path_factory.mktemp("viewer_run") / "run", moving_model(scene.model), scene.root)


def test_a_dataset_camera_renders_what_stgc_render_writes(run, tmp_path):
    viewed = ViewerScene.open(run)
    assert viewed.frames == [0, 1, 2] and viewed.test_names == {"0"}
    for frame in (0.0, 1.0, 2.0):
        t = frame / 3  # (frame - start) / duration
        assert main(["render", str(run), "--camera", "0", "--time", repr(t), "--out", str(tmp_path / "r.png")]) == 0
        expected = np.asarray(Image.open(tmp_path / "r.png").convert("RGB"))
        got = viewed.render(viewed.dataset_camera("0", frame), frame)
        assert np.array_equal(got, expected), frame
    numbers = viewed.stats(1.0, "0", got)
    assert numbers["gaussians"] == 750 and 0 < numbers["gaussians_alive"] < 750  # short temporal lives
    assert numbers["psnr"] is not None and math.isfinite(numbers["psnr"])
    assert viewed.stats(1.5, "0", got)["psnr"] is None  # between frames there is no ground truth


def test_a_bitstream_shows_what_it_decodes_to(run, tmp_path):
    from stgc.codec import compress_run, load_model

    stgc_file = run / "model_q3.stgc"
    if not stgc_file.exists():
        compress_run(run, stgc_file)
    viewed = ViewerScene.open(stgc_file)
    decoded = load_model(stgc_file)
    camera = viewed.dataset_camera("0", 1.0)
    expected = decoded.render(camera, t=camera.time, background=torch.zeros(3)).rgb
    assert np.array_equal(viewed.render(camera, 1.0), (expected.clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy())
    numbers = viewed.stats(1.0, None)
    assert numbers["size_kind"] == "file" and numbers["size_mb"] * 2**20 == stgc_file.stat().st_size


def test_a_whole_video_plays_as_one_timeline(scene, tmp_path):
    """Two segments of 2 and 1 frames: a frame is drawn by the segment that holds it, at the segment's own time."""
    other = moving_model(scene.model)
    with torch.no_grad():
        other.params["trbf_center"].fill_(0.5)
    video = tmp_path / "video"
    first = _write_run(video / "segment_000", scene.model, scene.root)
    second = _write_run(video / "segment_001", other, scene.root)
    for part, start, duration in ((first, 0, 2), (second, 2, 1)):
        config = json.loads((part / "config.json").read_text())
        config["data"].update(start=start, duration=duration)
        (part / "config.json").write_text(json.dumps(config))
    (video / "config.json").write_text(json.dumps({"data": {"path": str(scene.root)}}))
    (video / "video.json").write_text(json.dumps({"segment_frames": 2, "data_path": str(scene.root), "segments": [
        {"name": "segment_000", "start": 0, "duration": 2}, {"name": "segment_001", "start": 2, "duration": 1}]}))
    viewed = ViewerScene.open(video)
    assert viewed.frames == [0, 1, 2] and len(viewed.segments) == 2
    assert viewed.segment_at(1.9) is viewed.segments[0] and viewed.segment_at(2.0) is viewed.segments[1]
    camera = viewed.dataset_camera("0", 2.0)
    assert camera.time == 0.0  # the first frame of the second segment
    expected = other.render(camera, t=0.0, background=torch.zeros(3)).rgb
    got = viewed.render(camera, 2.0)
    assert np.array_equal(got, (expected.clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy())
    assert viewed.stats(2.0, None)["segment"] == 1


def test_a_browser_camera_put_on_a_dataset_camera_is_that_camera(scene):
    viewed = ViewerScene.open(_write_run(scene.root.parent / "pose_run", scene.model, scene.root))
    dataset_camera = viewed.cameras["2"]
    position, wxyz, fov = view_of_camera(dataset_camera)
    browser = camera_from_view(position, wxyz, fov, dataset_camera.width, dataset_camera.height, dataset_camera.near)
    np.testing.assert_allclose(browser.w2c, dataset_camera.w2c, atol=1e-9)
    assert browser.K[1, 1] == pytest.approx(dataset_camera.K[1, 1], rel=1e-12)
    # The scene's cameras have their principal point in the middle: the two renders agree exactly.
    got = viewed.render(browser, 0.0)
    assert psnr(torch.from_numpy(got), torch.from_numpy(viewed.render(dataset_camera, 0.0))) > 40


def test_letterbox_keeps_every_pixel_at_whole_scale():
    image = np.random.default_rng(0).integers(0, 256, (6, 8, 3), dtype=np.uint8)
    canvas = letterbox(image, 30, 20, (0.0, 0.0, 1.0))
    assert canvas.shape == (20, 30, 3)
    # scale min(30 // 8, 20 // 6) = 3: 24 x 18 in the middle, offsets (3, 1)
    assert np.array_equal(canvas[1:19, 3:27][::3, ::3], image)
    assert np.array_equal(canvas[0, 0], [0, 0, 255]) and np.array_equal(canvas[19, 29], [0, 0, 255])
    # A smaller canvas: shrunk by a whole factor (here 2: 4 x 3), still the canvas's shape, so that the browser,
    # which stretches any image over its canvas, shows it undistorted.
    small = letterbox(image, 7, 5, (0, 0, 0))
    assert small.shape == (5, 7, 3)
    block_means = np.floor(image.reshape(3, 2, 4, 2, 3).mean(axis=(1, 3)) + 0.5).astype(np.uint8)
    assert np.array_equal(small[1:4, 1:5], block_means)
    assert not small[0].any() and not small[:, 0].any()


def test_the_moving_image_shows_as_large_as_the_still_one_and_undistorted():
    """While the camera moves the viewer sends a half-resolution render, unscaled (the browser stretches it over the
    canvas); it is padded so that it covers the part of the canvas the full render covers at rest, in the canvas's
    aspect ratio. It filled the canvas, and the picture jumped in size when the camera stopped."""
    from stgc.viewer import letterbox_scale, pad_like_still

    coarse = np.full((25, 50, 3), 200, dtype=np.uint8)  # the 100 x 50 render at half resolution
    for width, height in ((350, 200), (640, 480), (120, 40), (90, 60)):
        padded = pad_like_still(coarse, 100, 50, width, height, (0.0, 0.0, 0.0))
        ph, pw = padded.shape[:2]
        assert abs(pw / ph - width / height) < 0.05  # undistorted
        assert int((padded == 200).all(axis=2).sum()) == 50 * 25  # unscaled
        still = letterbox_scale(100, 50, width, height)
        # Shown on the canvas: the coarse image's share of the padded one, against the still image's share.
        assert 50 / pw * width == pytest.approx(100 * still, rel=0.05)
        assert 25 / ph * height == pytest.approx(50 * still, rel=0.05)
    assert letterbox_scale(100, 50, 350, 200) == 3 and letterbox_scale(100, 50, 90, 60) == 0.5
    # With the ground truth beside the still render, the pair sets the scale; the moving render alone keeps the
    # canvas's aspect ratio and its own share of the pair's size (it was stretched to twice its width).
    pair = letterbox_scale(200, 50, 640, 480)
    padded = pad_like_still(coarse, 100, 50, 640, 480, (0.0, 0.0, 0.0), still_scale=pair)
    ph, pw = padded.shape[:2]
    assert abs(pw / ph - 640 / 480) < 0.05 and 50 / pw * 640 == pytest.approx(100 * pair, rel=0.05)


def test_a_port_in_use_gives_a_clear_error_with_a_free_port():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(StgcError, match=rf"port {port} on 127.0.0.1 is in use.*try --port \d+"):
            check_port("127.0.0.1", port)


@pytest.mark.skipif(sys.platform == "win32", reason="TIME_WAIT and SO_REUSEADDR as on POSIX")
def test_a_port_left_in_time_wait_by_a_stopped_viewer_is_free_to_restart_on():
    """A viewer stopped while a browser was connected leaves its side of the connection in TIME_WAIT for about a
    minute; the port probe bound a plain socket, which that refuses, so `stgc view` on the same port was refused
    as "in use" though viser (SO_REUSEADDR) can listen there. A port with a listener on it is still in use, with
    or without SO_REUSEADDR on the listener."""
    with socket.socket() as server:
        server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as viser's listener
        server.bind(("127.0.0.1", 0))
        server.listen()
        port = server.getsockname()[1]
        with pytest.raises(StgcError, match=rf"port {port} on 127.0.0.1 is in use"):
            check_port("127.0.0.1", port)
        browser = socket.create_connection(("127.0.0.1", port))
        connection, _ = server.accept()
    connection.close()  # the server closes first (Ctrl-C): its end goes to TIME_WAIT once the browser closes too
    browser.settimeout(5)
    assert browser.recv(1) == b""
    browser.close()
    with socket.socket() as plain, pytest.raises(OSError) as info:  # the situation: a plain bind is refused
        plain.bind(("127.0.0.1", port))
    assert info.value.errno == errno.EADDRINUSE
    check_port("127.0.0.1", port)  # no error
    with socket.socket() as restarted:  # and the server can indeed listen there again
        restarted.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        restarted.bind(("127.0.0.1", port))
        restarted.listen()


def _ipv6_loopback() -> bool:
    try:
        with socket.socket(socket.AF_INET6) as probe:
            probe.bind(("::1", 0))
        return True
    except OSError:
        return False


@pytest.mark.skipif(not _ipv6_loopback(), reason="no IPv6 loopback here")
def test_the_address_printed_for_an_ipv6_host_is_a_url(run):
    """`stgc view --host ::1` printed http://::1:PORT, which is not a URL (a browser or urllib cannot open it)."""
    import urllib.parse

    from stgc.viewer import Viewer

    port = free_port("::1")
    viewer = Viewer(ViewerScene.open(run), host="::1", port=port)
    try:
        assert viewer.url == f"http://[::1]:{port}"
        parts = urllib.parse.urlsplit(viewer.url)
        assert (parts.hostname, parts.port) == ("::1", port)
        with urllib.request.urlopen(viewer.url, timeout=10) as page:
            assert page.status == 200
    finally:
        viewer.stop()


def test_a_host_that_cannot_be_listened_on_is_named_not_taken_for_a_port_in_use():
    """`stgc view --host 10.255.255.1` (not this machine's address) or a host name that does not resolve printed a
    bare OSError naming neither the host nor --host: the error was read as a port in use, and finding a free port on
    that host failed in turn. A port in use (only then) still gets a free port to try."""
    port = free_port()
    with pytest.raises(StgcError, match=r"--host 10\.255\.255\.1: cannot listen there") as info:
        check_port("10.255.255.1", port)
    assert "in use" not in str(info.value) and "127.0.0.1" in str(info.value)
    with pytest.raises(StgcError, match=r"--host no-such-host\.invalid: cannot resolve") as info:
        check_port("no-such-host.invalid", port)
    assert "in use" not in str(info.value)


def test_the_speed_slider_holds_the_datas_frame_rate_outside_its_usual_range(run):
    """The frames-per-second slider ran from 0.5 to 60 and started at the data's rate, which viser refuses outside
    that range: `stgc view` failed on data at 120 or 0.25 fps."""
    from stgc.viewer import Viewer

    for fps in (120.0, 0.25):
        viewed = ViewerScene.open(run)
        viewed.segments[0].dataset.fps = fps
        viewer = Viewer(viewed, port=free_port())
        try:
            assert viewer.speed.value == fps and viewer.speed.min <= 0.5 and viewer.speed.max >= 60.0
        finally:
            viewer.stop()


def test_with_ground_truth_on_the_picture_keeps_its_size_when_the_camera_stops(run):
    """With `ground truth` on, the moving (coarse) image was sized for the pair render | ground truth, but at rest the
    pair is shown only where an image exists (never between frames): stopping at frame 1.5 doubled the picture's
    size. Pair or single is now decided once per frame: the render covers the same part of the canvas moving and
    still, the left half beside the ground truth at a dataset frame, the whole between frames."""
    from types import SimpleNamespace

    from stgc.viewer import _ClientView

    viewed = ViewerScene.open(run)
    mark = np.array([255, 0, 255], np.uint8)
    viewed.render = lambda cam, frame: np.tile(mark, (cam.height, cam.width, 1))  # the render's pixels, found below
    sent = []

    class BrowserCamera:
        image_width, image_height, fov, update_timestamp = 640, 480, 1.0, 1.0
        position, wxyz = np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0])

        def on_update(self, callback):
            pass

    client = SimpleNamespace(client_id=1, camera=BrowserCamera(),
                             scene=SimpleNamespace(set_background_image=lambda image, format: sent.append(image)))
    viewer = SimpleNamespace(scene=viewed, frame=1.0, show_ground_truth=True, max_side=64, near=0.2,
                             show_stats=lambda *args: None)
    view = _ClientView(viewer, client)
    view.closed = True  # the test draws; the render loop stops
    view.wake.set()
    view.thread.join()
    position, wxyz, _ = view_of_camera(viewed.cameras["0"])
    client.camera.position, client.camera.wxyz = position, wxyz
    view.snapped = ("0", position, wxyz)

    def shown():
        """Where the render lies on the canvas, as shares of the image the browser stretches over it."""
        image = sent[-1]
        rows, cols = np.nonzero((image == mark).all(axis=2))
        h, w = image.shape[:2]
        return np.array([cols.min() / w, (cols.max() + 1) / w, rows.min() / h, (rows.max() + 1) / h])

    for frame, width_share in ((1.0, 0.5), (1.5, 1.0)):
        viewer.frame = frame
        view.changed_at = time.perf_counter()  # moving
        view.draw()
        moving = shown()
        view.changed_at = time.perf_counter() - 10.0  # at rest
        view.draw()
        still = shown()
        np.testing.assert_allclose(moving, still, atol=0.04, err_msg=f"frame {frame}")
        assert still[1] - still[0] == pytest.approx(width_share, abs=0.02)  # the pair at a dataset frame only
    assert np.array_equal(sent[-1].shape, (480, 640, 3))


def test_a_missing_source_gives_the_usual_clear_error(tmp_path, capsys):
    assert main(["view", str(tmp_path / "nothing")]) != 0
    assert "nothing" in capsys.readouterr().err


def test_a_corrupt_bitstream_gives_the_usual_clear_error(tmp_path, capsys):
    bad = tmp_path / "broken.stgc"
    bad.write_bytes(b"STGC" + bytes(40))
    assert main(["view", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "broken.stgc" in err and "Traceback" not in err


@pytest.mark.parametrize("fps, seconds, expected", [(0.5, 1.0, 0.5), (1.5, 1.0, 1.5), (10.0, 0.5, 1.0), (1.5, 2.0, 1.0)])
def test_playback_moves_the_frame_at_the_chosen_speed(run, fps, seconds, expected):
    """30 ticks a second, as the player thread gives them: slow speeds advance too (each tick moves by less than the
    slider's 0.1 step), and the frame rate is the one chosen, wrapping at the end (frames 0..2: 3 frames at 1.5 fps
    are 0 -> 2, then 1 more)."""
    from stgc.viewer import Viewer

    viewer = Viewer(ViewerScene.open(run), port=free_port())
    viewer.closed.set()  # the test gives the ticks: stop the real-time player thread first
    viewer.player.join()
    try:
        viewer.speed.value = fps
        viewer.play.value = True
        for _ in range(round(seconds * 30)):
            viewer.advance(1.0 / 30.0)
        assert viewer.frame == pytest.approx(expected, abs=0.051)
        viewer.play.value = False
        viewer.advance(1.0)
        assert viewer.playhead is None
    finally:
        viewer.stop()


def test_ctrl_c_stops_the_server_cleanly(run):
    port = free_port()
    # A shell starts background jobs with SIGINT ignored, and a child inherits that: Python then never turns SIGINT
    # into KeyboardInterrupt, and `make test &` waited here for ever. Give the viewer the default disposition.
    proc = subprocess.Popen([sys.executable, "-m", "stgc.cli", "view", str(run), "--port", str(port)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        line = ""
        deadline = time.monotonic() + 120
        while "Ctrl-C stops" not in line and time.monotonic() < deadline:
            line = proc.stdout.readline()
            assert line or proc.poll() is None, "the viewer exited before serving"
        with urllib.request.urlopen(f"http://127.0.0.1:{port}", timeout=10) as page:
            assert page.status == 200
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0 and "Traceback" not in out


# --------------------------------------------------------------------------------------------- real browser
def _chromium():
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    if browser is None or driver is None:
        pytest.skip("Chromium and its driver are not installed (apt-get install chromium chromium-driver)")
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed")
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = browser
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                "--window-size=1000,700", "--force-device-scale-factor=1"):
        options.add_argument(arg)
    return webdriver.Chrome(service=Service(driver), options=options)


def _until(condition, seconds=30.0):
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError("timed out waiting for the page")


@pytest.mark.slow
def test_in_a_browser_a_dataset_camera_and_frame_show_what_stgc_render_writes(run, tmp_path):
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    from stgc.viewer import Viewer

    viewer = Viewer(ViewerScene.open(run), port=free_port())
    driver = _chromium()
    try:
        driver.get(viewer.url)
        _until(lambda: viewer.clients)

        def control(label):
            return driver.find_element(By.ID, driver.find_element(
                By.XPATH, f"//label[normalize-space()='{label}']").get_attribute("for"))

        # Through the page: the camera menu, then the frame's number box.
        _until(lambda: control("camera")).click()
        option = _until(lambda: [o for o in driver.find_elements(By.XPATH, "//*[@role='option']") if o.text == "0"])
        option[0].click()
        frame_box = driver.find_elements(By.XPATH, "//label[normalize-space()='frame']/ancestor::div[1]"
                                                   "/following-sibling::*//input[not(@type='hidden')]")[-1]
        frame_box.send_keys(Keys.CONTROL, "a")  # a chord: CONTROL is released after this call
        frame_box.send_keys(Keys.BACKSPACE, "1", Keys.ENTER)
        view = next(iter(viewer.clients.values()))
        _until(lambda: viewer.frame == 1.0)
        _until(lambda: view.snapped_name() == "0")
        _until(lambda: "PSNR" in viewer.numbers.content)
        # Notices (headless Chromium draws WebGL in software, which viser points out) float over the canvas.
        for close in driver.find_elements(By.XPATH, "//button[contains(@class, 'Notification-close')]"):
            close.click()
        _until(lambda: not driver.find_elements(By.XPATH, "//*[@role='alert']"))
        # The last full image must be drawn for the canvas as it is now: one drawn for a size the page reported
        # before a resize is stretched to the canvas, and no longer one screen block per image pixel.
        canvas = driver.find_element(By.TAG_NAME, "canvas").rect
        _until(lambda: view.full_done and view.drawn_size == (int(canvas["width"]), int(canvas["height"])))
        time.sleep(1.0)  # the browser decodes and draws the last image
        shot = np.asarray(Image.open(_screenshot(driver, tmp_path / "view.png")).convert("RGB"))

        assert main(["render", str(run), "--camera", "0", "--time", repr(1 / 3), "--out", str(tmp_path / "r.png")]) == 0
        expected = np.asarray(Image.open(tmp_path / "r.png").convert("RGB"))
        panel_left = min(e.rect["x"] for e in driver.find_elements(By.XPATH, "//label[normalize-space()='camera']"))
        h, w = expected.shape[:2]
        width, height = int(canvas["width"]), int(canvas["height"])
        scale = min(width // w, height // h)
        top, left = int(canvas["y"]) + (height - h * scale) // 2, int(canvas["x"]) + (width - w * scale) // 2
        # The centre of each screen block is one image pixel; the control panel floats over the right side.
        visible = [j for j in range(w) if left + j * scale + scale - 1 < panel_left - 20]
        rows = top + np.arange(h) * scale + scale // 2
        cols = left + np.asarray(visible) * scale + scale // 2
        on_screen = shot[rows][:, cols]
        assert len(visible) >= w // 3
        score = float(psnr(torch.from_numpy(on_screen), torch.from_numpy(expected[:, visible])))
        print(f"viewer vs stgc render: {score:.2f} dB over {h} x {len(visible)} pixels at scale {scale}")
        assert score >= 40.0

        # A reload reconnects and comes back to the same camera; a closed browser leaves the server serving.
        driver.refresh()
        _until(lambda: any(v.snapped_name() == "0" for v in viewer.clients.values()))
    finally:
        driver.quit()
    with urllib.request.urlopen(viewer.url, timeout=10) as page:
        assert page.status == 200
    viewer.stop()


def _screenshot(driver, path):
    driver.save_screenshot(str(path))
    return path


def test_a_whole_videos_bitstreams_play_as_one_timeline(scene, tmp_path, capsys):
    """`--bitstream NAME`: each segment's .stgc of that name, decoded, one timeline; a segment without it is named."""
    from stgc.codec import CodecConfig, compress_run, load_model

    ladder = CodecConfig(allocation="ladder")  # fixed bit depths: no allocation renders (what is viewed is the point)
    other = moving_model(scene.model)
    video = tmp_path / "video"
    for k, (model, start, duration) in enumerate(((scene.model, 0, 2), (other, 2, 1))):
        part = _write_run(video / f"segment_{k:03d}", model, scene.root)
        (part / "config.json").write_text(json.dumps({"data": {"path": str(scene.root), "start": start,
                                                              "duration": duration}}))
    (video / "config.json").write_text(json.dumps({"data": {"path": str(scene.root)}}))
    (video / "video.json").write_text(json.dumps({"segment_frames": 2, "data_path": str(scene.root), "segments": [
        {"name": "segment_000", "start": 0, "duration": 2}, {"name": "segment_001", "start": 2, "duration": 1}]}))
    compress_run(video / "segment_000", video / "segment_000" / "m.stgc", config=ladder)
    assert main(["view", str(video), "--bitstream", "m.stgc", "--port", str(free_port())]) == 2
    assert "segment_001/m.stgc" in capsys.readouterr().err  # the segment that lacks it, before anything serves
    compress_run(video / "segment_001", video / "segment_001" / "m.stgc", config=ladder)
    viewed = ViewerScene.open(video, bitstream="m.stgc")
    assert viewed.frames == [0, 1, 2] and all(s.size.convention == "file" for s in viewed.segments)
    camera = viewed.dataset_camera("0", 2.0)
    decoded = load_model(video / "segment_001" / "m.stgc")
    expected = decoded.render(camera, t=camera.time, background=torch.zeros(3)).rgb
    assert np.array_equal(viewed.render(camera, 2.0), (expected.clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy())
    # The whole video's one file (`stgc compress RUN`): the same timeline, each frame from its segment in the file.
    whole = compress_run(video, video / "whole.stgc", config=ladder)
    assert len(whole.segments) == 2
    for source, bitstream in ((video / "whole.stgc", None), (video, "whole.stgc")):
        viewed = ViewerScene.open(source, bitstream=bitstream)
        assert viewed.frames == [0, 1, 2] and [s.size.size_bytes for s in viewed.segments] == [
            (video / f"segment_{k:03d}" / "m.stgc").stat().st_size for k in range(2)]
        assert np.array_equal(viewed.render(camera, 2.0), (expected.clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy())
