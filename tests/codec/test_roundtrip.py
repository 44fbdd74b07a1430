"""Encode/decode round trips on synthetic models with trained-model statistics: documented error bounds per
attribute, exact zeros, ordering, sizes, the fp16 decoder, and input validation."""

from __future__ import annotations

import numpy as np
import pytest

from stgc.codec import (
    DEFAULT_QUALITY,
    QUALITY_LEVELS,
    canonical_rotation,
    decode,
    encode,
)
from stgc.codec.format import GROUPS, HEADER_SIZE, SPAN_SIGMAS, decode_metadata, groups_for, time_span
from stgc.codec.synthetic import synthetic_model
from stgc.errors import DataError
from stgc.model.layout import bytes_per_gaussian, ply_fields

from .helpers import match_rows, sigmoid, steps

N = 4000


@pytest.fixture(scope="module")
def models():
    return {variant: synthetic_model(N, variant, seed=7) for variant in ("full", "lite")}


@pytest.fixture(scope="module")
def round_trips(models):
    out = {}
    for variant, (arrays, decoder) in models.items():
        for quality in QUALITY_LEVELS:
            data = encode(arrays, variant, decoder, quality)
            decoded = decode(data)
            out[variant, quality] = (data, decoded, match_rows(arrays, decoded.arrays))
    return out


def _float32_slack(values: np.ndarray) -> np.ndarray:
    return 2.0 * np.finfo(np.float32).eps * np.abs(values)


@pytest.mark.parametrize("variant", ["full", "lite"])
@pytest.mark.parametrize("quality", QUALITY_LEVELS)
def test_every_attribute_is_within_its_documented_bound(models, round_trips, variant, quality):
    arrays, _ = models[variant]
    _, decoded, index = round_trips[variant, quality]
    out = {k: v[index].astype(np.float64) for k, v in decoded.arrays.items()}
    assert list(decoded.arrays) == ply_fields(variant)
    assert all(v.dtype == np.float32 and v.shape == (N,) for v in decoded.arrays.values())
    step = steps(decoded)
    span = time_span(out["trbf_center"], out["trbf_scale"])
    for group in groups_for(variant):
        tag = group.tag.decode()
        if tag in ("OPAC", "ROTN", "OMGA"):
            continue
        powers = group.span_powers or (0,) * len(group.fields(variant))
        for field, s, power in zip(group.fields(variant), step[tag], powers):
            orig = arrays[field].astype(np.float64)
            # Time-span groups bound the error of coefficient * span**power (the displacement while visible).
            err = np.abs(out[field] - orig) * span**power
            assert np.all(err <= s / 2 + _float32_slack(orig * span**power)), (field, err.max(), s / 2)
    # Opacity: bounded in the sigmoid domain, the quantity that is blended.
    err = np.abs(sigmoid(out["opacity"]) - sigmoid(arrays["opacity"]))
    assert err.max() <= step["OPAC"][0] / 2 + 1e-6
    # Rotation and omega: against the canonical (unit, largest component positive) pair; the three stored
    # components are within step/2, the reconstructed largest one within 3 steps/2 (first order).
    rot = np.stack([arrays[f"rot_{i}"] for i in range(4)], 1).astype(np.float64)
    omega = np.stack([arrays[f"omega_{i}"] for i in range(4)], 1).astype(np.float64)
    rot_c, omega_c = canonical_rotation(rot, omega)
    rot_d = np.stack([out[f"rot_{i}"] for i in range(4)], 1)
    omega_d = np.stack([out[f"omega_{i}"] for i in range(4)], 1)
    assert np.abs(rot_d - rot_c).max() <= 2 * max(step["ROTN"][:3])
    assert np.allclose(np.linalg.norm(rot_d, axis=1), 1.0, atol=1e-6)
    for i in range(4):
        err = np.abs(omega_d[:, i] - omega_c[:, i]) * span
        assert np.all(err <= step["OMGA"][i] / 2 + _float32_slack(omega_c[:, i] * span))
    assert all(np.all(decoded.arrays[n] == 0) for n in ("nx", "ny", "nz"))


