"""Files written by the encoder of every format version decode, today, to exactly what their own decoder gave."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from stgc.codec import decode

REFERENCE = Path(__file__).parent / "reference"
FILES = sorted(REFERENCE.glob("v*_q3.stgc"))


def test_every_readable_version_has_reference_files():
    from stgc.codec.format import READABLE_VERSIONS

    versions = {int(p.name[1:].split("_")[0]) for p in FILES}
    assert versions == set(READABLE_VERSIONS)


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.stem)
def test_reference_file_decodes_bit_exactly(path: Path):
    model = decode(path.read_bytes(), source=str(path))
    assert model.header.version == int(path.name[1:].split("_")[0])
    expected = np.load(path.with_name(path.stem + "_decoded.npz"))
    arrays = {k[2:]: expected[k] for k in expected.files if k.startswith("a:")}
    weights = {k[2:]: expected[k] for k in expected.files if k.startswith("d:")}
    assert list(model.arrays) == list(arrays)
    for name, values in arrays.items():
        np.testing.assert_array_equal(model.arrays[name], values, err_msg=name)
    assert set(model.decoder_state or {}) == set(weights)
    for name, values in weights.items():
        np.testing.assert_array_equal(np.asarray(model.decoder_state[name]), values, err_msg=name)


@pytest.mark.parametrize("version", [1, 5])
def test_a_version_this_reader_does_not_know_is_refused_by_name(version: int):
    """Version 1 (before motion was stored scaled by each Gaussian's time span) would decode to wrong motion, and a
    future version may mean anything: both are refused with the version named, never decoded."""
    import zlib

    from stgc.codec.format import _HEADER, _HEADER_CRC
    from stgc.errors import FormatError

    data = bytearray(FILES[-1].read_bytes())
    data[8:10] = version.to_bytes(2, "little")  # the header's version field, after the 8-byte magic
    _HEADER_CRC.pack_into(data, _HEADER.size, zlib.crc32(bytes(data[: _HEADER.size])))  # a well-formed header
    with pytest.raises(FormatError, match=f"unsupported .stgc version {version}"):
        decode(bytes(data), source="old.stgc")


def test_the_whole_video_container_reference_reads_its_segments_bit_exactly():
    """video_v1.stgc (container version 1, written by `encode_video` at its first commit): frames 10-11 hold
    v4_lite_q3.stgc, frames 12-14 v2_full_q3.stgc, byte for byte; each decodes to its reference arrays."""
    from stgc.codec import read_video_index, read_video_segment

    path = REFERENCE / "video_v1.stgc"
    index = read_video_index(path)
    assert [(e.first_frame, e.num_frames) for e in index.entries] == [(10, 2), (12, 3)]
    data = path.read_bytes()
    for k, name in enumerate(("v4_lite_q3", "v2_full_q3")):
        entry = index.entries[k]
        assert data[entry.offset: entry.offset + entry.length] == (REFERENCE / f"{name}.stgc").read_bytes()
        expected = np.load(REFERENCE / f"{name}_decoded.npz")
        decoded = read_video_segment(path, k, index)
        for key in expected.files:
            got = decoded.arrays[key[2:]] if key.startswith("a:") else decoded.decoder_state[key[2:]]
            np.testing.assert_array_equal(np.asarray(got), expected[key], err_msg=f"{name} {key}")
