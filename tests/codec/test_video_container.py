"""The whole-video container (docs/stgc-format.md §9): each segment's bitstream unchanged behind an index, read
one segment at a time; and hostile containers (seeded mutations, half with every checksum resealed) end in a
clean FormatError or valid segments, within a bounded allocation."""

from __future__ import annotations

import struct
import tracemalloc
import zlib

import numpy as np
import pytest

from stgc.codec import (
    decode,
    decode_video,
    encode,
    encode_video,
    is_video_stgc,
    read_stgc,
    read_video_index,
    read_video_segment,
)
from stgc.codec.synthetic import synthetic_model
from stgc.errors import FormatError

# Layout from docs/stgc-format.md §9 (kept separate from the codec's own structs on purpose).
HEADER = struct.Struct("<8sHHIIII")  # + u32 header CRC = 32 bytes
ENTRY = struct.Struct("<IIQQII")
CASES = 600
MEMORY_LIMIT = 32 << 20


@pytest.fixture(scope="module")
def segments() -> list[tuple[int, int, bytes]]:
    """Three consecutive segments (frames 10-14, 15-19, 20-21), each a different model's .stgc."""
    out = []
    for k, (first, count) in enumerate([(10, 5), (15, 5), (20, 2)]):
        arrays, decoder = synthetic_model(120 + 40 * k, "full" if k != 1 else "lite", seed=k)
        out.append((first, count, encode(arrays, "full" if k != 1 else "lite", decoder if k != 1 else None,
                                         metadata={"iteration": k})))
    return out


def test_the_container_holds_each_segment_bitstream_unchanged_behind_its_index(segments, tmp_path):
    data = encode_video(segments)
    # Header + index by the spec's own layout: offsets follow each other, lengths are the segments' files.
    magic, version, flags, count, index_size, index_crc, _ = HEADER.unpack_from(data)
    assert (magic, version, flags, count, index_size) == (b"STGV\r\n\x1a\n", 1, 0, 3, 3 * 32)
    assert struct.unpack_from("<I", data, 28)[0] == zlib.crc32(data[:28]) and index_crc == zlib.crc32(data[32:128])
    offset = 128
    for k, (first, count, payload) in enumerate(segments):
        entry = ENTRY.unpack_from(data, 32 + 32 * k)
        assert entry == (first, count, offset, len(payload), zlib.crc32(payload), 0)
        assert data[offset: offset + len(payload)] == payload
        offset += len(payload)
    assert offset == len(data)
    path = tmp_path / "video.stgc"
    path.write_bytes(data)
    assert is_video_stgc(path)
    index = read_video_index(path)
    assert [(e.first_frame, e.num_frames) for e in index.entries] == [(10, 5), (15, 5), (20, 2)]
    assert index.frames == range(10, 22) and index.overhead_bytes == 128 and index.file_bytes == len(data)
    assert [index.segment_of_frame(f) for f in (10, 14, 15, 19, 20, 21)] == [0, 0, 1, 1, 2, 2]
    for k, (_, _, payload) in enumerate(segments):
        expected = decode(payload)
        got = read_video_segment(path, k, index)
        assert got.variant == expected.variant and got.metadata == expected.metadata
        for name in expected.arrays:
            np.testing.assert_array_equal(got.arrays[name], expected.arrays[name])
    assert [d.metadata["iteration"] for d in decode_video(data)] == [0, 1, 2]


def test_a_segment_is_read_without_the_others(segments, tmp_path):
    """Random access: segment 2 decodes although segment 0's payload is destroyed (its checksum fails only when
    segment 0 itself is read)."""
    data = bytearray(encode_video(segments))
    start = 128
    data[start + 40: start + 60] = bytes(20)
    path = tmp_path / "damaged.stgc"
    path.write_bytes(bytes(data))
    assert read_video_segment(path, 2).metadata["iteration"] == 2
    with pytest.raises(FormatError, match="segment 0: checksum"):
        read_video_segment(path, 0)


def test_the_encoder_refuses_what_a_reader_would(segments):
    with pytest.raises(ValueError, match="consecutive"):
        encode_video([segments[0], segments[2]])
    with pytest.raises(ValueError, match="1..4096"):
        encode_video([])
    with pytest.raises(FormatError):
        encode_video([(0, 5, b"not a bitstream" * 4)])
    first, second = segments[0], segments[1]
    with pytest.raises(FormatError, match=r"segment 1 \(frames %d\+%d\)" % second[:2]):  # which one is bad
        encode_video([first, (second[0], second[1], second[2][:-3])])