@pytest.mark.parametrize("quality", QUALITY_LEVELS)
def test_trajectory_error_is_bounded_while_the_gaussian_is_visible(models, round_trips, quality):
    """The guarantee behind the time-span scaling, checked on the trajectories themselves: at every frame time
    where a Gaussian's temporal opacity is at least exp(-SPAN_SIGMAS**2), its decoded cubic trajectory is within
    the sum over the three powers p of step/2 * max(1, max(|mu|, |1 - mu|))**p of the original one (per axis),
    whatever its lifetime (docs/stgc-format.md §2.2; the factor is 1 for mu in [0, 1])."""
    arrays, _ = models["full"]
    _, decoded, index = round_trips["full", quality]
    out = {k: v[index].astype(np.float64) for k, v in decoded.arrays.items()}
    step = steps(decoded)["MOTN"]
    mu, scale = out["trbf_center"], np.exp(out["trbf_scale"])
    reach = np.maximum(1.0, np.maximum(np.abs(mu), np.abs(1.0 - mu)))
    checked = 0
    for t in np.linspace(0.0, 1.0, 41):
        dt = t - mu
        visible = np.abs(dt) <= SPAN_SIGMAS * scale
        checked += int(visible.sum())
        for axis in range(3):
            def shift(a, dt=dt, axis=axis):
                return sum(a[f"motion_{axis + 3 * k}"].astype(np.float64) * dt ** (k + 1) for k in range(3))
            err = np.abs(shift(out) - shift(arrays))[visible]
            bound = sum(step[axis + 3 * k] / 2 * reach ** (k + 1) for k in range(3))[visible]
            assert np.all(err <= bound * (1 + 1e-6) + 1e-9), (t, axis, np.max(err / bound, initial=0.0))
    assert checked > N  # the synthetic lifetimes leave many Gaussians visible at many times


def test_a_trajectory_centred_outside_the_sequence_errs_by_its_reach_to_the_power():
    """The span is clipped to 1, so a Gaussian whose trbf_center mu lies outside [0, 1] is seen at |dt| up to
    max(|mu|, |1 - mu|) > 1: with each coefficient 0.49 step off the grid (same sign) its trajectory error exceeds
    the sum of the powers' step/2 (the bound docs/stgc-format.md stated) and stays within each power's step/2 times
    that reach to the power (the bound it states now)."""
    from stgc.codec import simulate_quantization
    from stgc.codec.format import quantized_groups

    arrays = {k: v.copy() for k, v in synthetic_model(500, "full", seed=4)[0].items()}
    arrays["trbf_center"][0], arrays["trbf_scale"][0] = -0.6, 1.0  # fades in before the first frame, never out
    step = [q.step for q in next(g for g in quantized_groups(arrays, "full") if g.tag == "MOTN").quantizers]
    for power in range(3):
        arrays[f"motion_{3 * power}"][0] = (np.round(0.01 / step[3 * power]) + 0.49) * step[3 * power]
    assert [q.step for q in next(g for g in quantized_groups(arrays, "full") if g.tag == "MOTN").quantizers] == step
    out = simulate_quantization(arrays, "full")  # what decoding the file gives (tested below)
    mu = float(out["trbf_center"][0])
    dt = np.linspace(0.0, 1.0, 101) - mu
    assert -0.61 < mu < -0.59 and SPAN_SIGMAS * np.exp(float(out["trbf_scale"][0])) > 1.0 - mu  # seen throughout
    err = np.abs(sum((float(out[f"motion_{3 * k}"][0]) - float(arrays[f"motion_{3 * k}"][0])) * dt ** (k + 1)
                     for k in range(3)))
    reach = max(abs(mu), abs(1.0 - mu))
    assert err.max() > 1.5 * sum(step[3 * k] / 2 for k in range(3))
    assert err.max() <= sum(step[3 * k] / 2 * reach ** (k + 1) for k in range(3)) * (1 + 1e-6)


