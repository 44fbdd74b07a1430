"""`stgc view RUN|FILE.stgc`: an interactive viewer in the browser (viser), drawn by stgc's own rasterizer.

The browser shows a three.js canvas whose background image is what stgc renders for that browser's camera at the
timeline's time: the exact STG colour, decoder and viewing direction included. While the camera moves the image is
rendered at a quarter of the pixels; once it rests for `REST_SECONDS`, at full resolution.

Snapped to a dataset camera (the `camera` dropdown), the view is that camera exactly: its intrinsics, its image
size, at whole-pixel scale in the middle of the canvas, so what the page shows is what `stgc render --camera C
--time T` writes; a canvas smaller than that image shows it shrunk by a whole factor, undistorted. At a dataset
frame the panel gives this view's PSNR against its ground truth, and `ground truth` puts the ground truth beside the
render. Moving the camera leaves the snapped view.

A whole-video run (`stgc train --segment-frames`) plays as one timeline: the frame picks the segment that holds
it, and its model renders at the segment's own time. A `.stgc` bitstream is decoded first, so the viewer shows
what the bitstream holds.
"""

from __future__ import annotations

import dataclasses
import errno
import logging
import math
import os
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from stgc.codec import is_video_stgc
from stgc.data.cameras import Camera
from stgc.data.dataset import Dataset
from stgc.errors import DataError, StgcError
from stgc.eval.accounting import ModelSize, bitstream_size, model_size_of
from stgc.eval.evaluate import dataset_duration_s, video_bitstream_segments
from stgc.eval.video import load_model_and_dataset
from stgc.metrics import psnr
from stgc.model import STGModel, rows_at
from stgc.run import Run

log = logging.getLogger(__name__)

FREE_VIEW = "free camera"
REST_SECONDS = 0.25  # a camera still for this long gets the full-resolution image
MOVING_PIXEL_SCALE = 0.5  # per axis, while the camera moves: a quarter of the pixels
POSE_TOLERANCE = 1e-4  # how far (world units, quaternion components) a browser camera may drift and stay snapped


@dataclass
class Segment:
    """One model and the frames it covers: a single run is one segment, a whole-video run one per segment run."""

    model: STGModel
    dataset: Dataset
    frames: list[int]  # absolute frame indices, ascending
    size: ModelSize

    @property
    def start(self) -> int:
        return self.frames[0]

    def time_of(self, frame: float) -> float:
        """The segment's normalised time of (fractional) absolute `frame`: the dataset's time of the frames on
        either side (`Dataset.time_of`, which places unevenly timed frames where their times lie), interpolated."""
        below = math.floor(frame)
        t_below = self.dataset.time_of(below)
        if frame == below:
            return min(max(t_below, 0.0), 1.0)
        t_above = self.dataset.time_of(below + 1)
        return min(max(t_below + (frame - below) * (t_above - t_below), 0.0), 1.0)


