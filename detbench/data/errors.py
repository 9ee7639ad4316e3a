"""Errors of the data layer: every message names the file (and line), what is wrong and the fix."""
from __future__ import annotations

import os


class DatasetError(ValueError):
    """A dataset file is malformed or inconsistent.

    Attributes: `path` (the offending file, or None), `line` (1-based line number, or None).
    The message reads ``PATH:LINE: what is wrong; how to fix it``.
    """

    def __init__(self, message: str, path: str | os.PathLike | None = None, line: int | None = None):
        self.path = None if path is None else str(path)
        self.line = line
        self.reason = message
        where = ""
        if self.path is not None:
            where = self.path + (f":{line}" if line is not None else "") + ": "
        super().__init__(where + message)


class MissingFileError(DatasetError, FileNotFoundError):
    """A file the dataset needs is absent (also a FileNotFoundError, so generic handlers catch it)."""