def test_canonical_rotation_changes_no_rotation_at_any_time():
    rng = np.random.default_rng(3)
    rot, omega = rng.normal(size=(500, 4)) * rng.uniform(0.2, 3, (500, 1)), rng.normal(0, 0.3, (500, 4))
    rot_c, omega_c = canonical_rotation(rot, omega)
    assert np.allclose(np.linalg.norm(rot_c, axis=1), 1.0)
    assert np.all(rot_c[np.arange(500), np.argmax(np.abs(rot_c), axis=1)] > 0)
    for dt in (-0.7, 0.0, 0.4):
        a = rot + omega * dt
        b = rot_c + omega_c * dt
        a /= np.linalg.norm(a, axis=1, keepdims=True)
        b /= np.linalg.norm(b, axis=1, keepdims=True)
        assert np.allclose(np.abs(np.sum(a * b, axis=1)), 1.0)  # same rotation (q and -q are the same)



def test_a_zero_quaternion_with_a_spin_keeps_its_rotation():
    # The official error-guided sampling writes q = 0; with omega != 0 it renders normalize(omega * dt), which a unit
    # q must reproduce at every dt != 0 (it used to decode as the identity).
    rng = np.random.default_rng(4)
    rot, omega = np.zeros((50, 4)), rng.normal(0, 0.5, (50, 4))
    rot_c, omega_c = canonical_rotation(rot, omega)
    assert np.allclose(np.linalg.norm(rot_c, axis=1), 1.0)
    for dt in (-1.0, -0.3, 0.2, 1.0):
        a = omega * dt
        b = rot_c + omega_c * dt
        a /= np.linalg.norm(a, axis=1, keepdims=True)
        b /= np.linalg.norm(b, axis=1, keepdims=True)
        assert np.allclose(np.abs(np.sum(a * b, axis=1)), 1.0)
    untouched, _ = canonical_rotation(np.zeros((1, 4)), np.zeros((1, 4)))
    assert not untouched.any()


def test_rendered_quantities_stay_close_at_the_default_quality(models, round_trips):
    arrays, _ = models["full"]
    _, decoded, index = round_trips["full", DEFAULT_QUALITY]
    out = {k: v[index].astype(np.float64) for k, v in decoded.arrays.items()}
    a = {k: v.astype(np.float64) for k, v in arrays.items()}
    for t in (0.0, 0.5, 1.0):
        # temporal opacity sigmoid(o) * exp(-((t - mu_t) / exp(s_t))^2)
        def temporal(p):
            return sigmoid(p["opacity"]) * np.exp(-(((t - p["trbf_center"]) / np.exp(p["trbf_scale"])) ** 2))

        assert np.abs(temporal(out) - temporal(a)).max() < 0.03
        # 7-bit opacity alone gives an RMS error of step/sqrt(12) ~ 0.0023; the temporal factor adds a little.
        assert np.sqrt(np.mean((temporal(out) - temporal(a)) ** 2)) < 5e-3


def test_static_gaussians_stay_exactly_static(models, round_trips):
    arrays, _ = models["full"]
    _, decoded, index = round_trips["full", 1]  # even at the coarsest level
    zero_omega = np.all([arrays[f"omega_{i}"] == 0 for i in range(4)], axis=0)
    assert zero_omega.sum() > N // 2
    for i in range(4):
        assert np.all(decoded.arrays[f"omega_{i}"][index][zero_omega] == 0.0)


