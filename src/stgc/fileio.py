"""Atomic file writes: a reader never sees a half-written output."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

from stgc.errors import FormatError, OutputError

# Errors that writing the temporary file itself can raise: the device is full, or the file outgrows a limit.
# A broken pipe: the encoder process writing it (ffmpeg for a video) stopped, most often for the same reasons.
_WRITE_ERRORS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EPIPE}


def output_error(path: str | Path, exc: OSError) -> OutputError:
    """An OutputError for `exc`, raised while writing `path`, in words a user can act on."""
    path = Path(path)
    code = exc.errno
    if code in (errno.ENOSPC, errno.EDQUOT):
        problem = "no space left on the device (free some and run the same command again)"
    elif code == errno.EFBIG:
        problem = "the file grew beyond what this system allows (file size limit)"
    elif code == errno.EPIPE:
        problem = "the encoder writing it stopped (a full disk, or the encoder failed)"
    elif code == errno.EROFS:
        problem = "the file system is read-only"
    elif code in (errno.EACCES, errno.EPERM):
        problem = "permission denied"
    elif code in (errno.ENOTDIR, errno.EEXIST) and not path.parent.is_dir():
        blocker = next((p for p in [path.parent, *path.parent.parents] if p.exists() and not p.is_dir()), None)
        problem = f"{blocker or path.parent} is a file, not a folder"
    else:
        problem = exc.strerror or str(exc)
    return OutputError(path, f"cannot write: {problem}")


def _through_link(path: str | Path) -> Path:
    """Where a write to `path` lands: the target of a symbolic link there, as a plain open would write it. Renaming
    a new file or folder onto the link itself replaced the link and left its target with the earlier content. A
    link that cannot be followed (a loop) is an OutputError."""
    path = Path(path)
    if not path.is_symlink():
        return path
    try:
        return path.resolve(strict=True)
    except FileNotFoundError:
        return path.resolve()  # a link to what does not exist yet: the write creates its target
    except (OSError, RuntimeError) as exc:  # a loop: RuntimeError up to Python 3.12, OSError (ELOOP) since
        raise OutputError(path, f"is a symbolic link that cannot be followed ({exc})") from None


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside `path` (beside its target, where it is a symbolic link); rename it onto `path`
    only if the block succeeds.

    Use it for writers that want a filename (torch.save, imageio, plyfile)."""
    path = _through_link(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        os.close(fd)
    except OSError as exc:
        raise output_error(path, exc) from None
    with _renamed_into_place(Path(tmp), path, 0o666) as written:
        yield written


@contextlib.contextmanager
def atomic_folder(path: str | Path) -> Iterator[Path]:
    """Yield a temporary folder beside `path`; it replaces `path` (and whatever an earlier write left there) only if
    the block succeeds, so the folder holds one write's files, never two writes' mixed or half of one. A symbolic
    link at `path` is followed: its target is the folder replaced."""
    path = _through_link(path)
    if path.exists() and not path.is_dir():
        raise OutputError(path, "cannot write: exists and is not a folder")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    except OSError as exc:
        raise output_error(path, exc) from None
    with _renamed_into_place(tmp, path, 0o777) as written:
        yield written


@contextlib.contextmanager
def _renamed_into_place(tmp: Path, path: Path, mode: int) -> Iterator[Path]:
    """Yield `tmp` (a file or folder); when the block succeeds, give it the permissions a plain create would have
    (`mode` less the umask: mkstemp and mkdtemp make them private) and rename it onto `path` (a folder there is
    replaced); remove it in any case."""
    try:
        try:
            yield tmp
        except OSError as exc:
            # Only what writing can cause is the output's fault; any other OSError of the block is its own.
            if exc.errno in _WRITE_ERRORS:
                raise output_error(path, exc) from None
            raise
        try:
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp, mode & ~umask)
            if tmp.is_dir() and path.exists():
                _swap_folder(tmp, path)
            else:
                os.replace(tmp, path)
        except OSError as exc:
            raise output_error(path, exc) from None
    finally:
        if tmp.is_dir():
            shutil.rmtree(tmp, ignore_errors=True)
        elif tmp.exists():
            tmp.unlink()


def _swap_folder(new: Path, path: Path) -> None:
    """Put the folder `new` where the folder `path` is. The old one is renamed aside first and removed only once
    `new` is in place; when that rename fails it is renamed back, so `path` holds the old write or the new one,
    never neither (removing the old folder first lost both where the rename then failed)."""
    backup = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".old", dir=path.parent))
    os.rmdir(backup)  # a free name beside `path`: rename needs it empty or absent
    os.replace(path, backup)
    try:
        os.replace(new, path)
    except OSError:
        try:
            os.replace(backup, path)
        except OSError as exc:
            raise OutputError(path, f"cannot write ({exc.strerror}), nor put the earlier write back: it is in "
                                    f"{backup}") from None
        raise
    shutil.rmtree(backup, ignore_errors=True)


@contextlib.contextmanager
def atomic_open(path: str | Path, mode: str = "w", **kwargs: Any) -> Iterator[IO[Any]]:
    """Open a temporary file beside `path` for writing; it replaces `path` when the block succeeds."""
    with atomic_path(path) as tmp, open(tmp, mode, **kwargs) as f:
        yield f
        f.flush()
        os.fsync(f.fileno())  # a full disk shows here at the latest, before the rename


def write_json(path: str | Path, obj: Any) -> None:
    with atomic_open(path, "w") as f:
        json.dump(obj, f, indent=2, sort_keys=False)
        f.write("\n")


def read_json_object(path: str | Path, *, strict: bool = True) -> dict[str, Any] | None:
    """The JSON object stored at `path`, or None when the file does not exist.

    An unreadable or non-object file raises FormatError naming it (strict), or reads as None (not strict: for
    callers that treat a damaged marker file as "not done yet")."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        if strict:
            raise FormatError(path, f"cannot read JSON ({exc})") from None
        return None
    if not isinstance(data, dict):
        if strict:
            raise FormatError(path, "expected a JSON object")
        return None
    return data


def file_sha256(path: str | Path) -> str:
    """SHA-256 of a file's bytes (hex), read in blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
