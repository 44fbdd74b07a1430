"""The one canonical camera record used everywhere in stgc, and conversions into it.

Convention: OpenCV pinhole. World-to-camera `w2c` maps world points to camera coordinates with
x right, y down, z forward (looking along +z). `K` is the 3x3 intrinsic matrix in pixels where the
centre of the top-left pixel is at (0.5, 0.5) (the 3DGS/gsplat convention: a pixel (u, v) integer
index has its centre at (u + 0.5, v + 0.5)).

Each source format states its own axes and pixel convention; the `camera_from_*` / `*_to_w2c`
helpers below are the only places where those conventions are translated.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import cast

import numpy as np

# Where a view's pixels come from: an image file, or a callable that returns uint8 [H, W, 3] (a video frame).
ImageSource = Path | str | Callable[[], np.ndarray]

# The official STG rasterizers (and 3DGS, and Dynamic 3D Gaussians' fork) cull every Gaussian whose centre lies at
# view depth <= 0.2 (`in_frustum`). A format may state a larger one (SourceScene.near_plane); data.near_plane
# overrides both.
DEFAULT_NEAR_PLANE = 0.2


@dataclass(frozen=True, eq=False)
class Camera:
    """One view of one frame.

    name:   camera identifier as the dataset names it ("cam00", "v06", "3").
    frame:  absolute frame index in the source video.
    time:   normalised time of the frame within its segment, t = (frame - start) / duration.
    K:      float64 [3, 3] intrinsics.
    w2c:    float64 [4, 4] world-to-camera (OpenCV).
    width, height: image size in pixels (after any downscale).
    image:  where the pixels come from: a file path, or a callable returning uint8 [H, W, 3].
    near:   view depth at or below which a Gaussian's centre is culled when this camera renders.
    """

    name: str
    frame: int
    time: float
    K: np.ndarray
    w2c: np.ndarray
    width: int
    height: int
    image: ImageSource | None = field(default=None, repr=False)
    near: float = DEFAULT_NEAR_PLANE

    @property
    def c2w(self) -> np.ndarray:
        return np.linalg.inv(self.w2c)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates."""
        return w2c_center(self.w2c)

    def scaled(self, factor: float) -> Camera:
        """The same camera for an image resized by `factor` (pixel-centre preserving).

        The new size is rounded to whole pixels, so each axis of K is scaled by the ratio actually
        achieved (new_width / width, new_height / height): with corner-convention K this keeps every
        pixel's footprint exact even when the size does not divide evenly."""
        width = max(1, int(round(self.width * factor)))
        height = max(1, int(round(self.height * factor)))
        return self.resized(width, height)

    def resized(self, width: int, height: int) -> Camera:
        """The same camera for its image resampled to `width` x `height` pixels."""
        K = self.K.copy()
        K[0, :] *= width / self.width
        K[1, :] *= height / self.height
        return replace(self, K=K, width=int(width), height=int(height))

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points [M, 3] to pixel coordinates [M, 2] (corner convention) and depths [M]."""
        points = np.asarray(points, dtype=np.float64)
        cam = points @ self.w2c[:3, :3].T + self.w2c[:3, 3]
        depth = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (cam @ self.K.T)[:, :2] / depth[:, None]
        return uv, depth


# ---------------------------------------------------------------------------------------------
# Intrinsics


def intrinsics(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """Corner-convention pinhole K from its four numbers (no skew)."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=np.float64)


def opencv_to_corner_K(K: np.ndarray) -> np.ndarray:
    """An OpenCV-convention K (top-left pixel centre at (0, 0), e.g. Panoptic's) in our convention.

    The principal point moves by +0.5 px; the focal lengths are unchanged."""
    K = np.array(K, dtype=np.float64, copy=True)
    K[0, 2] += 0.5
    K[1, 2] += 0.5
    return K


def fov_to_focal(fov: float, size: float) -> float:
    """Focal length in pixels for a full field of view `fov` (radians) spanning `size` pixels."""
    return cast(float, 0.5 * size / np.tan(0.5 * fov))


# ---------------------------------------------------------------------------------------------
# Extrinsics: every format's pose to an OpenCV world-to-camera matrix

# Camera-axis changes expressed as matrices acting on camera coordinates.
_GL_TO_CV = np.diag([1.0, -1.0, -1.0])  # OpenGL (x right, y up, z back) -> OpenCV (x right, y down, z fwd)
# OMAF camera axes (x forward, y left, z up) -> OpenCV: x_cv = -y, y_cv = -z, z_cv = x.
_OMAF_TO_CV = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


def _w2c_from_c2w_rotation(R_c2w: np.ndarray, center: np.ndarray) -> np.ndarray:
    w2c = np.eye(4)
    w2c[:3, :3] = R_c2w.T
    w2c[:3, 3] = -R_c2w.T @ center
    return w2c