def test_higher_quality_costs_more_bytes_and_gives_smaller_errors(models, round_trips):
    arrays, _ = models["full"]
    sizes = [len(round_trips["full", q][0]) for q in QUALITY_LEVELS]
    assert sizes == sorted(sizes) and len(set(sizes)) == len(sizes)
    errors = []
    for q in QUALITY_LEVELS:
        _, decoded, index = round_trips["full", q]
        out = {k: v[index].astype(np.float64) for k, v in decoded.arrays.items()}
        span = time_span(out["trbf_center"], out["trbf_scale"])  # motion_0's error, as a displacement while visible
        errors.append(np.max(np.abs(out["motion_0"] - arrays["motion_0"]) * span))
        errors.append(np.max(np.abs(out["x"] - arrays["x"])))
    assert errors[0::2] == sorted(errors[0::2], reverse=True)
    assert errors[1::2] == sorted(errors[1::2], reverse=True)


@pytest.mark.parametrize("variant", ["full", "lite"])
def test_default_quality_is_at_least_8x_smaller_than_float32_ply_rows(variant):
    n = 50_000
    arrays, decoder = synthetic_model(n, variant, seed=0)
    data = encode(arrays, variant, decoder)
    ratio = n * bytes_per_gaussian(variant) / len(data)
    assert ratio >= 8.0, f"{variant}: {len(data) / n:.2f} B/Gaussian, {ratio:.2f}x"


def test_gaussians_are_stored_in_morton_order(round_trips):
    _, decoded, _ = round_trips["lite", DEFAULT_QUALITY]
    xyz = np.stack([decoded.arrays[a] for a in "xyz"], 1).astype(np.float64)
    # Consecutive stored Gaussians are much closer than random pairs: the order has locality.
    consecutive = np.linalg.norm(np.diff(xyz, axis=0), axis=1).mean()
    shuffled = np.linalg.norm(np.diff(xyz[np.random.default_rng(0).permutation(len(xyz))], axis=0), axis=1).mean()
    assert consecutive < 0.25 * shuffled


def test_decoder_weights_come_back_at_half_precision(models, round_trips):
    _, decoder = models["full"]
    _, decoded, _ = round_trips["full", DEFAULT_QUALITY]
    assert set(decoded.decoder_state) == set(decoder)
    for name, w in decoder.items():
        got = decoded.decoder_state[name]
        assert got.shape == w.shape and got.dtype == np.float32
        assert np.array_equal(got, w.astype(np.float16).astype(np.float32))
    assert round_trips["lite", DEFAULT_QUALITY][1].decoder_state is None


def test_decoder_weights_beyond_half_range_are_kept_in_float32(models):
    arrays, decoder = models["full"]
    big = dict(decoder, **{"mlp2.weight": decoder["mlp2.weight"] * 1e6})
    decoded = decode(encode(arrays, "full", big, 2))
    assert np.array_equal(decoded.decoder_state["mlp2.weight"], big["mlp2.weight"])


def test_header_reports_counts_and_sizes(round_trips):
    data, decoded, _ = round_trips["full", DEFAULT_QUALITY]
    h = decoded.header
    assert (h.variant, h.quality, h.num_gaussians, h.file_size) == ("full", DEFAULT_QUALITY, N, len(data))
    assert h.bytes_per_gaussian == pytest.approx(len(data) / N)
    assert sum(h.section_bytes().values()) < len(data) - HEADER_SIZE
    assert {s.tag for s in h.sections} == {g.tag.decode() for g in GROUPS} | {"DECO"}


def test_encoding_is_deterministic_and_metadata_round_trips(models):
    arrays, decoder = models["lite"]
    meta = {"iteration": 3000, "note": "ünïcode"}
    a = encode(arrays, "lite", None, 2, metadata=meta)
    assert a == encode(arrays, "lite", None, 2, metadata=meta)
    assert decode(a).metadata == meta
    assert decode_metadata(a) == meta  # read alone, without the Gaussians
    assert decode_metadata(encode(arrays, "lite", None, 2)) == {}