class ViewerScene:
    """What the viewer shows, without the browser: the timeline, renders of any camera at any frame, the numbers
    beside the picture. `stgc view` wires it to viser; tests drive it directly."""

    def __init__(self, segments: list[Segment], source: Path):
        if not segments:
            raise StgcError(f"{source}: nothing to view (no segment holds a model)")
        self.segments = segments
        self.source = source
        self.frames = [f for s in segments for f in s.frames]
        first = segments[0].dataset
        red, green, blue = (float(c) for c in first.background)
        self.background = (red, green, blue)
        # One camera per name (the rig is fixed over time): tests first, as `stgc render` picks them.
        by_name: dict[str, Camera] = {}
        for cam in [*first.test, *first.train]:
            by_name.setdefault(str(cam.name), cam)
        self.cameras = by_name
        self.test_names = {str(c.name) for c in first.test}
        self._lock = threading.Lock()  # torch renders from several browser threads, one at a time

    @classmethod
    def open(cls, source: str | Path, bitstream: str | None = None,
             data_path: str | Path | None = None) -> ViewerScene:
        """A run directory (single or whole-video), an iteration directory or PLY, or a `.stgc` bitstream.
        bitstream: show the run's (each segment's, for a whole video) file of this name instead of its model, so a
        whole video's bitstreams play as one timeline. data_path: the dataset, where the saved one moved or the
        model has no stgc run config (an official run)."""
        path = Path(source)
        if not path.exists():
            raise DataError(path, "not found: give a run directory or a .stgc file")
        run = Run(path)
        folders = [s.path for s in run.segments()] if path.is_dir() and run.is_video() else [path]
        if bitstream is not None:
            if not path.is_dir():
                raise StgcError(f"--bitstream {bitstream}: names a file inside a run directory, and {path} is not one")
            if is_video_stgc(path / bitstream):  # the whole video's one file (stgc compress RUN)
                folders = [path]
            missing = [f / bitstream for f in folders if not (f / bitstream).is_file()]
            if missing:
                raise DataError(missing[0], "not found (write it with `stgc compress` on that run"
                                + (" or segment" if len(folders) > 1 else "") + ")")
            folders = [f / bitstream for f in folders]
        if len(folders) == 1 and is_video_stgc(folders[0]):
            return cls([Segment(s.model, s.dataset, sorted(int(f) for f in s.dataset.frames), s.size)
                        for s in video_bitstream_segments(folders[0], data_path)], path)
        segments = []
        for target in folders:
            model, dataset = load_model_and_dataset(target, data_path=data_path)
            duration = dataset_duration_s(dataset)
            if target.suffix == ".stgc":
                size = bitstream_size(target, model.num_gaussians, model.variant, duration)
            else:
                size = model_size_of(model, duration)
            segments.append(Segment(model, dataset, sorted(int(f) for f in dataset.frames), size))
        return cls(segments, path)

    # ------------------------------------------------------------------------------------------ timeline
    def segment_at(self, frame: float) -> Segment:
        whole = math.floor(frame)
        for segment in self.segments:
            if whole <= segment.frames[-1]:
                return segment
        return self.segments[-1]

    def dataset_camera(self, name: str, frame: float) -> Camera:
        """Dataset camera `name` at (fractional) `frame`, timed in the segment that holds the frame."""
        if name not in self.cameras:
            raise StgcError(f"no camera named {name!r}; cameras are {', '.join(sorted(self.cameras))}")
        segment = self.segment_at(frame)
        return dataclasses.replace(self.cameras[name], time=segment.time_of(frame), frame=int(math.floor(frame)))

    # ------------------------------------------------------------------------------------------ pictures
    def render(self, camera: Camera, frame: float) -> np.ndarray:
        """uint8 [H, W, 3] of `camera` at (fractional) absolute `frame`, as `stgc render` draws it."""
        segment = self.segment_at(frame)
        t = segment.time_of(frame)
        with self._lock, torch.no_grad():
            rgb = segment.model.render(camera, t=t, background=self.background).rgb
        return (rgb.clamp(0.0, 1.0) * 255.0 + 0.5).to(torch.uint8).numpy()

    def ground_truth(self, name: str, frame: float) -> np.ndarray | None:
        """The dataset's image of camera `name` at a whole `frame`; None between frames or without the image."""
        if frame != math.floor(frame):
            return None
        segment = self.segment_at(frame)
        match = [c for c in [*segment.dataset.test, *segment.dataset.train]
                 if str(c.name) == name and int(c.frame) == int(frame)]
        if not match:
            return None
        try:
            return np.asarray(segment.dataset.load_image(match[0]))[..., :3]
        except (OSError, DataError):
            return None

    def stats(self, frame: float, camera_name: str | None, rendered: np.ndarray | None = None) -> dict[str, Any]:
        """The numbers beside the picture: Gaussians alive at this time, size and rate of the model on screen, and
        this view's PSNR when it is a dataset camera at a dataset frame."""
        segment = self.segment_at(frame)
        with torch.no_grad():
            alive = len(rows_at(segment.model.params, segment.time_of(frame)).index)  # the rows a render keeps
        out: dict[str, Any] = {
            "frame": frame,
            "segment": self.segments.index(segment),
            "gaussians_alive": alive,
            "gaussians": segment.model.num_gaussians,
            "size_mb": segment.size.size_mib,
            "mbps": segment.size.mbps,
            "size_kind": "file" if segment.size.convention == "file" else "float32 model",
            "psnr": None,
        }
        if camera_name is not None and rendered is not None:
            gt = self.ground_truth(camera_name, frame)
            if gt is not None and gt.shape == rendered.shape:
                out["psnr"] = float(psnr(torch.from_numpy(rendered), torch.from_numpy(np.ascontiguousarray(gt))))
        return out


