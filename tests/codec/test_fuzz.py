"""Hostile input: seeded random mutations and truncations of a valid file must each end in a clean FormatError
or a valid model; never another exception, a crash, or a large allocation.

Raw mutations are mostly caught by the CRCs, so half of the cases re-seal every checksum after mutating (the way
docs/stgc-format.md defines them): those reach the structural checks behind the checksums."""

from __future__ import annotations

import struct
import tracemalloc
import zlib

import numpy as np
import pytest

from stgc.codec import decode, encode
from stgc.codec.format import DecodedModel, decode_metadata
from stgc.codec.synthetic import synthetic_model
from stgc.errors import FormatError

CASES = 1200
MEMORY_LIMIT = 32 << 20  # a 500-Gaussian file decodes in well under 1 MB; nothing may claim more than this

# Layout from docs/stgc-format.md (kept separate from the codec's own structs on purpose).
HEADER = struct.Struct("<8sHBBIHHII")
ENTRY = struct.Struct("<4sBBBBIII")
QPARAM_SIZE = 16
PREDICT = 8  # section flag: C(C-1)/2 int16 prediction coefficients follow the quantizers


def entry_size(entry) -> int:
    comps, flags = entry[3], entry[4]
    return ENTRY.size + comps * QPARAM_SIZE + (comps * (comps - 1) if flags & PREDICT else 0)


def reseal(data: bytearray) -> bytearray:
    """Recompute section, table and header CRC32s wherever the (possibly mutated) structure allows it."""
    if len(data) < 32:
        return data
    fields = list(HEADER.unpack_from(data))
    num_sections, table_size = fields[5], fields[7]
    table_end = 32 + table_size
    if table_end <= len(data):
        pos, payload = 32, table_end
        for _ in range(num_sections):
            if pos + ENTRY.size > table_end:
                break
            entry = list(ENTRY.unpack_from(data, pos))
            size = entry[6]
            if payload + size <= len(data):
                entry[7] = zlib.crc32(bytes(data[payload: payload + size]))
                ENTRY.pack_into(data, pos, *entry)
            payload += size
            pos += entry_size(entry)
        fields[8] = zlib.crc32(bytes(data[32:table_end]))
    HEADER.pack_into(data, 0, *fields)
    struct.pack_into("<I", data, 28, zlib.crc32(bytes(data[:28])))
    return data


def mutate(rng: np.random.Generator, data: bytes, table_end: int) -> bytearray:
    out = bytearray(data)
    kind = rng.integers(0, 7)
    if kind == 0:  # flip a few bits anywhere
        for _ in range(rng.integers(1, 6)):
            out[rng.integers(0, len(out))] ^= 1 << rng.integers(0, 8)
    elif kind == 1:  # overwrite bytes of the header / section table (counts, sizes, bit depths, quantizers)
        for _ in range(rng.integers(1, 4)):
            out[rng.integers(8, table_end)] = rng.integers(0, 256)
    elif kind == 2:  # an extreme value in a header or table integer
        pos = int(rng.integers(8, table_end - 4))
        out[pos: pos + 4] = struct.pack("<I", int(rng.choice([0, 1, 2**31 - 1, 2**32 - 1, 2**27, 10**6])))
    elif kind == 3:  # truncate
        del out[int(rng.integers(0, len(out))):]
    elif kind == 4:  # append or insert junk
        at = int(rng.integers(0, len(out) + 1))
        out[at:at] = rng.integers(0, 256, int(rng.integers(1, 40))).astype(np.uint8).tobytes()
    elif kind == 5:  # delete a slice
        a = int(rng.integers(0, len(out)))
        del out[a: a + int(rng.integers(1, 64))]
    else:  # scribble over a payload stretch
        a = int(rng.integers(table_end, len(out)))
        n = int(rng.integers(1, 16))
        out[a: a + n] = rng.integers(0, 256, len(out[a: a + n])).astype(np.uint8).tobytes()
    return out


@pytest.fixture(scope="module")
def valid_file() -> tuple[bytes, int]:
    arrays, decoder = synthetic_model(500, "full", seed=5)  # large enough for delta-coded positions
    data = encode(arrays, "full", decoder, metadata={"iteration": 7, "scene_extent": 2.5})
    table_size = HEADER.unpack_from(data)[7]
    return data, 32 + table_size


def _check_valid(model: DecodedModel) -> None:
    assert model.num_gaussians == len(model.arrays["x"]) <= 1 << 27
    for value in model.arrays.values():
        assert value.dtype == np.float32 and np.all(np.isfinite(value))
    for value in (model.decoder_state or {}).values():
        assert np.all(np.isfinite(value))


def test_unmodified_file_decodes(valid_file):
    _check_valid(decode(valid_file[0]))
    # The mutations below only reach the layouts this file uses: it must have delta, centred, predicted sections.
    flags = [e[4] for _, e in _entries(valid_file[0])]
    assert any(f & 1 for f in flags) and any(f & 4 for f in flags) and any(f & PREDICT for f in flags)


