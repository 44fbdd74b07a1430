"""The numeric building blocks, each checked against an independent construction."""

from __future__ import annotations

import numpy as np
import pytest

from stgc.codec.quantize import (
    container_dtype,
    delta_decode,
    delta_encode,
    dequantize,
    fit_quantizer,
    from_byte_planes,
    morton_codes,
    quantize,
    to_byte_planes,
)


@pytest.mark.parametrize("bits", [2, 5, 8, 11, 16, 24])
def test_quantizer_error_is_at_most_half_a_step_and_codes_fit(bits):
    rng = np.random.default_rng(bits)
    for values in (rng.normal(3.0, 2.0, 5000), rng.laplace(0, 0.1, 5000), rng.uniform(-7.5, -2.25, 5000)):
        q = fit_quantizer(values, bits)
        codes = quantize(values, q)
        assert codes.dtype == container_dtype(bits)
        assert int(codes.max()) < 2**bits
        err = np.abs(dequantize(codes, q) - values)
        assert err.max() <= q.step / 2 * (1 + 1e-9)
        # The step is set by the range: (max - min) / (2**bits - 2).
        assert q.step == pytest.approx((values.max() - values.min()) / (2**bits - 2))
        # A coarsened step (an encoder's choice for a less visible component) keeps both guarantees.
        for factor in (1.19, 2.0, 16.0):
            coarse = fit_quantizer(values, bits, coarsen=factor)
            codes = quantize(values, coarse)
            assert coarse.step == pytest.approx(q.step * factor) and int(codes.max()) < 2**bits
            assert np.abs(dequantize(codes, coarse) - values).max() <= coarse.step / 2 * (1 + 1e-9)
    with pytest.raises(ValueError, match="coarsen"):
        fit_quantizer(values, bits, coarsen=0.5)  # finer than the range allows: codes would not fit


def test_zero_and_constants_are_reproduced_exactly():
    rng = np.random.default_rng(0)
    values = np.concatenate([np.zeros(100), rng.normal(0.3, 1.0, 900)])
    q = fit_quantizer(values, 6)
    assert np.all(dequantize(quantize(values[:100], q), q) == 0.0)
    for constant in (0.0, 3.7, -1e-20, 2.5e30):
        v = np.full(10, constant, dtype=np.float32).astype(np.float64)
        q = fit_quantizer(v, 4)
        assert np.all(dequantize(quantize(v, q), q).astype(np.float32) == np.float32(constant))


def _morton_reference(x: int, y: int, z: int) -> int:
    code = 0
    for bit in range(21):
        code |= ((x >> bit) & 1) << (3 * bit) | ((y >> bit) & 1) << (3 * bit + 1) | ((z >> bit) & 1) << (3 * bit + 2)
    return code


def test_morton_codes_match_bitwise_interleaving():
    rng = np.random.default_rng(1)
    grid = rng.integers(0, 2**21, (200, 3))
    codes = morton_codes(grid, 21)
    assert [int(c) for c in codes] == [_morton_reference(*map(int, p)) for p in grid]
    # More than 21 bits per axis: the top 21 bits are used.
    grid24 = rng.integers(0, 2**24, (50, 3))
    assert np.array_equal(morton_codes(grid24, 24), morton_codes(grid24 >> 3, 21))


@pytest.mark.parametrize("bits", [3, 8, 13, 24])
def test_delta_coding_round_trips_and_makes_smooth_sequences_small(bits):
    rng = np.random.default_rng(bits)
    dtype = container_dtype(bits)
    codes = rng.integers(0, 2**bits, (3, 1000)).astype(dtype)
    assert np.array_equal(delta_decode(delta_encode(codes, bits), bits), codes)
    ramp = (np.arange(1000) % 2**bits).astype(dtype)[None]  # wraps around at 2**bits
    zig = delta_encode(ramp, bits)
    assert int(zig[0, 1:].max()) == 2  # +1 steps zigzag to 2, the wrap-around too
    # Any garbage decodes to in-range codes (the decoder relies on it).
    assert int(delta_decode(rng.integers(0, 2**bits, (2, 500)).astype(dtype), bits).max()) < 2**bits


@pytest.mark.parametrize("interleave", [False, True])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.uint32])
def test_byte_planes_round_trip_and_put_low_bytes_first(dtype, interleave):
    codes = np.arange(12, dtype=dtype).reshape(3, 4) + dtype(1) * (256 if dtype != np.uint8 else 0)
    raw = to_byte_planes(codes, interleave)
    assert len(raw) == codes.nbytes
    assert np.array_equal(from_byte_planes(raw, 3, 4, np.dtype(dtype), interleave), codes)
    expected_first = codes[0] if not interleave else codes[:, 0]
    first_plane = np.frombuffer(raw, np.uint8)[: len(expected_first)]
    assert np.array_equal(first_plane, (expected_first & 0xFF).astype(np.uint8))


def test_zigzag_and_centring_round_trip():
    from stgc.codec.quantize import centre_encode, unzigzag, zigzag

    signed = np.arange(-300, 300)
    assert np.array_equal(unzigzag(zigzag(signed)), signed)
    assert list(zigzag(np.array([0, -1, 1, -2, 2]))) == [0, 1, 2, 3, 4]
    rng = np.random.default_rng(3)
    for bits in (2, 7, 8, 16):
        codes = rng.integers(0, 2**bits, (3, 400)).astype(container_dtype(bits))
        stored, centre = centre_encode(codes, bits)
        assert stored.dtype == container_dtype(bits + 1) and int(stored.max()) < 2 ** (bits + 1)
        assert np.array_equal(unzigzag(stored) + centre[:, None], codes.astype(np.int64))
        assert np.array_equal(centre, np.round(np.median(codes, axis=1)))


def test_prediction_round_trips_any_input_and_keeps_the_centred_range():
    from stgc.codec.quantize import fit_prediction, predict_decode, predict_encode

    rng = np.random.default_rng(4)
    for bits in (2, 7, 12):
        half = 2**bits
        signed = rng.integers(-half, half, (4, 500))
        coefficients = np.tril(rng.integers(-40000, 40000, (4, 4)), -1).clip(-32767, 32767)
        residual = predict_encode(signed, coefficients, bits)
        assert residual.min() >= -half and residual.max() < half  # wraps: no extra bit needed
        assert np.array_equal(predict_decode(residual, coefficients, bits), signed)
        # Corrupted residuals (anything in the container) still decode into the centred range.
        junk = predict_decode(rng.integers(-half, half, (4, 500)), coefficients, bits)
        assert junk.min() >= -half and junk.max() < half
        assert fit_prediction(signed).shape == (4, 4)


def test_fitted_prediction_recovers_a_linear_relation_and_skips_unrelated_rows():
    from stgc.codec.quantize import PREDICTION_SHIFT, fit_prediction, predict_encode

    rng = np.random.default_rng(5)
    first = rng.integers(-100, 100, 3000)
    second = np.rint(0.75 * first + rng.normal(0, 1.0, 3000)).astype(np.int64)  # 3/4 of the first, plus noise
    unrelated = rng.integers(-100, 100, 3000)
    coefficients = fit_prediction(np.stack([first, second, unrelated]))
    assert abs(coefficients[1, 0] - 0.75 * 2**PREDICTION_SHIFT) <= 2
    assert np.all(np.triu(coefficients) == 0)
    residual = predict_encode(np.stack([first, second, unrelated]), coefficients, 8)
    assert np.abs(residual[1]).mean() < 1.0 < np.abs(second).mean() / 10
    assert np.all(coefficients[2] == 0)  # a prediction that would not shrink the residuals is not used
