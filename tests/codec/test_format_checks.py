"""Rules of docs/stgc-format.md §6 checked on files crafted field by field: the metadata read alone meets the whole
table's limits, quantizers are bounded exactly, streamed zstd frames read, the fixed `bits` of DECO and META and the
version that introduced each flag are enforced; and a written bitstream is on disk before it replaces the file."""

from __future__ import annotations

import io
import json
import os
import struct
import zlib
from dataclasses import dataclass

import numpy as np
import pytest
import zstandard

from stgc.codec import decode, encode
from stgc.codec.files import read_stgc_metadata, write_stgc
from stgc.codec.format import MAX_META_BYTES, decode_metadata
from stgc.codec.synthetic import synthetic_model
from stgc.errors import FormatError

# Layout from docs/stgc-format.md (kept separate from the codec's own structs on purpose).
HEADER = struct.Struct("<8sHBBIHHII")
ENTRY = struct.Struct("<4sBBBBIII")  # tag codec bits components flags raw_size payload_size payload_crc
QPARAM = struct.Struct("<dq")
CENTRED, PREDICT = 4, 8
F32_MAX = float(np.finfo(np.float32).max)  # (2**24 - 1) * 2**104


@dataclass
class Section:
    entry: list
    quantizers: list[list]  # [step, zero_point] per component
    prediction: bytes
    payload: bytes


def parse(data: bytes) -> tuple[list, list[Section]]:
    fields = list(HEADER.unpack_from(data))
    pos, at = 32, 32 + fields[7]
    sections = []
    for _ in range(fields[5]):
        entry = list(ENTRY.unpack_from(data, pos))
        pos += ENTRY.size
        comps = entry[3]
        quantizers = [list(QPARAM.unpack_from(data, pos + QPARAM.size * c)) for c in range(comps)]
        pos += QPARAM.size * comps
        extra = comps * (comps - 1) if entry[4] & PREDICT else 0
        sections.append(Section(entry, quantizers, data[pos: pos + extra], data[at: at + entry[6]]))
        pos += extra
        at += entry[6]
    return fields, sections


def assemble(fields: list, sections: list[Section]) -> bytes:
    """The file of these (edited) sections, every size and CRC recomputed."""
    table = bytearray()
    for s in sections:
        s.entry[6], s.entry[7] = len(s.payload), zlib.crc32(s.payload)
        table += ENTRY.pack(*s.entry)
        for step, zero_point in s.quantizers:
            table += QPARAM.pack(step, zero_point)
        table += s.prediction
    fields = list(fields)
    fields[5], fields[7], fields[8] = len(sections), len(table), zlib.crc32(bytes(table))
    head = HEADER.pack(*fields)
    return head + struct.pack("<I", zlib.crc32(head)) + bytes(table) + b"".join(s.payload for s in sections)


def section(sections: list[Section], tag: bytes) -> Section:
    return next(s for s in sections if s.entry[0] == tag)


@pytest.fixture(scope="module")
def full_file() -> bytes:
    arrays, decoder = synthetic_model(500, "full", seed=5)  # has delta, centred and predicted sections
    return encode(arrays, "full", decoder, metadata={"iteration": 7})


# --- the metadata read alone ------------------------------------------------------------------------------------------

def test_metadata_that_claims_more_than_its_limit_is_refused_unread(tmp_path):
    """A META section of 2 MiB of valid JSON (a few hundred bytes as zstd): decode refuses it from the table, and so
    must the metadata reader, before decompressing anything (it decompressed all of it, 256 MiB as readily)."""
    arrays, decoder = synthetic_model(50, "full", seed=1)
    fields, sections = parse(encode(arrays, "full", decoder, metadata={"iteration": 1}))
    meta = section(sections, b"META")
    big = json.dumps({"iteration": 1, "pad": " " * (2 << 20)}).encode()
    meta.payload = zstandard.ZstdCompressor(level=3).compress(big)
    meta.entry[1], meta.entry[5] = 1, len(big)
    assert len(meta.payload) < 1000
    path = tmp_path / "bomb.stgc"
    path.write_bytes(assemble(fields, sections))
    problem = f"metadata section claims {len(big)} bytes, above the limit of {MAX_META_BYTES}"
    with pytest.raises(FormatError, match=problem) as info:
        read_stgc_metadata(path)
    assert str(path) in str(info.value)
    with pytest.raises(FormatError, match=problem):
        decode(path)


