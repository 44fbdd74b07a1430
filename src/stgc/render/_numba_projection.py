"""Numba CPU kernels for the EWA projection (stgc.render.projection's math) and its hand-written backward.

One pass per Gaussian instead of the few dozen small torch ops (and their autograd nodes) the torch projection
builds: on CPU, at the 10k-50k Gaussians of a training iteration, those ops cost more in dispatch than in
arithmetic. Each Gaussian is computed in float64 whatever the storage dtype (the work per Gaussian is tiny) and
written back in the storage dtype. The forward saves nothing per Gaussian: the backward recomputes the few
intermediates it needs, which is cheaper than storing and reloading them.

The math (conventions in projection.py's docstring):
    mc = Rv m + tv;  z = mc.z if near < mc.z < far else 1 (culled: a harmless stand-in)
    x_c = z clamp(mc.x / z, -lim_x-, lim_x+), y_c likewise
    J Rv = [[fx/z Rv0 - fx x_c/z^2 Rv2], [fy/z Rv1 - fy y_c/z^2 Rv2]]   (2x3)
    M = (J Rv) R(q / |q|),  A = M diag(s),  cov2d = A A^T + eps2d I
    conic = (c11, -c01, c00) / max(det, 1e-10),  means2d = K[:2] mc / z
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .projection import ALPHA_MIN, DET_MIN, MAX_RADIUS, RADIUS_SIGMAS, jacobian_limits

# Layout of `camera` (float64): viewmat rotation (row-major 9), translation (3), K rows 0 and 1 (6),
# clamp limits (lim_x-, lim_x+, lim_y-, lim_y+), eps2d, near, far.
CAM_R, CAM_T, CAM_K, CAM_LIM, CAM_EPS, CAM_NEAR, CAM_FAR = 0, 9, 12, 18, 22, 23, 24
CAMERA_SIZE = 25


@njit(cache=True, nogil=True, inline="always")
def _rotation(qw, qx, qy, qz, R):
    R[0, 0] = 1.0 - 2.0 * (qy * qy + qz * qz)
    R[0, 1] = 2.0 * (qx * qy - qw * qz)
    R[0, 2] = 2.0 * (qx * qz + qw * qy)
    R[1, 0] = 2.0 * (qx * qy + qw * qz)
    R[1, 1] = 1.0 - 2.0 * (qx * qx + qz * qz)
    R[1, 2] = 2.0 * (qy * qz - qw * qx)
    R[2, 0] = 2.0 * (qx * qz - qw * qy)
    R[2, 1] = 2.0 * (qy * qz + qw * qx)
    R[2, 2] = 1.0 - 2.0 * (qx * qx + qy * qy)


@njit(cache=True, nogil=True, inline="always")
def _camera_frame(means, g, cam):
    """(x, y, z_raw) of Gaussian g in the camera frame."""
    mx, my, mz = means[g, 0], means[g, 1], means[g, 2]
    x = cam[0] * mx + cam[1] * my + cam[2] * mz + cam[9]
    y = cam[3] * mx + cam[4] * my + cam[5] * mz + cam[10]
    z = cam[6] * mx + cam[7] * my + cam[8] * mz + cam[11]
    return x, y, z


@njit(cache=True, nogil=True, inline="always")
def _jacobian_rows(x, y, z, cam, JW):
    """JW = J Rv (2x3) at the clamped camera-space mean; returns (x_c, y_c, x clamped?, y clamped?)."""
    fx = cam[CAM_K + 0]
    fy = cam[CAM_K + 4]
    rx = x / z
    ry = y / z
    x_clamped = rx < -cam[CAM_LIM + 0] or rx > cam[CAM_LIM + 1]
    y_clamped = ry < -cam[CAM_LIM + 2] or ry > cam[CAM_LIM + 3]
    x_c = z * min(max(rx, -cam[CAM_LIM + 0]), cam[CAM_LIM + 1])
    y_c = z * min(max(ry, -cam[CAM_LIM + 2]), cam[CAM_LIM + 3])
    inv_z = 1.0 / z
    u0 = fx * inv_z
    v0 = fx * x_c * inv_z * inv_z
    u1 = fy * inv_z
    v1 = fy * y_c * inv_z * inv_z
    for k in range(3):
        JW[0, k] = u0 * cam[CAM_R + k] - v0 * cam[CAM_R + 6 + k]
        JW[1, k] = u1 * cam[CAM_R + 3 + k] - v1 * cam[CAM_R + 6 + k]
    return x_c, y_c, x_clamped, y_clamped


@njit(parallel=True, cache=True, nogil=True)
def project_forward(means, quats, scales, opacities, cam, width, height, means2d, conics, depths, radii):
    """Fill means2d [N,2], conics [N,3], depths [N] (raw camera z) and radii [N,2] int32 (0 = culled)."""
    n = means.shape[0]
    eps2d = cam[CAM_EPS]
    near = cam[CAM_NEAR]
    far = cam[CAM_FAR]
    for g in prange(n):
        JW = np.empty((2, 3))
        R = np.empty((3, 3))
        x, y, z_raw = _camera_frame(means, g, cam)
        in_depth = (z_raw > near) and (z_raw < far)
        z = z_raw if in_depth else 1.0
        _jacobian_rows(x, y, z, cam, JW)
        qw, qx, qy, qz = quats[g, 0], quats[g, 1], quats[g, 2], quats[g, 3]
        qn = max(math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz), 1e-12)
        _rotation(qw / qn, qx / qn, qy / qn, qz / qn, R)
        c00 = eps2d
        c11 = eps2d
        c01 = 0.0
        for j in range(3):
            s = scales[g, j]
            a0 = (JW[0, 0] * R[0, j] + JW[0, 1] * R[1, j] + JW[0, 2] * R[2, j]) * s
            a1 = (JW[1, 0] * R[0, j] + JW[1, 1] * R[1, j] + JW[1, 2] * R[2, j]) * s
            c00 += a0 * a0
            c11 += a1 * a1
            c01 += a0 * a1
        det_raw = c00 * c11 - c01 * c01
        det = max(det_raw, DET_MIN)
        conics[g, 0] = c11 / det
        conics[g, 1] = -c01 / det
        conics[g, 2] = c00 / det
        px = (cam[CAM_K + 0] * x + cam[CAM_K + 1] * y + cam[CAM_K + 2] * z_raw) / z
        py = (cam[CAM_K + 3] * x + cam[CAM_K + 4] * y + cam[CAM_K + 5] * z_raw) / z
        means2d[g, 0] = px
        means2d[g, 1] = py
        depths[g] = z_raw
        # The opacity-aware screen box (projection._screen_radii).
        o = opacities[g]
        radii[g, 0] = 0
        radii[g, 1] = 0
        if not (in_depth and det_raw > DET_MIN and o >= ALPHA_MIN):  # (projection._screen_radii: why DET_MIN)
            continue
        extent = min(math.sqrt(2.0 * math.log(max(o, ALPHA_MIN) * 255.0)), RADIUS_SIGMAS)
        # Capped before rounding up: ceil of a float beyond 2^63 wraps to a negative int64 (the Gaussian vanished).
        rx = math.ceil(min(extent * math.sqrt(max(c00, 0.0)), MAX_RADIUS))
        ry = math.ceil(min(extent * math.sqrt(max(c11, 0.0)), MAX_RADIUS))
        if not (math.isfinite(px) and math.isfinite(py)):
            continue
        if (rx > 0 or ry > 0) and px + rx > 0 and px - rx < width and py + ry > 0 and py - ry < height:
            radii[g, 0] = int(rx)
            radii[g, 1] = int(ry)


@njit(parallel=True, cache=True, nogil=True)
def project_backward(means, quats, scales, cam, grad_means2d, grad_conics, grad_means, grad_quats, grad_scales):
    """dL/d(means, quats, scales) from dL/d(means2d, conics), by the chain rule through the forward above."""
    n = means.shape[0]
    eps2d = cam[CAM_EPS]
    near = cam[CAM_NEAR]
    far = cam[CAM_FAR]
    fx = cam[CAM_K + 0]
    fy = cam[CAM_K + 4]
    for g in prange(n):
        JW = np.empty((2, 3))
        R = np.empty((3, 3))
        M = np.empty((2, 3))
        dM = np.empty((2, 3))
        dR = np.empty((3, 3))
        x, y, z_raw = _camera_frame(means, g, cam)
        in_depth = (z_raw > near) and (z_raw < far)
        z = z_raw if in_depth else 1.0
        x_c, y_c, x_clamped, y_clamped = _jacobian_rows(x, y, z, cam, JW)
        qw, qx, qy, qz = quats[g, 0], quats[g, 1], quats[g, 2], quats[g, 3]
        qn = max(math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz), 1e-12)
        w, xq, yq, zq = qw / qn, qx / qn, qy / qn, qz / qn
        _rotation(w, xq, yq, zq, R)
        c00 = eps2d
        c11 = eps2d
        c01 = 0.0
        for j in range(3):
            M[0, j] = JW[0, 0] * R[0, j] + JW[0, 1] * R[1, j] + JW[0, 2] * R[2, j]
            M[1, j] = JW[1, 0] * R[0, j] + JW[1, 1] * R[1, j] + JW[1, 2] * R[2, j]
            a0 = M[0, j] * scales[g, j]
            a1 = M[1, j] * scales[g, j]
            c00 += a0 * a0
            c11 += a1 * a1
            c01 += a0 * a1
        det_raw = c00 * c11 - c01 * c01
        ga = grad_conics[g, 0]
        gb = grad_conics[g, 1]
        gc = grad_conics[g, 2]
        # conic = (c11, -c01, c00) / det
        if det_raw >= DET_MIN:
            det = det_raw
            inv = 1.0 / det
            inv2 = inv * inv
            # d det / d(c00, c11, c01) = (c11, c00, -2 c01); gsum = dL/d(1/det) * ... collected per term
            g_det = -(ga * c11 - gb * c01 + gc * c00) * inv2
            g00 = gc * inv + g_det * c11
            g11 = ga * inv + g_det * c00
            g01 = -gb * inv + g_det * (-2.0 * c01)
        else:
            inv = 1.0 / DET_MIN
            g00 = gc * inv
            g11 = ga * inv
            g01 = -gb * inv
        # cov2d entries -> A -> (M, s)
        for j in range(3):
            s = scales[g, j]
            a0 = M[0, j] * s
            a1 = M[1, j] * s
            dA0 = 2.0 * a0 * g00 + a1 * g01
            dA1 = 2.0 * a1 * g11 + a0 * g01
            dM[0, j] = dA0 * s
            dM[1, j] = dA1 * s
            grad_scales[g, j] = dA0 * M[0, j] + dA1 * M[1, j]
        # M = JW R: dJW = dM R^T, dR = JW^T dM
        dJW00 = dM[0, 0] * R[0, 0] + dM[0, 1] * R[0, 1] + dM[0, 2] * R[0, 2]
        dJW01 = dM[0, 0] * R[1, 0] + dM[0, 1] * R[1, 1] + dM[0, 2] * R[1, 2]
        dJW02 = dM[0, 0] * R[2, 0] + dM[0, 1] * R[2, 1] + dM[0, 2] * R[2, 2]
        dJW10 = dM[1, 0] * R[0, 0] + dM[1, 1] * R[0, 1] + dM[1, 2] * R[0, 2]
        dJW11 = dM[1, 0] * R[1, 0] + dM[1, 1] * R[1, 1] + dM[1, 2] * R[1, 2]
        dJW12 = dM[1, 0] * R[2, 0] + dM[1, 1] * R[2, 1] + dM[1, 2] * R[2, 2]
        for a in range(3):
            for b in range(3):
                dR[a, b] = JW[0, a] * dM[0, b] + JW[1, a] * dM[1, b]
        # R(q_normalised) -> q_normalised
        dw = 2.0 * (-zq * dR[0, 1] + yq * dR[0, 2] + zq * dR[1, 0] - xq * dR[1, 2] - yq * dR[2, 0] + xq * dR[2, 1])
        dx = 2.0 * (yq * dR[0, 1] + zq * dR[0, 2] + yq * dR[1, 0] - 2.0 * xq * dR[1, 1] - w * dR[1, 2]
                    + zq * dR[2, 0] + w * dR[2, 1] - 2.0 * xq * dR[2, 2])  # fmt: skip
        dy = 2.0 * (-2.0 * yq * dR[0, 0] + xq * dR[0, 1] + w * dR[0, 2] + xq * dR[1, 0] + zq * dR[1, 2]
                    - w * dR[2, 0] + zq * dR[2, 1] - 2.0 * yq * dR[2, 2])  # fmt: skip
        dz = 2.0 * (-2.0 * zq * dR[0, 0] - w * dR[0, 1] + xq * dR[0, 2] + w * dR[1, 0] - 2.0 * zq * dR[1, 1]
                    + yq * dR[1, 2] + xq * dR[2, 0] + yq * dR[2, 1])  # fmt: skip
        # normalisation: dq = (dqn - qn (qn . dqn)) / |q|
        proj = w * dw + xq * dx + yq * dy + zq * dz
        grad_quats[g, 0] = (dw - w * proj) / qn
        grad_quats[g, 1] = (dx - xq * proj) / qn
        grad_quats[g, 2] = (dy - yq * proj) / qn
        grad_quats[g, 3] = (dz - zq * proj) / qn
        # JW rows = u Rv_i - v Rv2 with u = f/z, v = f x_c / z^2
        du0 = dJW00 * cam[CAM_R + 0] + dJW01 * cam[CAM_R + 1] + dJW02 * cam[CAM_R + 2]
        dv0 = -(dJW00 * cam[CAM_R + 6] + dJW01 * cam[CAM_R + 7] + dJW02 * cam[CAM_R + 8])
        du1 = dJW10 * cam[CAM_R + 3] + dJW11 * cam[CAM_R + 4] + dJW12 * cam[CAM_R + 5]
        dv1 = -(dJW10 * cam[CAM_R + 6] + dJW11 * cam[CAM_R + 7] + dJW12 * cam[CAM_R + 8])
        inv_z = 1.0 / z
        d_inv_z = fx * du0 + 2.0 * fx * x_c * inv_z * dv0 + fy * du1 + 2.0 * fy * y_c * inv_z * dv1
        d_xc = fx * inv_z * inv_z * dv0
        d_yc = fy * inv_z * inv_z * dv1
        d_z = -d_inv_z * inv_z * inv_z
        d_x = 0.0
        d_y = 0.0
        # x_c = z clamp(x / z): identity in x inside the limits, z times the bound outside
        if x_clamped:
            d_z += d_xc * (x_c / z)
        else:
            d_x += d_xc
        if y_clamped:
            d_z += d_yc * (y_c / z)
        else:
            d_y += d_yc
        # means2d = K[:2] mc / z (mc.z unclamped in the numerator)
        gx = grad_means2d[g, 0]
        gy = grad_means2d[g, 1]
        px = (cam[CAM_K + 0] * x + cam[CAM_K + 1] * y + cam[CAM_K + 2] * z_raw) / z
        py = (cam[CAM_K + 3] * x + cam[CAM_K + 4] * y + cam[CAM_K + 5] * z_raw) / z
        d_x += (gx * cam[CAM_K + 0] + gy * cam[CAM_K + 3]) * inv_z
        d_y += (gx * cam[CAM_K + 1] + gy * cam[CAM_K + 4]) * inv_z
        d_zraw = (gx * cam[CAM_K + 2] + gy * cam[CAM_K + 5]) * inv_z
        d_z += -(gx * px + gy * py) * inv_z
        if in_depth:
            d_zraw += d_z
        # mc = Rv m + tv
        for k in range(3):
            grad_means[g, k] = cam[CAM_R + k] * d_x + cam[CAM_R + 3 + k] * d_y + cam[CAM_R + 6 + k] * d_zraw


def camera_array(K: np.ndarray, viewmat: np.ndarray, width: int, height: int, eps2d: float, near: float,
                 far: float) -> np.ndarray:
    """The `camera` vector the kernels read (float64)."""
    cam = np.zeros(CAMERA_SIZE, dtype=np.float64)
    cam[CAM_R:CAM_R + 9] = viewmat[:3, :3].reshape(-1)
    cam[CAM_T:CAM_T + 3] = viewmat[:3, 3]
    cam[CAM_K:CAM_K + 6] = K[:2, :3].reshape(-1)
    cam[CAM_LIM:CAM_LIM + 4] = jacobian_limits(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                                               width, height)
    cam[CAM_EPS] = eps2d
    cam[CAM_NEAR] = near
    cam[CAM_FAR] = far
    return cam
