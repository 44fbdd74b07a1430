"""The registry of dataset readers: a reader registers itself with the format's name, aliases and marker files.

Adding a format is one module in this package (discovered when the package loads) plus its test:

    @register_reader("myformat", order=70, aliases=("mine",), marker="my_cameras.json (My format)",
                     detect=lambda path: (path / "my_cameras.json").is_file())
    def read_myformat(path: Path, options: ReaderOptions) -> SourceScene: ...

`detect(path)` says whether `path` (a folder, or a file some formats accept) is in the format; `stgc` asks the
readers in increasing `order` and takes the first that says yes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ..dataset import SourceScene


@dataclass(frozen=True)
class ReaderOptions:
    """Options a reader may need besides the path (most need none)."""

    yuv_range: str = "limited"  # raw YUV inputs: "limited" (16-235) or "full" range


ReadFunction = Callable[[Path, ReaderOptions], SourceScene]


@dataclass(frozen=True)
class Reader:
    name: str
    read: ReadFunction
    detect: Callable[[Path], bool]
    marker: str  # what `detect` looks for, for the error message when nothing matches
    aliases: tuple[str, ...]
    order: int


READERS: dict[str, Reader] = {}


def register_reader(name: str, *, order: int, marker: str, detect: Callable[[Path], bool],
                    aliases: tuple[str, ...] = ()) -> Callable[[ReadFunction], ReadFunction]:
    """Register the decorated `read(path, options) -> SourceScene` as the reader of format `name`."""

    def decorator(read: ReadFunction) -> ReadFunction:
        taken = {alias for r in READERS.values() for alias in (r.name, *r.aliases)}
        clash = taken & {name, *aliases}
        if clash:
            raise ValueError(f"reader {name!r}: the name(s) {sorted(clash)} are already registered")
        READERS[name] = Reader(name, read, detect, marker, tuple(aliases), order)
        return read

    return decorator


def readers_in_order() -> list[Reader]:
    return sorted(READERS.values(), key=lambda r: r.order)


def format_names() -> tuple[str, ...]:
    """The registered formats, in detection order."""
    return tuple(r.name for r in readers_in_order())


def resolve_format(name: str) -> str | None:
    """The format a name or alias (any case) stands for, or None."""
    lowered = name.lower()
    return next((r.name for r in READERS.values() if lowered in (r.name, *r.aliases)), None)