# ---------------------------------------------------------------------------------------------- cameras
def camera_from_view(position: np.ndarray, wxyz: np.ndarray, fov_y: float, width: int, height: int,
                     near: float) -> Camera:
    """The stgc camera of a browser view: viser's pose is camera-to-world in OpenCV axes (x right, y down, z
    forward) with the vertical field of view `fov_y` (radians); square pixels, principal point in the middle."""
    from viser import transforms

    c2w = np.eye(4)
    c2w[:3, :3] = transforms.SO3(np.asarray(wxyz, dtype=np.float64)).as_matrix()
    c2w[:3, 3] = np.asarray(position, dtype=np.float64)
    focal = 0.5 * height / math.tan(0.5 * fov_y)
    K = np.array([[focal, 0.0, 0.5 * width], [0.0, focal, 0.5 * height], [0.0, 0.0, 1.0]])
    return Camera(name="view", frame=0, time=0.0, K=K, w2c=np.linalg.inv(c2w), width=int(width),
                  height=int(height), near=near)


def view_of_camera(camera: Camera) -> tuple[np.ndarray, np.ndarray, float]:
    """(position, wxyz, vertical fov) that puts a browser camera where the dataset camera is."""
    from viser import transforms

    c2w = camera.c2w
    wxyz = transforms.SO3.from_matrix(c2w[:3, :3]).wxyz
    fov_y = 2.0 * math.atan(0.5 * camera.height / float(camera.K[1, 1]))
    return c2w[:3, 3].copy(), np.asarray(wxyz, dtype=np.float64), fov_y


def letterbox(image: np.ndarray, width: int, height: int, fill: tuple[float, float, float]) -> np.ndarray:
    """`image` in the middle of a `width` x `height` canvas of the fill colour: at the largest whole-pixel scale
    (>= 1) that fits, never resampled, so each image pixel stays exact; in a canvas smaller than the image, shrunk
    by the smallest whole factor k that fits (means of k x k pixels). Always the canvas's shape: viser stretches
    whatever image it gets over the whole canvas, so any other shape would show the picture distorted."""
    h, w = image.shape[:2]
    scale = letterbox_scale(w, h, width, height)
    if scale >= 1:
        fitted = np.repeat(np.repeat(image, int(scale), axis=0), int(scale), axis=1)
    else:
        fitted = _shrink(image, round(1.0 / scale))
    return _centred(fitted, width, height, fill)