def test_random_mutations_end_in_format_error_or_a_valid_model(valid_file):
    data, table_end = valid_file
    rng = np.random.default_rng(20251122)
    outcomes = {"error": 0, "valid": 0}
    reasons = set()
    tracemalloc.start()
    try:
        for case in range(CASES):
            mutated = mutate(rng, data, table_end)
            if case % 2:
                mutated = reseal(mutated)
            tracemalloc.reset_peak()
            try:  # the metadata alone (how a file names its run): a FormatError at worst, like the whole decode
                metadata = decode_metadata(bytes(mutated))
            except FormatError:
                metadata = None
            try:
                model = decode(bytes(mutated))
            except FormatError as exc:
                outcomes["error"] += 1
                reasons.add(exc.problem.split(" ")[0])
            else:
                outcomes["valid"] += 1
                _check_valid(model)
                assert metadata == model.metadata
            peak = tracemalloc.get_traced_memory()[1]
            assert peak < MEMORY_LIMIT, f"case {case}: decoding allocated {peak} bytes"
    finally:
        tracemalloc.stop()
    assert outcomes["error"] > CASES // 2
    assert len(reasons) > 5  # resealed cases reach many different structural checks, not only the CRCs


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: d.__setitem__(slice(0, 4), b"PLY\n"), "magic"),
        (lambda d: struct.pack_into("<H", d, 8, 99), "version 99"),
        (lambda d: struct.pack_into("<I", d, 12, 2**32 - 1), "Gaussians"),
        (lambda d: struct.pack_into("<I", d, 12, 10**6), "does not match"),
        (lambda d: d.__setitem__(10, 7), "variant"),
    ],
)
def test_specific_header_lies_are_named(valid_file, edit, message):
    mutated = bytearray(valid_file[0])
    edit(mutated)
    with pytest.raises(FormatError, match=message):
        decode(bytes(reseal(mutated)))


def test_truncation_and_checksums_are_reported(valid_file):
    data, table_end = valid_file
    with pytest.raises(FormatError, match="shorter than"):
        decode(data[:20])
    with pytest.raises(FormatError, match="truncated"):
        decode(data[:-1])
    with pytest.raises(FormatError, match="trailing"):
        decode(data + b"\0")
    corrupted = bytearray(data)
    corrupted[-3] ^= 0x10
    with pytest.raises(FormatError, match="checksum"):
        decode(bytes(corrupted))


def test_a_zstd_bomb_claim_is_refused_before_decompression(valid_file):
    """N = 2**27 with every section size made consistent with it: the table alone shows the frames cannot expand
    that far, so nothing is decompressed or allocated."""
    data, _ = valid_file
    mutated = bytearray(data)
    n = 1 << 27
    struct.pack_into("<I", mutated, 12, n)
    pos = 32
    for _ in range(HEADER.unpack_from(mutated)[5]):
        entry = list(ENTRY.unpack_from(mutated, pos))
        tag, bits, comps = entry[0], entry[2], entry[3]
        if tag not in (b"DECO", b"META"):
            entry[5] = n * comps * (1 if bits <= 8 else 2 if bits <= 16 else 4)
            ENTRY.pack_into(mutated, pos, *entry)
        pos += entry_size(entry)
    tracemalloc.start()
    try:
        with pytest.raises(FormatError, match="more than zstd can expand"):
            decode(bytes(reseal(mutated)))
        assert tracemalloc.get_traced_memory()[1] < MEMORY_LIMIT
    finally:
        tracemalloc.stop()


def _entries(data: bytes):
    """(table offset, unpacked entry) of every section."""
    num_sections = HEADER.unpack_from(data)[5]
    pos, out = 32, []
    for _ in range(num_sections):
        entry = ENTRY.unpack_from(data, pos)
        out.append((pos, list(entry)))
        pos += entry_size(entry)
    return out


def _set_flags(data: bytes, tag: bytes, flags: int) -> bytes:
    out = bytearray(data)
    for pos, entry in _entries(data):
        if entry[0] == tag:
            entry[4] = flags
            ENTRY.pack_into(out, pos, *entry)
    return bytes(reseal(out))


def test_centred_sections_are_checked(valid_file):
    data, _ = valid_file
    with pytest.raises(FormatError, match="combines centring"):
        decode(_set_flags(data, b"MOTN", 1 | 4))  # centring and delta
    with pytest.raises(FormatError, match="combines centring"):
        decode(_set_flags(data, b"ROTN", 4))  # quaternion indices are not centred
    # A plain 8-bit section read as centred needs a 9-bit (uint16) container: the sizes disagree.
    arrays, decoder = synthetic_model(500, "full", seed=5)
    eight = encode(arrays, "full", decoder, group_bits={"OPAC": 8})  # opacity: plain at any depth
    plain = next(e for _, e in _entries(eight) if e[0] == b"OPAC")
    assert plain[4] & 5 == 0 and plain[2] == 8
    with pytest.raises(FormatError, match="does not match"):
        decode(_set_flags(eight, plain[0], plain[4] | 4))


def test_predicted_sections_are_checked(valid_file):
    data, _ = valid_file
    predicted = next(e for _, e in _entries(data) if e[4] & PREDICT)
    with pytest.raises(FormatError, match="predicted without being centred"):
        decode(_set_flags(data, predicted[0], predicted[4] & ~4))
    # Without the flag the coefficients are unexplained table bytes.
    with pytest.raises(FormatError, match="trailing bytes|runs? past|does not match"):
        decode(_set_flags(data, predicted[0], predicted[4] & ~PREDICT))
