"""Errors about the user's input. The CLI prints them as one line without a traceback."""

from __future__ import annotations

from pathlib import Path


class UserError(Exception):
    """A problem with the user's input (a flag, a file, a dataset layout)."""


class DataError(UserError):
    """A bad file: the message names the file (and line, when there is one) and what was expected."""

    def __init__(self, path: str | Path, message: str, line: int | None = None):
        self.path = str(path)
        self.line = line
        where = f"{self.path}:{line}" if line is not None else self.path
        super().__init__(f"{where}: {message}")