def test_tiny_and_degenerate_models_round_trip():
    arrays, decoder = synthetic_model(1, "full", seed=1)
    decoded = decode(encode(arrays, "full", decoder))
    for k in ("x", "opacity", "motion_4"):
        assert decoded.arrays[k][0] == pytest.approx(arrays[k][0], abs=1e-6)
    empty = {k: v[:0] for k, v in arrays.items()}
    assert decode(encode(empty, "full", decoder)).num_gaussians == 0
    # A zero quaternion (official error-guided sampling creates them) decodes to a valid unit quaternion.
    zero_rot = {k: v.copy() for k, v in synthetic_model(10, "lite", seed=2)[0].items()}
    for i in range(4):
        zero_rot[f"rot_{i}"][0] = 0.0
    out = decode(encode(zero_rot, "lite", None)).arrays
    assert np.allclose(np.linalg.norm(np.stack([out[f"rot_{i}"] for i in range(4)], 1), axis=1), 1.0, atol=1e-6)


def test_a_span_of_a_few_ulps_round_trips_and_what_cannot_be_stored_is_refused_when_encoding():
    """Opacity logits far out differ by float64 ulps after the sigmoid: the quantizer's zero point must stay within
    the 2**53 the decoder accepts (it was written, then refused on decoding). Values whose quantizer would reach
    beyond float32 are refused by the encoder, never written as a file the decoder refuses; a range within it is
    stored (the decoder bounds the codes' values exactly: version 2 wrote and read +-3e38, a bound 3x too loose
    refused it)."""
    from stgc.codec import simulate_quantization

    arrays = {k: v.copy() for k, v in synthetic_model(3, "lite", seed=4)[0].items()}
    arrays["opacity"] = np.array([20.0, 20.000002, 20.000004], np.float32)
    decoded = decode(encode(arrays, "lite", None)).arrays
    simulated = simulate_quantization(arrays, "lite")
    assert sorted(decoded["opacity"].tolist()) == sorted(simulated["opacity"].tolist())
    assert sigmoid(decoded["opacity"]) == pytest.approx(sigmoid(arrays["opacity"]), abs=1e-6)
    wide = dict(arrays, x=np.array([-3e38, 0.0, 3e38], np.float32))
    assert decode(encode(wide, "lite", None)).arrays["x"] == pytest.approx(wide["x"], rel=1e-3)
    # +-float32 max needs a code one step beyond it (the grid is snapped to multiples of the step)
    top = np.finfo(np.float32).max
    with pytest.raises(DataError, match="cannot be stored"):
        encode(dict(arrays, x=np.array([-top, 0.0, top], np.float32)), "lite", None)


def test_bad_input_is_refused_with_a_clear_error(models):
    arrays, decoder = models["lite"]
    with pytest.raises(DataError, match="non-finite"):
        encode(dict(arrays, opacity=np.where(np.arange(N) == 5, np.nan, arrays["opacity"])), "lite", None)
    with pytest.raises(DataError, match="lack"):
        encode({k: v for k, v in arrays.items() if k != "motion_3"}, "lite", None)
    with pytest.raises(DataError, match="values"):
        encode(dict(arrays, x=arrays["x"][:-1]), "lite", None)
    with pytest.raises(DataError, match="decoder"):
        encode(models["full"][0], "full", None)
    with pytest.raises(ValueError, match="quality"):
        encode(arrays, "lite", None, 9)
    with pytest.raises(ValueError, match="bit depth"):
        encode(arrays, "lite", None, position_bits=30)
    with pytest.raises(ValueError, match="unknown groups"):
        encode(arrays, "lite", None, group_bits={"NOPE": 3})
    with pytest.raises(ValueError, match="one factor per stored component"):
        encode(arrays, "lite", None, step_scales={"FDC_": [1.0] * 6})  # lite has 3 colour components
    with pytest.raises(ValueError, match="one factor per stored component"):
        encode(arrays, "lite", None, step_scales={"ROTN": [1.0] * 4})  # the index row is not scaled