def opengl_c2w_to_w2c(c2w: np.ndarray) -> np.ndarray:
    """Blender / NeRF / D-NeRF camera-to-world (OpenGL camera axes) to OpenCV w2c."""
    c2w = np.asarray(c2w, dtype=np.float64)
    return _w2c_from_c2w_rotation(c2w[:3, :3] @ _GL_TO_CV, c2w[:3, 3])


def w2c_to_opengl_c2w(w2c: np.ndarray) -> np.ndarray:
    """Inverse of `opengl_c2w_to_w2c` (used by writers and tests)."""
    c2w_cv = np.linalg.inv(np.asarray(w2c, dtype=np.float64))
    c2w = np.eye(4)
    c2w[:3, :3] = c2w_cv[:3, :3] @ _GL_TO_CV
    c2w[:3, 3] = c2w_cv[:3, 3]
    return c2w


def llff_to_w2c(pose_3x5: np.ndarray) -> tuple[np.ndarray, tuple[float, float, float]]:
    """One LLFF / N3DV poses_bounds pose [3, 5] = [R (columns down, right, back) | t | (H, W, f)].

    Returns (OpenCV w2c, (H, W, focal)). OpenCV camera axes are (right, down, forward) =
    (col1, col0, -col2) of the LLFF rotation."""
    pose = np.asarray(pose_3x5, dtype=np.float64).reshape(3, 5)
    down, right, back = pose[:, 0], pose[:, 1], pose[:, 2]
    R_c2w = np.stack([right, down, -back], axis=1)
    h, w, f = pose[:, 4]
    return _w2c_from_c2w_rotation(R_c2w, pose[:, 3]), (float(h), float(w), float(f))


def w2c_to_llff(w2c: np.ndarray, height: float, width: float, focal: float) -> np.ndarray:
    """Inverse of `llff_to_w2c`: the [3, 5] LLFF pose block."""
    c2w = np.linalg.inv(np.asarray(w2c, dtype=np.float64))
    right, down, fwd = c2w[:3, 0], c2w[:3, 1], c2w[:3, 2]
    return np.stack([down, right, -fwd, c2w[:3, 3], np.array([height, width, focal])], axis=1)


