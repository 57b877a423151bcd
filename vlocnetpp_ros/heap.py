"""The node process's C heap (glibc): hand freed pages back to the system, and read what is in use.

``malloc_trim(0)`` returns the free pages of every arena, so the resident memory follows the memory in use after a
burst of large messages instead of staying at its high-water mark. ``mallinfo2`` says how many bytes malloc has
handed out (``uordblks`` in the arenas + ``hblkhd`` in mmapped chunks): every message buffer, Fast DDS's payload
pools, numpy and torch arrays; not Python's small objects (obmalloc maps its own arenas). Unlike the resident memory
it does not move with the fragmentation left behind by a burst, so it shows a leak of a few MiB that the resident
memory's spread (several MiB from one burst to the next) would hide. On another C library both are unavailable.
"""

from __future__ import annotations

import ctypes

MIB = 1024 * 1024


class _Mallinfo2(ctypes.Structure):
    """glibc's ``struct mallinfo2`` (glibc >= 2.33), all ``size_t``."""

    _fields_ = [
        (name, ctypes.c_size_t)
        for name in "arena ordblks smblks hblks hblkhd usmblks fsmblks uordblks fordblks keepcost".split()
    ]


class Heap:
    """glibc's ``malloc_trim`` and ``mallinfo2`` of this process; each a no-op (None) where the C library lacks it."""

    def __init__(self) -> None:
        try:
            libc = ctypes.CDLL(None)
        except OSError:
            libc = None
        self._trim = getattr(libc, "malloc_trim", None)
        self._info = getattr(libc, "mallinfo2", None)
        if self._info is not None:
            self._info.restype = _Mallinfo2
            self._info.argtypes = []

    def trim(self) -> None:
        """Return the free heap pages to the system (~0.05 ms; ctypes releases the GIL meanwhile)."""
        if self._trim is not None:
            self._trim(0)

    def in_use_mb(self) -> float | None:
        """MiB that malloc has handed out and not had back (arenas + mmapped chunks), or None without ``mallinfo2``."""
        if self._info is None:
            return None
        info = self._info()
        return (info.uordblks + info.hblkhd) / MIB
