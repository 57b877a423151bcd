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


def require(module: str, what: str):
    """``import module``, or a :class:`UserError` saying that ``what`` needs it (an optional package)."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise UserError(
            f"{what} needs the Python package {module!r}, which is not installed (it is in requirements.txt)"
        ) from None
