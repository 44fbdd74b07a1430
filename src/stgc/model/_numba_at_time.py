"""Numba CPU kernels for the Gaussians at time t (stg.py's formulas) and their hand-written backward.

A render needs, for the rows visible at t, the temporal opacity, the position, rotation and features at t and the
activated scales. As torch ops that is about fifty small ops forward and more backward (index_select and its
index_add, slices and their slice_backward, the opacity's where/exp/div chain), each over every row: at the 30k-100k
rows of a `cpu`-preset model each takes microseconds of arithmetic, but on 2 threads each is an OpenMP parallel
region, and with stgc's passive wait policy every region wakes a sleeping thread (about 75 us, RESULTS "Session
45"). Here the forward is two passes (every row's temporal opacity, then the visible rows' state) and the backward
one (every row's gradients, zero for the culled rows), each a single parallel region.

Each row is computed in float64 whatever the storage dtype and written back in it, except Delta = t - mu_t, computed
in the storage dtype with t rounded to it, as the torch formulas compute it: so Delta' and the exact 0 of a row at
t = mu_t (which decides what a row whose exp(s_t) underflows gets) are theirs. The math (Delta = t - mu_t;
Delta' is Delta without gradient; `cutoff` is stg._gaussian_cutoff of the storage dtype):
    x = Delta / exp(s_t); far = |x| > cutoff (NaN: not far); unit = far or exp(s_t) == 0
    x = 0 if far, Delta if unit, else Delta / exp(s_t);   factor = 0 if far else exp(-x^2)
    opacity = sigmoid(o) factor [opacity_scale];   visible = opacity >= threshold
    means = xyz + m[0:3] Delta' + m[3:6] Delta'^2 + m[6:9] Delta'^3,   quats = q + omega Delta'
    scales = exp(s),   features = [f_dc, Delta' f_t]
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

# error_model="numpy" everywhere: a division by an exp(s_t) that underflowed to 0 must give inf or NaN (which the
# guards below expect), not raise ZeroDivisionError as njit's default Python error model would outside a prange.


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _opacity_terms(delta, log_scale, logit, cutoff):
    """(sigmoid(o), factor, x, unit, far) of one row; delta = t - mu_t computed in the storage dtype."""
    scale = math.exp(log_scale)
    far = abs(delta / scale) > cutoff
    unit = far or scale == 0.0
    x = 0.0 if far else (delta if unit else delta / scale)
    factor = 0.0 if far else math.exp(-x * x)
    sig = 1.0 / (1.0 + math.exp(-logit))
    return sig, factor, x, unit, far


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def visible_rows(t, trbf_center, trbf_scale, opacity, opacity_scale, scaled, cutoff, threshold, values, slot):
    """values[i] = row i's temporal opacity (in the storage dtype); slot[i] = row i's index among the rows whose
    value is >= threshold (in row order; NaN: culled), -1 if culled. Returns how many are visible."""
    n = trbf_center.shape[0]
    for i in prange(n):
        sig, factor, _, _, _ = _opacity_terms(np.float64(t - trbf_center[i, 0]), np.float64(trbf_scale[i, 0]),
                                              np.float64(opacity[i, 0]), cutoff)  # fmt: skip
        value = sig * factor
        if scaled:
            value *= np.float64(opacity_scale[i])
        values[i] = value
    count = 0
    for i in range(n):
        if values[i] >= threshold:
            slot[i] = count
            count += 1
        else:
            slot[i] = -1
    return count


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def rows_forward(t, slot, values, xyz, scaling, rotation, omega, trbf_center, motion, features_dc, features_t,
                 index, means, quats, scales, visible_opacity, features):  # fmt: skip
    n = slot.shape[0]
    c_dc = features_dc.shape[1]
    c_t = features_t.shape[1]
    for i in prange(n):
        j = slot[i]
        if j < 0:
            continue
        index[j] = i
        visible_opacity[j] = values[i]
        d = np.float64(t - trbf_center[i, 0])
        d2 = d * d
        d3 = d2 * d
        for k in range(3):
            means[j, k] = (np.float64(xyz[i, k]) + np.float64(motion[i, k]) * d + np.float64(motion[i, 3 + k]) * d2
                           + np.float64(motion[i, 6 + k]) * d3)  # fmt: skip
            scales[j, k] = math.exp(np.float64(scaling[i, k]))
        for k in range(4):
            quats[j, k] = np.float64(rotation[i, k]) + np.float64(omega[i, k]) * d
        for k in range(c_dc):
            features[j, k] = features_dc[i, k]
        for k in range(c_t):
            features[j, c_dc + k] = np.float64(features_t[i, k]) * d


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def rows_backward(t, slot, scaling, opacity, trbf_center, trbf_scale, opacity_scale, scaled, cutoff,
                  g_means, g_quats, g_scales, g_opacity, g_features,
                  d_xyz, d_scaling, d_rotation, d_omega, d_opacity, d_center, d_log_scale, d_motion, d_dc, d_t,
                  d_opacity_scale):  # fmt: skip
    """Every row's gradients (exactly 0 for culled rows, as the torch formulas' index_select gives them)."""
    n = slot.shape[0]
    c_dc = d_dc.shape[1]
    c_t = d_t.shape[1]
    for i in prange(n):
        j = slot[i]
        if j < 0:
            for k in range(3):
                d_xyz[i, k] = 0.0
                d_scaling[i, k] = 0.0
            for k in range(4):
                d_rotation[i, k] = 0.0
                d_omega[i, k] = 0.0
            for k in range(9):
                d_motion[i, k] = 0.0
            for k in range(c_dc):
                d_dc[i, k] = 0.0
            for k in range(c_t):
                d_t[i, k] = 0.0
            d_opacity[i, 0] = 0.0
            d_center[i, 0] = 0.0
            d_log_scale[i, 0] = 0.0
            if scaled:
                d_opacity_scale[i] = 0.0
            continue
        d = np.float64(t - trbf_center[i, 0])
        d2 = d * d
        d3 = d2 * d
        for k in range(3):
            g = np.float64(g_means[j, k])
            d_xyz[i, k] = g
            d_motion[i, k] = g * d
            d_motion[i, 3 + k] = g * d2
            d_motion[i, 6 + k] = g * d3
            d_scaling[i, k] = np.float64(g_scales[j, k]) * math.exp(np.float64(scaling[i, k]))
        for k in range(4):
            g = np.float64(g_quats[j, k])
            d_rotation[i, k] = g
            d_omega[i, k] = g * d
        for k in range(c_dc):
            d_dc[i, k] = g_features[j, k]
        for k in range(c_t):
            d_t[i, k] = np.float64(g_features[j, c_dc + k]) * d
        sig, factor, x, unit, far = _opacity_terms(np.float64(t - trbf_center[i, 0]), np.float64(trbf_scale[i, 0]),
                                                   np.float64(opacity[i, 0]), cutoff)  # fmt: skip
        g = np.float64(g_opacity[j])
        if scaled:
            d_opacity_scale[i] = g * sig * factor
            g *= np.float64(opacity_scale[i])
        d_opacity[i, 0] = g * factor * sig * (1.0 - sig)
        if far:
            d_center[i, 0] = 0.0
            d_log_scale[i, 0] = 0.0
        else:
            g_x = g * sig * factor * (-2.0 * x)
            if unit:  # x = Delta: the scale is a constant 1
                d_center[i, 0] = -g_x
                d_log_scale[i, 0] = 0.0
            else:  # x = Delta / exp(s): dx/dmu = -1/exp(s), dx/ds = -x
                d_center[i, 0] = -g_x / math.exp(np.float64(trbf_scale[i, 0]))
                d_log_scale[i, 0] = -g_x * x