def qvec_to_rotmat(qvec: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), COLMAP order, to a rotation matrix (normalises first)."""
    w, x, y, z = np.asarray(qvec, dtype=np.float64) / np.linalg.norm(qvec)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotmat_to_qvec(R: np.ndarray) -> np.ndarray:
    """Rotation matrix to a unit quaternion (w, x, y, z) with w >= 0 (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    trace = np.trace(R)
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    quat = np.array(q)
    quat /= np.linalg.norm(quat)
    return quat if quat[0] >= 0 else -quat


def colmap_to_w2c(qvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """COLMAP image pose (qvec wxyz, tvec), which is already an OpenCV world-to-camera transform."""
    w2c = np.eye(4)
    w2c[:3, :3] = qvec_to_rotmat(qvec)
    w2c[:3, 3] = np.asarray(tvec, dtype=np.float64)
    return w2c


# Number of parameters and the (fx, fy, cx, cy) positions of the pinhole part of COLMAP camera models.
# Distortion terms are ignored: the readers require undistorted images (checked by the caller).
COLMAP_MODELS: dict[str, tuple[int, int]] = {
    # name: (model id, number of params)
    "SIMPLE_PINHOLE": (0, 3),
    "PINHOLE": (1, 4),
    "SIMPLE_RADIAL": (2, 4),
    "RADIAL": (3, 5),
    "OPENCV": (4, 8),
    "OPENCV_FISHEYE": (5, 8),
    "FULL_OPENCV": (6, 12),
    "FOV": (7, 5),
    "SIMPLE_RADIAL_FISHEYE": (8, 4),
    "RADIAL_FISHEYE": (9, 5),
    "THIN_PRISM_FISHEYE": (10, 12),
}


def colmap_intrinsics(model: str, params: np.ndarray) -> tuple[np.ndarray, bool]:
    """K (corner convention, as COLMAP uses) from COLMAP camera params, and whether it has distortion.

    SIMPLE_* models share one focal f; PINHOLE/OPENCV-family and FOV store fx, fy, cx, cy first. The fisheye models
    are distorted whatever their coefficients: with all of them zero they still map by the equidistant angle
    theta = atan(r), which a pinhole K cannot express."""
    params = np.asarray(params, dtype=np.float64)
    fisheye = model.endswith("FISHEYE")
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE"):
        f, cx, cy = params[:3]
        K = intrinsics(f, f, cx, cy)
        distorted = fisheye or (model != "SIMPLE_PINHOLE" and bool(np.any(params[3:] != 0)))
    elif model in ("PINHOLE", "OPENCV", "OPENCV_FISHEYE", "FULL_OPENCV", "THIN_PRISM_FISHEYE", "FOV"):
        fx, fy, cx, cy = params[:4]
        K = intrinsics(fx, fy, cx, cy)
        distorted = fisheye or bool(np.any(params[4:] != 0))
    else:
        raise ValueError(f"unknown COLMAP camera model {model!r}")
    return K, distorted


def euler_zyx_deg(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Rz(yaw) · Ry(pitch) · Rx(roll), angles in degrees, right-handed rotations."""
    a, b, c = np.radians([yaw, pitch, roll])
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    Ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    Rx = np.array([[1, 0, 0], [0, np.cos(c), -np.sin(c)], [0, np.sin(c), np.cos(c)]])
    return cast(np.ndarray, Rz @ Ry @ Rx)


def omaf_to_w2c(position: np.ndarray, yaw_pitch_roll_deg: np.ndarray) -> np.ndarray:
    """MPEG OMAF / MIV camera (x forward, y left, z up) to OpenCV w2c.

    The OMAF camera-to-world rotation is Rz(yaw)·Ry(pitch)·Rx(roll); world coordinates are kept in the
    OMAF world frame. A camera-axis point p projects to u = cx − fx·p_y/p_x, v = cy − fy·p_z/p_x, which is
    the OpenCV projection of (−p_y, −p_z, p_x)."""
    R_c2w_omaf = euler_zyx_deg(*np.asarray(yaw_pitch_roll_deg, dtype=np.float64))
    R_c2w = R_c2w_omaf @ _OMAF_TO_CV.T
    return _w2c_from_c2w_rotation(R_c2w, np.asarray(position, dtype=np.float64))


def w2c_to_omaf(w2c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of `omaf_to_w2c`: (position, (yaw, pitch, roll) in degrees)."""
    c2w = np.linalg.inv(np.asarray(w2c, dtype=np.float64))
    R = c2w[:3, :3] @ _OMAF_TO_CV
    pitch = np.degrees(np.arcsin(np.clip(-R[2, 0], -1.0, 1.0)))
    yaw = np.degrees(np.arctan2(R[1, 0], R[0, 0]))
    roll = np.degrees(np.arctan2(R[2, 1], R[2, 2]))
    return c2w[:3, 3].copy(), np.array([yaw, pitch, roll])


# The projection ignores K[0, 1] (it renders with fx, fy, cx, cy alone), so a skew s places a pixel off by s * y / z.
# Below this fraction of the focal length that is under 0.001 x the image's half height in pixels (half a pixel at
# 1080 lines): calibration noise, accepted; above it the cameras would be silently wrong, refused.
_SKEW_TOLERANCE = 1e-3


def w2c_center(w2c: np.ndarray) -> np.ndarray:
    """The centre in world coordinates of the camera whose world-to-camera matrix is `w2c`."""
    return cast(np.ndarray, -w2c[:3, :3].T @ w2c[:3, 3])


def check_pose(w2c: np.ndarray, K: np.ndarray, tol: float = 1e-3) -> str | None:
    """A reason why (K, w2c) is not a usable pinhole camera, or None when it is.

    The bottom rows are checked because a matrix written column-major (transposed) is otherwise a valid one: a
    transposed rigid w2c has an orthonormal rotation, and its translation moves into the bottom row, where nothing
    reads it (every camera centre became the origin); a transposed K moves the principal point there."""
    if not (np.all(np.isfinite(w2c)) and np.all(np.isfinite(K))):
        return "non-finite (NaN or inf) value in the camera pose or intrinsics"
    problem = check_bottom_row(w2c, "pose w2c", tol)
    if problem:
        return problem
    R = w2c[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > tol or abs(np.linalg.det(R) - 1.0) > tol:
        return "camera rotation is not orthonormal with determinant +1"
    problem = check_bottom_row(K, "intrinsics K", tol)
    if problem:
        return problem
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        return "focal length is not positive"
    focal = max(abs(K[0, 0]), abs(K[1, 1]))
    if abs(K[1, 0]) > _SKEW_TOLERANCE * focal:
        return (f"intrinsics K[1, 0] is {K[1, 0]:g}, not 0 (an intrinsic matrix is upper triangular: written "
                "transposed?)")
    if abs(K[0, 1]) > _SKEW_TOLERANCE * focal:
        return (f"intrinsics K has skew K[0, 1] = {K[0, 1]:g}: stgc's cameras are pinholes without skew (the renderer "
                "uses fx, fy, cx, cy only); resample the images to a skew-free camera first")
    return None


def check_bottom_row(matrix: np.ndarray, what: str, tol: float = 1e-3) -> str | None:
    """A reason why the bottom row of a 4x4 pose or a 3x3 K is not [0, .., 0, 1] (a matrix written transposed, or
    not a rigid transform / intrinsic matrix at all), or None when it is."""
    matrix = np.asarray(matrix, dtype=np.float64)
    expected = np.zeros(matrix.shape[1])
    expected[-1] = 1.0
    if np.abs(matrix[-1] - expected).max() <= tol:
        return None
    row = ", ".join(f"{v:g}" for v in matrix[-1])
    want = ", ".join(f"{v:g}" for v in expected)
    return (f"{what} bottom row is [{row}], not [{want}] (written transposed? matrices are read row by row, "
            "as nested lists of rows)")
