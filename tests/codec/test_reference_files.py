"""Files written by the encoder of every format version decode, today, to exactly what their own decoder gave."""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from stgc.codec import decode

REFERENCE = Path(__file__).parent / "reference"
# v<version>_<variant>_q<quality>[_meta].stgc (tests/codec/reference/README.md); not video_v1.stgc, a container.
_NAME = re.compile(r"v(\d+)_(full|lite)_q([1-5])(_meta)?\.stgc")
FILES = sorted(p for p in REFERENCE.glob("v*.stgc") if _NAME.fullmatch(p.name))
META_FILES = [p for p in FILES if _NAME.fullmatch(p.name).group(4)]  # written by compress_run: a META section


def _version(path: Path) -> int:
    return int(_NAME.fullmatch(path.name).group(1))


@dataclass
class Expected:
    """What the decoder of the file's own commit read from it (`<stem>_decoded.npz`)."""

    arrays: dict[str, np.ndarray]
    weights: dict[str, np.ndarray]
    metadata: dict[str, Any]
    header: tuple[int, str, int, int] | None  # version, variant, quality, N (recorded for the _meta files)
    table: list[tuple] | None  # per section: tag, codec, bits, components, flags, raw_size, payload_size
    encoder: dict[str, Any] | None  # the options it was written with, and each group's depth before the guard


def _expected(path: Path) -> Expected:
    npz = np.load(path.with_name(path.stem + "_decoded.npz"))
    if "arrays" in npz.files:  # the _meta files: every field in one array (fewer npz members, fewer bytes)
        arrays = dict(zip(npz["fields"].tolist(), npz["arrays"]))
    else:
        arrays = {k[2:]: npz[k] for k in npz.files if k.startswith("a:")}
    weights = {k[2:]: npz[k] for k in npz.files if k.startswith("d:")}
    # The q3 files were written by encode() without metadata: no META section, so their decoder gave {}.
    metadata = json.loads(npz["meta"].item()) if "meta" in npz.files else {}
    header = table = encoder = None
    if "header" in npz.files:
        version, variant, quality, n = npz["header"].tolist()
        header = (version, {1: "full", 2: "lite"}[variant], quality, n)
        table = [(tag, *row) for tag, row in zip(npz["tags"].tolist(), npz["table"].tolist())]
        encoder = json.loads(npz["encoder"].item())
    return Expected(arrays, weights, metadata, header, table, encoder)


def test_every_readable_version_has_reference_files():
    from stgc.codec.format import READABLE_VERSIONS

    assert {_version(p) for p in FILES} == set(READABLE_VERSIONS)
    assert {_version(p) for p in META_FILES} == set(READABLE_VERSIONS)


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.stem)
def test_reference_file_decodes_bit_exactly(path: Path):
    from stgc.codec import read_stgc_metadata
    from stgc.codec.format import decode_metadata

    data = path.read_bytes()
    model = decode(data, source=str(path))
    assert model.header.version == _version(path)
    expected = _expected(path)
    assert list(model.arrays) == list(expected.arrays)
    for name, values in expected.arrays.items():
        np.testing.assert_array_equal(model.arrays[name], values, err_msg=name)
    assert set(model.decoder_state or {}) == set(expected.weights)
    for name, values in expected.weights.items():
        np.testing.assert_array_equal(np.asarray(model.decoder_state[name]), values, err_msg=name)
    # The metadata too (decompress restores the iteration, the decoder's activation and the run config from it),
    # by the whole decode and by the metadata-only readers.
    assert model.metadata == expected.metadata
    assert decode_metadata(data, source=str(path)) == expected.metadata
    assert read_stgc_metadata(path) == expected.metadata
    if expected.header is not None:
        header = model.header
        assert (header.version, header.variant, header.quality, header.num_gaussians) == expected.header
        assert [(s.tag, s.codec, s.bits, s.components, s.flags, s.raw_size, s.payload_size)
                for s in header.sections] == expected.table


def test_reference_files_hold_what_compress_run_writes():
    """Per readable version, the reference files reach what real files have: a META section as compress_run wrote
    it (a full model's with its decoder's activation, a lite model's), a 17..24-bit section (4-byte codes), a
    quality other than 3 (another ladder), and a depth the outlier guard raised above the one asked for."""
    from stgc.codec.format import READABLE_VERSIONS

    for version in READABLE_VERSIONS:
        files = [p for p in FILES if _version(p) == version]
        seen: dict[str, list[str]] = {}
        for path in files:
            model = decode(path.read_bytes(), source=str(path))
            header, meta = model.header, model.metadata
            if isinstance(meta.get("iteration"), int) and meta["iteration"] > 0 and {"data", "model"} <= set(
                    meta.get("run_config", {})):
                seen.setdefault(f"META {header.variant}", []).append(path.name)
                if header.variant == "full" and meta.get("decoder_activation") not in (None, "sigmoid"):
                    seen.setdefault("decoder_activation", []).append(path.name)  # not the default a reader assumes
            attributes = [s for s in header.sections if s.tag not in ("DECO", "META")]
            if any(17 <= s.bits <= 24 for s in attributes):
                seen.setdefault("17-24 bits", []).append(path.name)
            if header.quality != 3:
                seen.setdefault("not q3", []).append(path.name)
            encoder = _expected(path).encoder
            if encoder and any(s.bits > encoder["requested_bits"][s.tag] for s in attributes):
                seen.setdefault("outlier guard", []).append(path.name)
        wanted = {"META full", "META lite", "decoder_activation", "17-24 bits", "not q3", "outlier guard"}
        assert wanted <= set(seen), f"version {version}: no reference file has {sorted(wanted - set(seen))}"


@pytest.mark.parametrize("path", [p for p in META_FILES if "_full_" in p.name], ids=lambda p: p.stem)
def test_a_reference_file_restores_its_run(path: Path, tmp_path: Path):
    """decompress restores what the file's META says: the iteration directory, the run config and the decoder's
    activation (not the default a reader assumes), with the Gaussians bit for bit."""
    from stgc.codec import decompress
    from stgc.model import STGModel

    expected = _expected(path)
    meta = expected.metadata
    iteration_dir = decompress(path, tmp_path / "run")
    assert iteration_dir == tmp_path / "run" / "point_cloud" / f"iteration_{meta['iteration']}"
    assert json.loads((tmp_path / "run" / "config.json").read_text()) == meta["run_config"]
    model = STGModel.load(tmp_path / "run")
    assert model.decoder_activation == meta["decoder_activation"]
    restored = model.to_ply_arrays()
    for name, values in expected.arrays.items():
        np.testing.assert_array_equal(restored[name], values, err_msg=name)


@pytest.mark.parametrize("version", [1, 5])
def test_a_version_this_reader_does_not_know_is_refused_by_name(version: int):
    """Version 1 (before motion was stored scaled by each Gaussian's time span) would decode to wrong motion, and a
    future version may mean anything: both are refused with the version named, never decoded."""
    import zlib

    from stgc.codec.format import _HEADER, _HEADER_CRC
    from stgc.errors import FormatError

    data = bytearray((REFERENCE / "v4_lite_q3.stgc").read_bytes())
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
