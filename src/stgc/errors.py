"""Errors a user can act on. Each names the offending file (or input) and the problem."""

from __future__ import annotations

from pathlib import Path


class StgcError(Exception):
    """Base class for errors that are reported to the user without a traceback."""


class DataError(StgcError, ValueError):
    """Bad or unreadable input data: names the file and what is wrong with it."""

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path is not None else problem)

    def __reduce__(self) -> tuple[type, tuple[Path | None, str]]:  # pickled whole: a Ray task's error reaches the driver
        return type(self), (self.path, self.problem)


class OutputError(StgcError):
    """An output cannot be written (full disk, read-only or missing folder, permissions): names the file."""

    def __init__(self, path: str | Path, problem: str):
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")

    def __reduce__(self) -> tuple[type, tuple[Path, str]]:
        return type(self), (self.path, self.problem)


class FormatError(DataError):
    """A file in one of our own formats (.stgc, checkpoint, PLY) is invalid."""
