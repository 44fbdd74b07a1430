"""The reader registry: a format registers itself in one place, and detection, opening and the option's choices
follow."""

from __future__ import annotations

import pytest
from scenes import write_panoptic_scene

from stgc.data import readers
from stgc.data.readers import READERS, detect_format, open_dataset, register_reader


@pytest.fixture
def scratch_registry():
    """Registrations made by a test are removed after it."""
    before = dict(READERS)
    yield
    READERS.clear()
    READERS.update(before)


def test_builtin_formats_register_themselves_in_detection_order():
    assert readers.format_names() == ("panoptic", "stg-colmap", "blender", "n3dv", "technicolor", "miv")
    assert readers.resolve_format("D3DGS") == "panoptic" and readers.resolve_format("dnerf") == "blender"
    assert readers.resolve_format("bogus") is None


def test_a_registered_reader_is_detected_and_opened(tmp_path, scratch_registry):
    scene = write_panoptic_scene(tmp_path / "scene", views=3, frames=1, width=16, height=12)
    (scene.root / "mine.marker").write_text("")
    panoptic = READERS["panoptic"].read
    seen = []

    # Ahead of Panoptic (order 5) and recognised by its own marker file: it wins detection.
    @register_reader("mine", order=5, marker="mine.marker (Mine)", detect=lambda p: (p / "mine.marker").is_file(),
                     aliases=("my-format",))
    def read_mine(path, options):
        seen.append(path)
        return panoptic(path, options)

    assert detect_format(scene.root) == "mine"
    dataset = open_dataset(scene.root, format="my-format")
    assert seen == [scene.root.resolve()] and len(dataset.train) == 2


def test_names_and_aliases_are_unique(scratch_registry):
    with pytest.raises(ValueError, match="already registered"):
        register_reader("other", order=99, marker="-", detect=lambda p: False, aliases=("dnerf",))(lambda p, o: None)


def test_nothing_matching_lists_every_formats_marker(tmp_path):
    from stgc.errors import DataError

    with pytest.raises(DataError) as err:
        detect_format(tmp_path)
    for reader in READERS.values():
        assert reader.marker in str(err.value)
