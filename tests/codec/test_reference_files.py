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