@pytest.mark.parametrize("read", [decode, decode_metadata])
def test_a_file_whose_section_table_is_refused_yields_no_metadata_either(full_file, read):
    fields, sections = parse(full_file)
    section(sections, b"POSI").quantizers[0][0] = float("nan")
    with pytest.raises(FormatError, match="crafted.stgc: section 'POSI' has an invalid quantizer step nan"):
        read(assemble(fields, sections), source="crafted.stgc")


# --- quantizers bounded exactly ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("centred", [False, True], ids=["plain", "centred"])
@pytest.mark.parametrize("side", [1, -1], ids=["top", "bottom"])
def test_a_quantizer_reaching_exactly_the_float32_limit_is_read_and_one_beyond_it_is_refused(centred, side):
    """The decoder bounds the values a section's codes can give: (code + zero_point) * step for codes in
    [0, 2**B) (plain) or signed offsets in [-2**B, 2**B) (CENTRED). Here scale_0's codes all sit at the extreme
    code of that side and the quantizer puts it exactly on +-float32 max; one zero point further is refused.
    (The bound was (|zero_point| + 2**B) * step, about 3x too loose: version 2 files that version's decoder read
    were refused.)"""
    bits, n = 6, 40
    arrays, _ = synthetic_model(n, "lite", seed=3)
    data = encode(arrays, "lite", None, group_bits={"SCAL": bits}, adaptive_delta=False, outlier_guard=False)
    fields, sections = parse(data)
    scal = section(sections, b"SCAL")
    assert scal.entry[2] == bits and scal.entry[3] == 3 and scal.entry[4] == 0
    step = 2.0**104  # F32_MAX = (2**24 - 1) * step exactly
    if centred:  # a 6-bit centred section keeps its 1-byte container: the sizes stay valid
        lowest, highest = -(1 << bits), (1 << bits) - 1
        extreme_code = (2 * highest) if side > 0 else (-2 * lowest - 1)  # zigzag of the extreme offset
    else:
        lowest, highest = 0, (1 << bits) - 1
        extreme_code = highest if side > 0 else lowest
    edge = ((1 << 24) - 1 - highest) if side > 0 else (-((1 << 24) - 1) - lowest)
    codes = np.zeros((3, n), np.uint8)
    codes[0] = extreme_code
    scal.entry[1], scal.entry[4], scal.entry[5] = 0, CENTRED if centred else 0, codes.size  # stored, planar
    scal.payload = codes.tobytes()

    scal.quantizers[0] = [step, edge]
    decoded = decode(assemble(fields, sections), source="edge.stgc")
    assert np.all(decoded.arrays["scale_0"] == np.float32(side * F32_MAX))

    scal.quantizers[0] = [step, edge + side]
    with pytest.raises(FormatError, match="beyond.stgc: section 'SCAL' quantizer reaches .*, beyond float32"):
        decode(assemble(fields, sections), source="beyond.stgc")


# --- zstd frames ------------------------------------------------------------------------------------------------------

def _streamed(raw: bytes, **params: int) -> bytes:
    """One zstd frame written the streaming way: no content size in its header, so the level's window stays."""
    compressor = zstandard.ZstdCompressor(
        compression_params=zstandard.ZstdCompressionParameters.from_level(19, **params))
    out = io.BytesIO()
    with compressor.stream_writer(out, closefd=False) as writer:
        writer.write(raw)
    return out.getvalue()