def test_a_single_model_reader_names_the_container_instead_of_misreading_it(segments, tmp_path):
    path = tmp_path / "video.stgc"
    path.write_bytes(encode_video(segments))
    with pytest.raises(FormatError, match="whole-video"):
        read_stgc(path)


def _reseal(data: bytearray) -> bytearray:
    """Recompute the header, index and segment CRCs wherever the mutated structure allows it."""
    if len(data) < 32:
        return data
    fields = list(HEADER.unpack_from(data))
    count, index_size = fields[3], fields[4]
    end = 32 + index_size
    if end <= len(data) and index_size <= 4096 * 32:
        for k in range(min(count, index_size // 32)):
            entry = list(ENTRY.unpack_from(data, 32 + 32 * k))
            if entry[2] + entry[3] <= len(data):
                entry[4] = zlib.crc32(bytes(data[entry[2]: entry[2] + entry[3]]))
                ENTRY.pack_into(data, 32 + 32 * k, *entry)
        fields[5] = zlib.crc32(bytes(data[32:end]))
    HEADER.pack_into(data, 0, *fields)
    struct.pack_into("<I", data, 28, zlib.crc32(bytes(data[:28])))
    return data


def _mutate(rng: np.random.Generator, data: bytes) -> bytearray:
    out = bytearray(data)
    kind = rng.integers(0, 5)
    if kind == 0:  # bit flips anywhere
        for _ in range(rng.integers(1, 4)):
            out[rng.integers(0, len(out))] ^= 1 << rng.integers(0, 8)
    elif kind == 1:  # an extreme value in a header or index integer
        pos = int(rng.integers(8, 128 - 4))
        out[pos: pos + 4] = struct.pack("<I", int(rng.choice([0, 1, 3, 4097, 2**31, 2**32 - 1, 10**6])))
    elif kind == 2:  # an index field set to another segment's (overlapping / swapped ranges)
        a, b = rng.integers(0, 3, 2)
        field = int(rng.integers(0, 4)) * 4 if rng.random() < 0.5 else 8 + 8 * int(rng.integers(0, 2))
        width = 4 if field < 8 else 8
        out[32 + 32 * a + field: 32 + 32 * a + field + width] = data[32 + 32 * b + field: 32 + 32 * b + field + width]
    elif kind == 3:  # truncate
        del out[int(rng.integers(0, len(out))):]
    else:  # insert junk
        at = int(rng.integers(0, len(out) + 1))
        out[at:at] = rng.integers(0, 256, int(rng.integers(1, 40))).astype(np.uint8).tobytes()
    return out


def test_random_mutations_end_in_format_error_or_valid_segments(segments):
    data = encode_video(segments)
    rng = np.random.default_rng(20261125)
    reasons, valid = set(), 0
    tracemalloc.start()
    try:
        for case in range(CASES):
            mutated = _mutate(rng, data)
            if case % 2:
                mutated = _reseal(mutated)
            tracemalloc.reset_peak()
            try:
                decoded = decode_video(bytes(mutated))
            except FormatError as exc:
                reasons.add(exc.problem.split(":")[0].split(" ")[0])
            else:
                valid += 1
                assert 1 <= len(decoded) <= 4096
                for model in decoded:
                    assert all(np.all(np.isfinite(v)) for v in model.arrays.values())
            peak = tracemalloc.get_traced_memory()[1]
            assert peak < MEMORY_LIMIT, f"case {case}: decoding allocated {peak} bytes"
    finally:
        tracemalloc.stop()
    assert valid < CASES // 4
    assert len(reasons) > 4, reasons  # resealed cases reach the index's structural checks, not only the CRCs


@pytest.mark.parametrize("edit, message", [
    (lambda d: struct.pack_into("<H", d, 8, 2), "version 2"),
    (lambda d: struct.pack_into("<I", d, 12, 5000), "5000 segments"),
    (lambda d: struct.pack_into("<I", d, 32 + 32 + 0, 16), "starts at frame 16"),
    (lambda d: struct.pack_into("<I", d, 32 + 4, 0), "frames 10\\+0"),
    (lambda d: struct.pack_into("<Q", d, 32 + 32 + 8, 129), "offset 129"),
    (lambda d: struct.pack_into("<Q", d, 32 + 64 + 16, 10**6), "past the end"),
])
def test_specific_index_lies_are_named(segments, edit, message):
    mutated = bytearray(encode_video(segments))
    edit(mutated)
    with pytest.raises(FormatError, match=message):
        decode_video(bytes(_reseal(mutated)))