def test_step_scales_coarsen_exactly_the_components_named(models):
    from stgc.codec.format import read_header

    arrays, _ = models["lite"]
    base = {s.tag: s for s in read_header(encode(arrays, "lite", None)).sections}
    scaled = {s.tag: s for s in read_header(encode(arrays, "lite", None, step_scales={
        "MOTN": [1, 1, 1, 2, 2, 2, 8, 8, 8], "ROTN": [2.0, 2.0, 2.0]})).sections}
    for tag, factors in (("MOTN", [1, 1, 1, 2, 2, 2, 8, 8, 8]), ("ROTN", [2.0, 2.0, 2.0, 1.0])):
        for q0, q1, f in zip(base[tag].quantizers, scaled[tag].quantizers, factors):
            assert q1.step == pytest.approx(q0.step * f)
    assert scaled["MOTN"].payload_size < base["MOTN"].payload_size


def test_outlier_guard_keeps_the_bulk_precise_when_one_gaussian_is_far_out(models):
    arrays, _ = models["lite"]
    stretched = {k: v.copy() for k, v in arrays.items()}
    stretched["x"][0] = 5e3  # a floater ~1000 scene extents away
    stretched["motion_0"][1] = 40.0  # and one absurd velocity, on a Gaussian seen all the time (span 1)
    stretched["trbf_center"][1], stretched["trbf_scale"][1] = 0.0, 3.0
    errors, bits = {}, {}
    for guard in (False, True):
        decoded = decode(encode(stretched, "lite", None, outlier_guard=guard))
        index = match_rows(stretched, decoded.arrays)
        bits[guard] = {s.tag: s.bits for s in decoded.header.sections}
        out = {k: v[index].astype(np.float64) for k, v in decoded.arrays.items()}
        weight = {"x": 1.0, "motion_0": time_span(out["trbf_center"], out["trbf_scale"])[2:]}  # displacements
        errors[guard] = {k: (np.abs(out[k][2:] - stretched[k][2:]) * weight[k]).max() for k in ("x", "motion_0")}
        assert abs(float(decoded.arrays["x"][index][0]) - 5e3) <= steps(decoded)["POSI"][0] / 2 + 1e-3
    assert bits[True]["POSI"] > bits[False]["POSI"] and bits[True]["MOTN"] > bits[False]["MOTN"]
    assert errors[True]["x"] < errors[False]["x"] / 20
    assert errors[True]["motion_0"] < errors[False]["motion_0"] / 5  # (guarded step <= 4x the central-range step)
    # Without outliers the guard changes nothing (the synthetic tails are heavy but bounded).
    plain = decode(encode(arrays, "lite", None))
    motion = next(g for g in GROUPS if g.tag == b"MOTN")
    assert {s.tag: s.bits for s in plain.header.sections}["MOTN"] == motion.bits_by_quality[DEFAULT_QUALITY - 1]


def test_centred_layout_is_used_where_components_peak_apart_and_decodes_identically(models):
    from stgc.codec.format import FLAG_CENTRED, read_header

    arrays, decoder = models["full"]
    shifted = dict(arrays)
    rng = np.random.default_rng(11)
    for i in range(9):  # most Gaussians still, each coefficient's range lopsided differently: zero at varied codes
        coefficient = np.where(rng.random(N) < 0.7, 0.0, rng.laplace(0.0, 0.05, N))
        coefficient[:3] = [-(0.3 + 0.2 * i), 1.5 - 0.1 * i, 0.01]
        shifted[f"motion_{i}"] = coefficient.astype(np.float32)
    centred = encode(shifted, "full", decoder)
    plain = encode(shifted, "full", decoder, adaptive_delta=False)
    flags = {s.tag: s.flags for s in read_header(centred).sections}
    assert flags["MOTN"] & FLAG_CENTRED
    assert len(centred) < len(plain)
    a, b = decode(centred).arrays, decode(plain).arrays
    for name in ply_fields("full"):
        assert np.array_equal(a[name], b[name]), name