def test_a_section_compressed_as_a_stream_without_its_content_size_decodes(full_file):
    """A streamed frame at level 19 asks for its level's 8 MiB window whatever the content: §6 allows windows up to
    2**max(23, min(27, bit length of raw_size)) bytes, so an ordinary writer's frame is read, a larger window not."""
    fields, sections = parse(full_file)
    posi = section(sections, b"POSI")
    assert posi.entry[1] == 1
    raw = zstandard.ZstdDecompressor().decompress(posi.payload)
    assert len(raw) < 1 << 20
    posi.payload = _streamed(raw)
    frame = zstandard.get_frame_parameters(posi.payload)
    assert frame.content_size == zstandard.CONTENTSIZE_UNKNOWN and frame.window_size == 8 << 20
    decoded, expected = decode(assemble(fields, sections), source="streamed.stgc"), decode(full_file)
    for name, values in expected.arrays.items():
        np.testing.assert_array_equal(decoded.arrays[name], values, err_msg=name)

    posi.payload = _streamed(raw, window_log=24)
    assert zstandard.get_frame_parameters(posi.payload).window_size == 16 << 20
    with pytest.raises(FormatError, match="streamed.stgc: section 'POSI' is not a valid zstd frame"):
        decode(assemble(fields, sections), source="streamed.stgc")


def test_a_section_payload_is_read_as_a_zstd_stream(full_file):
    """§6 rule 4: a zstd payload is a stream, as zstd's own tools read it: several frames decode one after another
    and a skippable frame is skipped (stgc writes one frame; another writer may not)."""
    fields, sections = parse(full_file)
    posi = section(sections, b"POSI")
    raw = zstandard.ZstdDecompressor().decompress(posi.payload)
    compressor = zstandard.ZstdCompressor(level=19)
    skippable = struct.pack("<II", 0x184D2A50, 4) + b"junk"
    expected = decode(full_file)
    for payload in (compressor.compress(raw[: len(raw) // 2]) + compressor.compress(raw[len(raw) // 2:]),
                    skippable + compressor.compress(raw), compressor.compress(raw) + skippable):
        posi.payload = payload
        decoded = decode(assemble(fields, sections), source="stream.stgc")
        for name, values in expected.arrays.items():
            np.testing.assert_array_equal(decoded.arrays[name], values, err_msg=name)


# --- fields fixed by the spec, flags by version -----------------------------------------------------------------------

@pytest.mark.parametrize("tag, bits", [(b"DECO", 8), (b"DECO", 200), (b"META", 16), (b"META", 0)])
@pytest.mark.parametrize("read", [decode, decode_metadata])
def test_the_bits_of_the_decoder_and_metadata_sections_are_checked(full_file, tag, bits, read):
    fields, sections = parse(full_file)
    section(sections, tag).entry[2] = bits
    what = "decoder" if tag == b"DECO" else "metadata"
    with pytest.raises(FormatError, match=f"crafted.stgc: {what} section is malformed .*bits {bits}"):
        read(assemble(fields, sections), source="crafted.stgc")


@pytest.mark.parametrize("version, flag, since", [(2, "CENTRED", 3), (3, "PREDICT", 4)])
def test_a_flag_is_refused_in_a_file_of_a_version_before_it(full_file, version, flag, since):
    """Version 3 introduced CENTRED and version 4 PREDICT: no older encoder wrote them and the older decoders
    refused them, so an older file holding one is not a valid file (the reference files of every version decode:
    test_reference_files.py)."""
    fields, sections = parse(full_file)
    assert any(s.entry[4] & CENTRED for s in sections) and any(s.entry[4] & PREDICT for s in sections)
    fields[1] = version
    with pytest.raises(FormatError, match=f"old.stgc: section '.*' has the {flag} flag, new in version {since}, "
                                          f"in a version {version} file"):
        decode(assemble(fields, sections), source="old.stgc")


# --- writing ----------------------------------------------------------------------------------------------------------

def test_a_bitstream_is_on_disk_before_it_replaces_the_file(tmp_path, monkeypatch):
    """write_stgc fsyncs the new bytes before the rename (as the JSON writer does): after a crash the path holds
    the old file or the whole new one, never an empty or partial one."""
    path = tmp_path / "model.stgc"
    path.write_bytes(b"old")
    data = b"STGC\r\n\x1a\n" + bytes(range(256)) * 4
    synced = []
    real_fsync = os.fsync

    def fsync(fd: int) -> None:
        synced.append((os.fstat(fd).st_size, path.read_bytes()))
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    write_stgc(path, data)
    assert synced == [(len(data), b"old")]  # the new bytes were synced while the old file was still in place
    assert path.read_bytes() == data
