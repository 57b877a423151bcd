"""Output paths of the tools: the ``--force`` rule, folders this process can write, atomic output folders.

Every check raises :class:`~vlocnetpp_core.errors.UserError` with one line naming the path (the CLI prints it
and exits 2), before any work is done:

* :func:`refuse_existing`: the one ``--force`` refusal, for any output (file or folder);
* :func:`check_output_dir`: an output folder that is replaced as a whole (``synth``, ``extract``): not a file,
  not the current folder or one above it, in a folder that can be written;
* :func:`check_run_dir`: a folder that is written in place (``train --out``): not a file, writable;
* :func:`atomic_output_dir`: a hidden temporary sibling ``.OUT.partial-<pid>`` (the naming of
  :mod:`vlocnetpp_core.bag.bagfile`, so the two clean up each other's stale folders) that is renamed to ``OUT``
  only when the block ends without an error; an error, Ctrl-C or SIGTERM (with
  :func:`~vlocnetpp_core.interrupts.sigterm_as_interrupt`) deletes it and any parent folder it had to make.

``os.access`` answers for permissions, a read-only file system too, but not for root, which may write anywhere
the kernel lets it: what it refuses (e.g. ``/sys``) is caught where the folder is made, with the same kind of line.
"""

from __future__ import annotations

import os
import re
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from vlocnetpp_core.errors import UserError

FORCE_REFUSAL = "exists already (use --force to replace it)"


def refuse_existing(path: str | Path, force: bool) -> None:
    """The ``--force`` rule: refuse an existing ``path`` unless ``force``."""
    if Path(path).exists() and not force:
        raise UserError(f"{path}: {FORCE_REFUSAL}")


def _absolute(path: str | Path) -> Path:
    """``path`` made absolute with ``.`` and ``..`` resolved (``synth . --force`` names the current folder)."""
    return Path(os.path.abspath(path))


def _nearest_existing(path: Path) -> Path:
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def check_writable(folder: str | Path, out: str | Path) -> None:
    """Refuse ``out`` unless ``folder`` (or, where it is still to be made, its nearest existing ancestor) is a folder
    this process may write in."""
    existing = _nearest_existing(_absolute(folder))
    if not existing.is_dir():
        raise UserError(f"{out}: {existing} is not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise UserError(f"{out}: cannot write in {existing} (permission denied)")


def check_output_dir(out: str | Path, force: bool) -> None:
    """Refuse an output folder that :func:`atomic_output_dir` could not make or replace (module doc)."""
    target = _absolute(out)
    if not target.name:
        raise UserError(f"{out}: not a folder that can be replaced")
    refuse_existing(out, force)
    if target.exists():
        if not target.is_dir():
            raise UserError(f"{out}: exists and is not a folder; not replacing it")
        cwd = Path.cwd().resolve()
        if target.resolve() == cwd or target.resolve() in cwd.parents:
            raise UserError(f"{out}: is the current folder or one above it ({cwd}); run from outside it to replace it")
    check_writable(target.parent, out)


def check_run_dir(out: str | Path) -> None:
    """Refuse a folder to be written in place (a run folder) that is a file or cannot be written."""
    target = _absolute(out)
    if target.exists() and not target.is_dir():
        raise UserError(f"{out}: exists and is not a folder")
    check_writable(target, out)


def make_dirs(folder: str | Path, out: str | Path | None = None) -> list[Path]:
    """``mkdir -p folder`` with a :class:`UserError` naming ``out`` (default: ``folder``); returns the folders made,
    outermost first."""
    folder = _absolute(folder)
    made = []
    p = folder
    while not p.exists() and p != p.parent:
        made.insert(0, p)
        p = p.parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise UserError(
            f"{out if out is not None else folder}: cannot make the folder {folder} ({err.strerror})"
        ) from None
    return made


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def temp_dir_for(path: Path, pid: int | None = None) -> Path:
    """The temporary folder a writer of ``path`` uses: ``.NAME.partial-PID`` next to it."""
    return path.with_name(f".{path.name}.partial-{os.getpid() if pid is None else pid}")


def remove_stale_temps(path: Path) -> list[Path]:
    """Delete temporary folders of ``path`` left by writers that are no longer running; returns them."""
    pattern = re.compile(rf"^\.{re.escape(path.name)}\.partial-(\d+)$")
    removed = []
    if path.parent.is_dir():
        for p in path.parent.iterdir():
            m = pattern.match(p.name)
            if m and (int(m.group(1)) == os.getpid() or not _pid_alive(int(m.group(1)))):
                shutil.rmtree(p, ignore_errors=True)
                removed.append(p)
    return removed


def _replace(tmp: Path, target: Path) -> None:
    """Rename ``tmp`` to ``target``; an existing ``target`` goes only once ``tmp`` stands in its place."""
    if not target.exists():
        os.replace(tmp, target)
        return
    old = tmp.with_name(tmp.name + "-old")
    os.replace(target, old)
    try:
        os.replace(tmp, target)
    except BaseException:
        os.replace(old, target)  # put the previous output back
        raise
    shutil.rmtree(old, ignore_errors=True)


@contextmanager
def atomic_output_dir(out: str | Path, force: bool = False) -> Iterator[Path]:
    """Yield an empty temporary folder that becomes ``out`` when the block succeeds (an old ``out`` is replaced only
    then, with ``force``); on any exception it is deleted, with the parent folders made for it, and ``out`` is left
    as it was."""
    check_output_dir(out, force)
    target = _absolute(out)
    made = make_dirs(target.parent, out)
    try:
        remove_stale_temps(target)
        tmp = temp_dir_for(target)
        try:
            tmp.mkdir()
        except OSError as err:
            raise UserError(f"{out}: cannot make the folder {tmp} ({err.strerror})") from None
        try:
            yield tmp
            _replace(tmp, target)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    except BaseException:
        for folder in reversed(made):
            if folder.is_dir() and not any(folder.iterdir()):
                folder.rmdir()
        raise