def test_predicted_layout_is_used_where_components_correlate_and_decodes_identically(models):
    from stgc.codec.format import FLAG_CENTRED, FLAG_PREDICT, read_header

    arrays, decoder = models["full"]
    assert np.corrcoef(arrays["f_dc_0"], arrays["f_dc_1"])[0, 1] > 0.9  # albedo channels share brightness
    predicted = encode(arrays, "full", decoder)
    sections = {s.tag: s for s in read_header(predicted).sections}
    fdc = sections["FDC_"]
    assert fdc.flags & FLAG_PREDICT and fdc.flags & FLAG_CENTRED
    assert len(fdc.prediction) == 15 and fdc.prediction[0] > 0  # f_dc_1 predicted from f_dc_0, positively
    plain = encode(arrays, "full", decoder, adaptive_delta=False)
    assert fdc.payload_size < {s.tag: s for s in read_header(plain).sections}["FDC_"].payload_size
    a, b = decode(predicted).arrays, decode(plain).arrays
    for name in ply_fields("full"):
        assert np.array_equal(a[name], b[name]), name


@pytest.mark.parametrize("variant", ["full", "lite"])
def test_simulated_quantization_is_exactly_what_decoding_the_file_gives(models, variant):
    """What training that sees the codec uses: decode(encode(x)) without the entropy coding, in x's own order;
    with the ladder, an allocation's depths and step shapes, and the outlier guard."""
    from stgc.codec import simulate_quantization

    arrays, decoder = models[variant]
    options = [dict(quality=1), dict(quality=4, position_bits=16),
               dict(quality=3, group_bits={"MOTN": 5, "SCAL": 6}, step_scales={"ROTN": [1.0, 2.0, 1.5]})]
    for option in options:
        simulated = simulate_quantization(arrays, variant, **option)
        decoded = decode(encode(arrays, variant, decoder if variant == "full" else None, **option)).arrays
        order = match_rows(arrays, decoded)  # decoded row of each input row (the file is in Morton order)
        for name in ply_fields(variant):
            assert simulated[name].dtype == np.float32
            np.testing.assert_array_equal(simulated[name], decoded[name][order], err_msg=f"{option} {name}")


def test_a_quantization_memo_changes_no_result_and_serves_only_its_arrays(models):
    """The rd allocation's trials share a memo of per-group results: with it, every call must give what it gives
    without, whichever groups change between calls (TCEN and TSCL change the span the motion groups are scaled by)."""
    from stgc.codec.format import QuantizationMemo, section_payload_bytes, simulate_quantization

    arrays, _ = models["full"]
    memo = QuantizationMemo(arrays)
    settings = [dict(group_bits={"MOTN": 5}), dict(group_bits={"TCEN": 6}), dict(group_bits={"TSCL": 4, "MOTN": 5}),
                dict(group_bits={"MOTN": 5}), dict(group_bits={"POSI": 11}, step_scales={"FDC_": [1, 2, 1, 1, 4, 1]}),
                dict(quality=1), dict(group_bits={"MOTN": 5})]
    for option in settings * 2:  # the second pass is served from the memo
        alone = simulate_quantization(arrays, "full", **option)
        shared = simulate_quantization(arrays, "full", memo=memo, **option)
        for name in ply_fields("full"):
            np.testing.assert_array_equal(shared[name], alone[name], err_msg=f"{option} {name}")
            shared[name][:] = 0  # a caller may write into what it gets: the memo keeps its own copy
        for tag in ("POSI", "MOTN", "FDC_"):
            assert section_payload_bytes(arrays, "full", tag, memo=memo, **option) == \
                section_payload_bytes(arrays, "full", tag, **option)
    with pytest.raises(ValueError, match="only the arrays it was made for"):
        simulate_quantization(dict(arrays), "full", memo=memo)
