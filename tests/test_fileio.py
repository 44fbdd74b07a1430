import os
import stat

import pytest

from stgc.fileio import atomic_open, write_json


def test_atomic_write_replaces_only_on_success(tmp_path):
    target = tmp_path / "out.json"
    write_json(target, {"a": 1})
    with pytest.raises(RuntimeError), atomic_open(target, "w") as f:
        f.write("half")
        raise RuntimeError("interrupted")
    assert target.read_text().startswith("{") and list(tmp_path.iterdir()) == [target]


def test_written_files_get_umask_permissions(tmp_path):
    umask = os.umask(0o022)
    try:
        write_json(tmp_path / "x.json", {})
    finally:
        os.umask(umask)
    assert stat.S_IMODE((tmp_path / "x.json").stat().st_mode) == 0o644


def test_a_folder_is_replaced_whole_or_not_at_all(tmp_path):
    from stgc.fileio import atomic_folder

    out = tmp_path / "out"
    with atomic_folder(out) as tmp:
        (tmp / "a").write_text("1")
        (tmp / "b").write_text("1")
    with pytest.raises(RuntimeError):
        with atomic_folder(out) as tmp:
            (tmp / "c").write_text("2")
            raise RuntimeError("failed halfway")
    assert sorted(p.name for p in out.iterdir()) == ["a", "b"]  # the earlier write, untouched
    with atomic_folder(out) as tmp:
        (tmp / "c").write_text("2")
    assert sorted(p.name for p in out.iterdir()) == ["c"]  # not mixed with the earlier write
    assert [p.name for p in tmp_path.iterdir()] == ["out"]  # no temporary folder left


def test_a_folder_whose_swap_fails_keeps_the_earlier_write(tmp_path, monkeypatch):
    """The earlier folder was removed before the new one was renamed onto its name: when that rename failed (a full
    quota, a busy mount), neither the old write nor the new one was left."""
    import stgc.fileio
    from stgc.errors import OutputError
    from stgc.fileio import atomic_folder

    out = tmp_path / "out"
    with atomic_folder(out) as tmp:
        (tmp / "a").write_text("old")
    real_replace = os.replace

    def failing_onto_out(src, dst):
        if os.fspath(dst) == os.fspath(out) and not os.fspath(src).endswith(".old"):
            raise OSError(28, "No space left on device")
        return real_replace(src, dst)

    monkeypatch.setattr(stgc.fileio.os, "replace", failing_onto_out)
    with pytest.raises(OutputError, match="no space left"):
        with atomic_folder(out) as tmp:
            (tmp / "b").write_text("new")
    monkeypatch.setattr(stgc.fileio.os, "replace", real_replace)
    assert sorted(p.name for p in out.iterdir()) == ["a"] and (out / "a").read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out"]  # no temporary or backup folder left
    with atomic_folder(out) as tmp:  # and a later swap that succeeds replaces it, leaving nothing beside it
        (tmp / "c").write_text("new")
    assert sorted(p.name for p in out.iterdir()) == ["c"] and [p.name for p in tmp_path.iterdir()] == ["out"]


def test_a_write_onto_a_symbolic_link_goes_into_its_target_and_the_link_stays(tmp_path):
    """A write renamed the new file or folder onto the link itself: the link was gone, its target kept the earlier
    content, and for a folder a `.out.*.old` link was left beside it (rmtree refuses a link). Writes follow the link
    as a plain open does; a link that cannot be followed is named."""
    from stgc.errors import OutputError
    from stgc.fileio import atomic_folder, atomic_open

    (tmp_path / "target").mkdir()
    (tmp_path / "target" / "a").write_text("old")
    os.symlink("target", tmp_path / "out")
    with atomic_folder(tmp_path / "out") as tmp:
        (tmp / "b").write_text("new")
    assert (tmp_path / "out").is_symlink() and sorted(p.name for p in tmp_path.iterdir()) == ["out", "target"]
    assert [p.name for p in (tmp_path / "target").iterdir()] == ["b"]

    (tmp_path / "file").write_text("old")
    os.symlink("file", tmp_path / "link")
    os.symlink("missing", tmp_path / "dangling")
    for name in ("link", "dangling"):
        with atomic_open(tmp_path / name) as f:
            f.write("new")
        assert (tmp_path / name).is_symlink()
    assert (tmp_path / "file").read_text() == (tmp_path / "missing").read_text() == "new"

    os.symlink("loop", tmp_path / "loop")
    with pytest.raises(OutputError, match="loop: is a symbolic link that cannot be followed"):
        with atomic_open(tmp_path / "loop") as f:
            f.write("new")
    assert (tmp_path / "loop").is_symlink()
