"""Errors shown to users as one line, naming the file and the problem."""

from __future__ import annotations

import os


class McDenoiseError(Exception):
    """Base of every error the CLI prints as one line instead of a traceback."""


class FormatError(McDenoiseError):
    """A file on disk is not what the format says: wrong version, missing channel, truncated..."""

    def __init__(self, path: str | os.PathLike, problem: str) -> None:
        self.path = os.fspath(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class SceneError(McDenoiseError):
    """A scene cannot be loaded or rendered (missing file, unknown plugin, no sensor...)."""


class OutputError(McDenoiseError):
    """An output cannot be written safely: not replaceable, locked, no space, an OS error..."""

    def __init__(self, path: str | os.PathLike, problem: str) -> None:
        self.path = os.fspath(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class OutputExistsError(OutputError, FileExistsError):
    """The output already exists and replacing it was not asked for (also a FileExistsError)."""


class NonFiniteError(FormatError):
    """Data holds NaN/Inf where the caller asked to refuse them (``--nonfinite error``)."""


class EvalError(McDenoiseError):
    """An evaluation cannot run as asked: no images, no references, bad sample counts..."""