def letterbox_scale(width: int, height: int, canvas_width: int, canvas_height: int) -> float:
    """The scale `letterbox` shows a `width` x `height` image at on a canvas: a whole number, or 1/k."""
    scale = min(canvas_width // width, canvas_height // height)
    return float(scale) if scale >= 1 else 1.0 / math.ceil(max(width / canvas_width, height / canvas_height))


def pad_like_still(image: np.ndarray, full_width: int, full_height: int, width: int, height: int,
                   fill: tuple[float, float, float], still_scale: float | None = None) -> np.ndarray:
    """A coarse `image` (the render while the camera moves), not scaled, in the middle of a canvas of the fill
    colour with the `width` x `height` canvas's aspect ratio, so sized that the browser, stretching it over the
    canvas, shows it as large as the `full_width` x `full_height` render is shown at rest: at `still_scale` (by
    default `letterbox`'s for that render alone; with the ground truth beside it, the pair's). The picture does not
    jump in size when the camera stops."""
    h, w = image.shape[:2]
    shown = letterbox_scale(full_width, full_height, width, height) if still_scale is None else still_scale
    canvas_w = max(w, round(w * width / (full_width * shown)))
    canvas_h = max(h, round(h * height / (full_height * shown)))
    return _centred(image, canvas_w, canvas_h, fill)


def _fitted(image: np.ndarray, shape: tuple[int, ...], fill: tuple[float, float, float]) -> np.ndarray:
    """`image` cut or padded (in the middle of the fill colour) to `shape` [H, W, 3]."""
    cut = image[: shape[0], : shape[1]]
    return cut if cut.shape == tuple(shape) else _centred(cut, shape[1], shape[0], fill)


def _centred(image: np.ndarray, width: int, height: int, fill: tuple[float, float, float]) -> np.ndarray:
    canvas = np.empty((height, width, 3), dtype=np.uint8)
    canvas[:] = (np.asarray(fill) * 255.0 + 0.5).astype(np.uint8)
    top, left = (height - image.shape[0]) // 2, (width - image.shape[1]) // 2
    canvas[top:top + image.shape[0], left:left + image.shape[1]] = image
    return canvas


def _shrink(image: np.ndarray, factor: int) -> np.ndarray:
    """`image` made `factor` times smaller in each direction by the mean of each factor x factor block (the last
    row and column of blocks average what they hold)."""
    h, w = image.shape[:2]
    rows, cols = -(-h // factor), -(-w // factor)
    padded = np.pad(image.astype(np.float64), ((0, rows * factor - h), (0, cols * factor - w), (0, 0)))
    weights = np.pad(np.ones((h, w, 1)), ((0, rows * factor - h), (0, cols * factor - w), (0, 0)))
    sums = padded.reshape(rows, factor, cols, factor, -1).sum(axis=(1, 3))
    counts = weights.reshape(rows, factor, cols, factor, 1).sum(axis=(1, 3))
    return np.clip(sums / counts + 0.5, 0, 255).astype(np.uint8)


# ---------------------------------------------------------------------------------------------- server
def check_port(host: str, port: int) -> None:
    """A clear error when the viewer cannot listen on `host`:`port`: a host name that does not resolve or an
    address that is not this machine's names --host; a port that is taken (only then) gets a free one to use."""
    family, address = _listen_address(host, port)
    with _probe_socket(family) as probe:
        try:
            probe.bind(address)
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise StgcError(f"port {port} on {host} is in use ({exc.strerror}); "
                                f"try --port {free_port(host)}") from None
            if exc.errno in (errno.EACCES, errno.EPERM):
                raise StgcError(f"--port {port} on {host}: permission denied ({exc.strerror}; ports below 1024 "
                                f"need privileges); try --port {free_port(host)}") from None
            raise StgcError(f"--host {host}: cannot listen there ({exc.strerror}); give an address of this "
                            "machine: 127.0.0.1 (this machine only) or 0.0.0.0 (every network interface)") from None


def _listen_address(host: str, port: int) -> tuple[socket.AddressFamily, Any]:
    """The socket family and address to bind for `host` (a name or an IPv4/IPv6 address); a clear error, naming
    --host, when the name does not resolve."""
    try:
        family, _, _, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    except (socket.gaierror, UnicodeError) as exc:
        reason = exc.strerror if isinstance(exc, socket.gaierror) else str(exc)
        raise StgcError(f"--host {host}: cannot resolve that host name ({reason}); give a name or address of "
                        "this machine: 127.0.0.1 (this machine only) or 0.0.0.0 (every network interface)") from None
    return family, address


def free_port(host: str = "127.0.0.1") -> int:
    family, address = _listen_address(host, 0)
    with _probe_socket(family) as probe:
        probe.bind(address)
        return int(probe.getsockname()[1])


def _probe_socket(family: socket.AddressFamily) -> socket.socket:
    """A socket to test-bind with as the viewer's server binds: with SO_REUSEADDR on POSIX, as viser's listener
    has. Without it a port that a stopped viewer's connections leave in TIME_WAIT (about a minute after a browser
    was connected) read as in use, and restarting `stgc view` on it was refused though its server could listen
    there; a port with a listener on it is refused either way. (On Windows SO_REUSEADDR would take a port that is
    listened on: not set there.)"""
    probe = socket.socket(family, socket.SOCK_STREAM)
    if os.name == "posix":
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    return probe


class _ClientView:
    """One browser's camera and its render loop (a thread): renders when the camera or the timeline changes,
    coarse while moving, full once still."""

    def __init__(self, viewer: Viewer, client: Any):
        self.viewer = viewer
        self.client = client
        self.snapped: tuple[str, np.ndarray, np.ndarray] | None = None  # (camera name, position, wxyz)
        self.changed_at = time.perf_counter()
        self.full_done = False
        self.changes = 0  # counts touches: a change during a draw makes that draw not the last one
        self.wake = threading.Event()
        self.closed = False
        self.last_render_s: float | None = None
        self.drawn: tuple[float, bool] | None = None  # (frame, full resolution) of the last image sent
        self.drawn_size: tuple[int, int] | None = None  # the (width, height) the browser reported for it
        client.camera.on_update(lambda _camera: self.touch(camera_moved=True))
        self.thread = threading.Thread(target=self._loop, name=f"stgc-view-{client.client_id}", daemon=True)
        self.thread.start()

    def touch(self, camera_moved: bool = False) -> None:
        """Draw again; a moving camera gets coarse images until it rests, a new frame on a still camera full ones."""
        if camera_moved:
            self.changed_at = time.perf_counter()
        self.changes += 1
        self.full_done = False
        self.wake.set()

    def snap(self, name: str) -> None:
        camera = self.viewer.scene.cameras[name]
        position, wxyz, fov = view_of_camera(camera)
        with self.client.atomic():
            self.client.camera.fov = fov
            self.client.camera.position = position
            self.client.camera.wxyz = wxyz
        self.snapped = (name, position, wxyz)
        self.touch(camera_moved=True)

    def snapped_name(self) -> str | None:
        """The dataset camera this browser shows, while its camera has not moved away from it."""
        if self.snapped is None:
            return None
        name, position, wxyz = self.snapped
        cam = self.client.camera
        same = (np.abs(np.asarray(cam.position) - position).max() <= POSE_TOLERANCE * max(1.0, np.abs(position).max())
                and min(np.abs(np.asarray(cam.wxyz) - wxyz).max(), np.abs(np.asarray(cam.wxyz) + wxyz).max())
                <= POSE_TOLERANCE)
        return name if same else None

    def _loop(self) -> None:
        while not self.closed:
            self.wake.wait(timeout=REST_SECONDS)
            self.wake.clear()
            if self.closed:
                return
            if self.full_done:
                continue
            try:
                self.draw()
            except Exception:  # a browser gone mid-render must not end the server
                log.debug("render for client %s failed", self.client.client_id, exc_info=True)

    def draw(self) -> None:
        changes = self.changes
        still = time.perf_counter() - self.changed_at >= REST_SECONDS
        viewer, scene = self.viewer, self.viewer.scene
        frame = viewer.frame
        cam = self.client.camera
        width, height = int(cam.image_width), int(cam.image_height)
        if width <= 0 or height <= 0:
            return
        name = self.snapped_name()
        t0 = time.perf_counter()
        if name is not None:
            dataset_camera = scene.dataset_camera(name, frame)
            rendered = scene.render(dataset_camera if still else dataset_camera.scaled(MOVING_PIXEL_SCALE), frame)
            numbers = scene.stats(frame, name, rendered if still else None)
            # The pair (render | ground truth) or the render alone, decided once for this frame, moving or still:
            # deciding apart (the pair's scale while moving, the pair at rest only where an image exists) made the
            # picture jump in size when the camera stopped between dataset frames.
            gt = scene.ground_truth(name, frame) if viewer.show_ground_truth else None
            pair = gt is not None and gt.shape == (dataset_camera.height, dataset_camera.width, 3)
            shown_width = dataset_camera.width * (2 if pair else 1)
            if pair and gt is not None:
                # While moving, the ground truth subsampled to the coarse render's size (a preview).
                step = 1 if still else round(1.0 / MOVING_PIXEL_SCALE)
                picture = np.concatenate([rendered, _fitted(gt[::step, ::step], rendered.shape, scene.background)],
                                         axis=1)
            else:
                picture = rendered
            # At rest every pixel exact; while moving padded so the browser shows it as large as at rest (an
            # upscaled coarse image would cost the encoding time the coarse render saves).
            image = (letterbox(picture, width, height, scene.background) if still
                     else pad_like_still(picture, shown_width, dataset_camera.height, width, height, scene.background))
        else:
            scale = min(1.0, viewer.max_side / max(width, height)) * (1.0 if still else MOVING_PIXEL_SCALE)
            w, h = max(1, round(width * scale)), max(1, round(height * scale))
            free = camera_from_view(cam.position, cam.wxyz, cam.fov, w, h, viewer.near)
            image = scene.render(free, frame)
            numbers = scene.stats(frame, None)
        self.last_render_s = time.perf_counter() - t0
        self.client.scene.set_background_image(image, format="png")
        viewer.show_stats(numbers, name, self.last_render_s, still)
        self.drawn = (frame, still)
        self.drawn_size = (width, height)
        self.full_done = still and changes == self.changes


class Viewer:
    """The viser server: the timeline, the camera list, play/pause, the numbers; one `_ClientView` per browser."""

    def __init__(self, scene: ViewerScene, host: str = "127.0.0.1", port: int = 8080, max_side: int | None = None):
        import viser

        check_port(host, port)
        self.scene = scene
        first = scene.segments[0].dataset
        any_camera = next(iter(scene.cameras.values()))
        self.near = float(any_camera.near)
        self.max_side = int(max_side or max(any_camera.width, any_camera.height))
        self.frame: float = float(scene.frames[0])
        self.playhead: float | None = None  # the exact playback position while playing
        self.show_ground_truth = False
        self.clients: dict[int, _ClientView] = {}
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.gui.configure_theme(control_width="large")
        gui = self.server.gui
        self.camera_menu = gui.add_dropdown("camera", [FREE_VIEW, *sorted(scene.cameras)], initial_value=FREE_VIEW,
                                            hint="snap to a dataset camera (test cameras are marked in the panel)")
        self.frame_slider = gui.add_slider("frame", min=scene.frames[0], max=scene.frames[-1], step=0.1,
                                           initial_value=scene.frames[0])
        self.play = gui.add_checkbox("play", initial_value=False)
        fps = float(first.fps)  # viser refuses an initial value outside the slider's range: the range holds it
        self.speed = gui.add_slider("frames per second", min=min(0.5, fps), max=max(60.0, fps), step=0.5,
                                    initial_value=fps)
        self.truth = gui.add_checkbox("ground truth", initial_value=False,
                                      hint="the dataset's image beside the render (at a dataset camera and frame)")
        self.numbers = gui.add_markdown("")
        self.camera_menu.on_update(lambda _e: self._on_camera_menu())
        self.frame_slider.on_update(lambda _e: self._on_frame())
        self.truth.on_update(lambda _e: self._on_truth())
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)
        self.closed = threading.Event()
        self.player = threading.Thread(target=self._playback, name="stgc-view-play", daemon=True)
        self.player.start()

    @property
    def url(self) -> str:
        host = self.server.get_host()
        if ":" in host and not host.startswith("["):
            # An IPv6 address goes in brackets (RFC 3986; a zone's % as %25): http://::1:8080 is not a URL.
            host = "[" + host.replace("%", "%25") + "]"
        return f"http://{host}:{self.server.get_port()}"

    def _connect(self, client: Any) -> None:
        view = _ClientView(self, client)
        self.clients[client.client_id] = view
        if self.camera_menu.value != FREE_VIEW:
            # A reloaded page comes back to the dataset camera the panel shows.
            threading.Thread(target=self._snap_when_ready, args=(view, self.camera_menu.value), daemon=True).start()

    def _snap_when_ready(self, view: _ClientView, name: str) -> None:
        """Snap a new page to `name` once its camera exists; snap again while its own first camera messages, which
        may arrive after the snap, move it away (for up to 10 s, until it has held still for a second)."""
        deadline = time.perf_counter() + 10.0
        while view.client.camera.update_timestamp == 0.0 and time.perf_counter() < deadline:
            time.sleep(0.02)
        view.snap(name)
        held_since = time.perf_counter()
        while time.perf_counter() < deadline and time.perf_counter() - held_since < 1.0 and not view.closed:
            time.sleep(0.05)
            if self.camera_menu.value != name:
                return  # the user chose another view meanwhile
            if view.snapped_name() != name:
                view.snap(name)
                held_since = time.perf_counter()

    def _disconnect(self, client: Any) -> None:
        view = self.clients.pop(client.client_id, None)
        if view is not None:
            view.closed = True
            view.wake.set()

    def _on_camera_menu(self) -> None:
        name = self.camera_menu.value
        for view in list(self.clients.values()):
            if name == FREE_VIEW:
                view.snapped = None
                view.touch()
            else:
                view.snap(name)

    def _on_frame(self) -> None:
        self.frame = float(self.frame_slider.value)
        if self.playhead is not None and round(self.playhead, 1) != self.frame:
            self.playhead = self.frame  # moved by hand while playing: play on from there
        for view in list(self.clients.values()):
            view.touch()

    def _on_truth(self) -> None:
        self.show_ground_truth = bool(self.truth.value)
        for view in list(self.clients.values()):
            view.touch()

    def _playback(self) -> None:
        last = time.perf_counter()
        while not self.closed.wait(1.0 / 30.0):
            now = time.perf_counter()
            self.advance(now - last)
            last = now

    def advance(self, seconds: float) -> None:
        """Move the timeline on by `seconds` of playback when playing. The playhead keeps its exact position; only
        the slider shows it rounded to its 0.1 step (rounding each tick would stall slow speeds and skew others)."""
        if not self.play.value:
            self.playhead = None
            return
        first, end = self.scene.frames[0], self.scene.frames[-1]
        start = self.frame if self.playhead is None else self.playhead
        self.playhead = first + (start + seconds * float(self.speed.value) - first) % (end - first + 1e-9)
        shown = round(self.playhead, 1)
        if shown != self.frame_slider.value:
            # viser's setter takes what its getter gives; mypy does not model such properties yet.
            self.frame_slider.value = shown  # type: ignore[misc]

    def show_stats(self, numbers: dict[str, Any], camera: str | None, seconds: float, still: bool) -> None:
        lines = [
            f"**frame** {numbers['frame']:.1f} (segment {numbers['segment']})",
            f"**Gaussians** {numbers['gaussians_alive']:,} alive of {numbers['gaussians']:,}",
            f"**size** {numbers['size_mb']:.3f} MiB ({numbers['size_kind']}), **{numbers['mbps']:.2f} Mbps**",
        ]
        if camera is not None:
            role = "test" if camera in self.scene.test_names else "training"
            score = "—" if numbers["psnr"] is None else f"{numbers['psnr']:.2f} dB"
            lines.append(f"**camera** {camera} ({role}), **PSNR** {score}")
        lines.append(f"render {seconds * 1000:.0f} ms ({'full' if still else 'moving: coarse'})")
        self.numbers.content = "  \n".join(lines)

    def wait(self) -> None:
        """Serve until Ctrl-C."""
        try:
            while not self.closed.wait(0.5):
                pass
        except KeyboardInterrupt:
            pass
        finally:
            self.stop()

    def stop(self) -> None:
        self.closed.set()
        for view in list(self.clients.values()):
            view.closed = True
            view.wake.set()
        self.server.stop()


def serve(source: str | Path, host: str = "127.0.0.1", port: int = 8080, max_side: int | None = None,
          on_ready: Callable[[Viewer], None] | None = None, bitstream: str | None = None,
          data_path: str | Path | None = None) -> None:
    """`stgc view`: open `source`, serve it at host:port until Ctrl-C."""
    try:
        import viser  # noqa: F401
    except ImportError:
        raise StgcError("the viewer needs viser: pip install 'stgc[viewer]'") from None
    scene = ViewerScene.open(source, bitstream, data_path)
    viewer = Viewer(scene, host=host, port=port, max_side=max_side)
    print(f"stgc view: {source} at {viewer.url} (Ctrl-C stops)", flush=True)
    if on_ready is not None:
        on_ready(viewer)
    viewer.wait()
