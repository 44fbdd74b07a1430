"""Camera conversions, checked against independent constructions (scipy rotations, explicit formulas)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stgc.data.cameras import (
    Camera,
    colmap_intrinsics,
    colmap_to_w2c,
    euler_zyx_deg,
    intrinsics,
    llff_to_w2c,
    omaf_to_w2c,
    opencv_to_corner_K,
    opengl_c2w_to_w2c,
    qvec_to_rotmat,
    rotmat_to_qvec,
    w2c_to_llff,
    w2c_to_omaf,
    w2c_to_opengl_c2w,
)

rng = np.random.default_rng(3)


def random_w2c() -> np.ndarray:
    w2c = np.eye(4)
    w2c[:3, :3] = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
    w2c[:3, 3] = rng.normal(size=3)
    return w2c


def test_quaternion_matches_scipy_and_round_trips():
    for _ in range(20):
        R = Rotation.random(random_state=int(rng.integers(1 << 30)))
        x, y, z, w = R.as_quat()  # scipy: scalar last
        assert np.allclose(qvec_to_rotmat([w, x, y, z]), R.as_matrix(), atol=1e-12)
        q = rotmat_to_qvec(R.as_matrix())
        assert q[0] >= 0
        assert np.allclose(qvec_to_rotmat(q), R.as_matrix(), atol=1e-12)
    # Shepperd branches: rotations by pi about each axis have trace -1.
    for axis in np.eye(3):
        R = Rotation.from_rotvec(np.pi * axis).as_matrix()
        assert np.allclose(qvec_to_rotmat(rotmat_to_qvec(R)), R, atol=1e-12)


def test_opengl_c2w_looks_along_minus_z():
    # An OpenGL camera at (0, 0, 5) with identity rotation looks down -z: the origin is in front, centred,
    # and the world +y axis is up in the image (smaller v).
    c2w = np.eye(4)
    c2w[2, 3] = 5.0
    cam = Camera("c", 0, 0.0, intrinsics(100, 100, 50, 40), opengl_c2w_to_w2c(c2w), 100, 80)
    uv, depth = cam.project(np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]))
    assert depth[0] == pytest.approx(5.0)
    assert np.allclose(uv[0], [50, 40])
    assert uv[1, 1] < 40 and uv[2, 0] > 50
    w2c = random_w2c()
    assert np.allclose(opengl_c2w_to_w2c(w2c_to_opengl_c2w(w2c)), w2c, atol=1e-12)


def test_llff_axes_and_round_trip():
    # LLFF columns (down, right, back): for a camera whose back axis is world +z, right is +x and down is -y.
    pose = np.zeros((3, 5))
    pose[:, 0] = [0, -1, 0]  # down
    pose[:, 1] = [1, 0, 0]  # right
    pose[:, 2] = [0, 0, 1]  # back
    pose[:, 3] = [0, 0, 4]
    pose[:, 4] = [80, 100, 90]
    w2c, (h, w, f) = llff_to_w2c(pose)
    assert (h, w, f) == (80, 100, 90)
    # Same camera as OpenGL c2w with identity rotation at (0, 0, 4).
    c2w = np.eye(4)
    c2w[2, 3] = 4
    assert np.allclose(w2c, opengl_c2w_to_w2c(c2w))
    w2c = random_w2c()
    back, _ = llff_to_w2c(w2c_to_llff(w2c, 10, 20, 30))
    assert np.allclose(back, w2c, atol=1e-12)


def test_colmap_pose_and_models():
    w2c = random_w2c()
    assert np.allclose(colmap_to_w2c(rotmat_to_qvec(w2c[:3, :3]), w2c[:3, 3]), w2c, atol=1e-12)
    K, distorted = colmap_intrinsics("SIMPLE_PINHOLE", [100, 50, 40])
    assert np.allclose(K, intrinsics(100, 100, 50, 40)) and not distorted
    K, distorted = colmap_intrinsics("PINHOLE", [100, 110, 50, 40])
    assert np.allclose(K, intrinsics(100, 110, 50, 40)) and not distorted
    K, distorted = colmap_intrinsics("OPENCV", [100, 110, 50, 40, 0, 0, 0, 0])
    assert np.allclose(K, intrinsics(100, 110, 50, 40)) and not distorted
    _, distorted = colmap_intrinsics("OPENCV", [100, 110, 50, 40, 0.1, 0, 0, 0])
    assert distorted
    # A fisheye stays a fisheye with zero coefficients (equidistant mapping), and FOV stores fx, fy, cx, cy.
    for model, params in (("OPENCV_FISHEYE", [100, 110, 50, 40, 0, 0, 0, 0]), ("SIMPLE_RADIAL_FISHEYE", [100, 50, 40, 0]),
                          ("RADIAL_FISHEYE", [100, 50, 40, 0, 0])):
        assert colmap_intrinsics(model, params)[1], model
    K, distorted = colmap_intrinsics("FOV", [100, 110, 50, 40, 0])
    assert np.allclose(K, intrinsics(100, 110, 50, 40)) and not distorted


def test_omaf_projection_formula():
    # The brief's OMAF projection: a camera-axis point p maps to u = cx - fx p_y / p_x, v = cy - fy p_z / p_x,
    # with camera-to-world rotation Rz(yaw) Ry(pitch) Rx(roll). Check against that formula directly.
    fx, fy, cx, cy = 300.0, 310.0, 160.0, 90.0
    for _ in range(10):
        position = rng.normal(size=3)
        ypr = rng.uniform(-60, 60, size=3)
        cam = Camera("v", 0, 0.0, intrinsics(fx, fy, cx, cy), omaf_to_w2c(position, ypr), 320, 180)
        R = euler_zyx_deg(*ypr)
        p_cam = rng.normal(size=(50, 3)) + [5, 0, 0]  # in front (x forward)
        world = p_cam @ R.T + position
        uv, depth = cam.project(world)
        assert np.allclose(depth, p_cam[:, 0])
        assert np.allclose(uv[:, 0], cx - fx * p_cam[:, 1] / p_cam[:, 0])
        assert np.allclose(uv[:, 1], cy - fy * p_cam[:, 2] / p_cam[:, 0])
        pos2, ypr2 = w2c_to_omaf(cam.w2c)
        assert np.allclose(pos2, position) and np.allclose(ypr2, ypr)
    # Yaw is a right-handed turn about +z (up): yaw 90 deg looks along +y (left).
    cam = Camera("v", 0, 0.0, intrinsics(fx, fy, cx, cy), omaf_to_w2c([0, 0, 0], [90, 0, 0]), 320, 180)
    assert cam.project(np.array([[0.0, 5.0, 0.0]]))[1][0] == pytest.approx(5.0)


def test_opencv_K_shift_and_resizing():
    K = opencv_to_corner_K(intrinsics(100, 100, 49.5, 39.5))
    assert K[0, 2] == 50 and K[1, 2] == 40
    cam = Camera("c", 0, 0.0, intrinsics(100, 100, 50, 40), np.eye(4), 100, 80)
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (50, 40)
    assert np.allclose(half.K, intrinsics(50, 50, 25, 20))
    # A point projecting to the centre of pixel (i, j) maps to the centre of the block-averaged pixel.
    odd = Camera("c", 0, 0.0, intrinsics(100, 100, 50.5, 40), np.eye(4), 101, 80).scaled(1 / 3)
    assert (odd.width, odd.height) == (34, 27)
    assert odd.K[0, 0] == pytest.approx(100 * 34 / 101) and odd.K[1, 1] == pytest.approx(100 * 27 / 80)
