"""Portable Float Map (PFM) files: the depth format of ``DeepLoc_stereo``.

Layout: a text header ``Pf`` (one channel) or ``PF`` (three channels), ``"<width> <height>"``
and a scale whose sign gives the byte order (negative: little-endian), each on its own line,
then float32 rows stored bottom-to-top, as the PFM specification says. Arrays in memory are
top-to-bottom ``(H, W)`` or ``(H, W, 3)`` float32.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vlocnetpp_core.errors import DataError

__all__ = ["write_pfm", "read_pfm"]


def write_pfm(path: str | Path, array: np.ndarray) -> None:
    """Write ``(H, W)`` or ``(H, W, 3)`` values as little-endian float32 PFM (scale -1.0)."""
    a = np.asarray(array)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 3)):
        raise ValueError(f"PFM holds (H, W) or (H, W, 3) arrays, got shape {a.shape}")
    magic = b"Pf" if a.ndim == 2 else b"PF"
    header = magic + b"\n%d %d\n-1.0\n" % (a.shape[1], a.shape[0])
    data = np.ascontiguousarray(a[::-1], dtype="<f4")
    with open(path, "wb") as f:
        f.write(header)
        f.write(data.tobytes())


def _header_token(data: bytes, pos: int, path: Path, what: str) -> tuple[bytes, int]:
    end = data.find(b"\n", pos)
    if end < 0:
        raise DataError(path, f"truncated PFM header (no {what} line)")
    return data[pos:end].strip(), end + 1


def read_pfm(path: str | Path) -> np.ndarray:
    """``(H, W)`` (``Pf``) or ``(H, W, 3)`` (``PF``) float32, top row first.

    Raises :class:`DataError` naming the file when it is missing, has a bad header or holds
    fewer values than its header announces.
    """
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as err:
        raise DataError(p, f"cannot read PFM file ({err.strerror or err})") from err
    magic, pos = _header_token(data, 0, p, "magic")
    if magic not in (b"Pf", b"PF"):
        raise DataError(p, f"not a PFM file (magic {magic[:8]!r}, expected b'Pf' or b'PF')")
    dims, pos = _header_token(data, pos, p, "size")
    try:
        width, height = (int(v) for v in dims.split())
        scale_line, pos = _header_token(data, pos, p, "scale")
        scale = float(scale_line)
    except ValueError as err:
        raise DataError(p, f"bad PFM header ({err})") from err
    if width <= 0 or height <= 0 or scale == 0.0:
        raise DataError(p, f"bad PFM header: size {width}x{height}, scale {scale}")
    channels = 1 if magic == b"Pf" else 3
    count = width * height * channels
    if len(data) - pos < 4 * count:
        raise DataError(
            p, f"truncated PFM data: {len(data) - pos} bytes, expected {4 * count} for {width}x{height}x{channels}"
        )
    values = np.frombuffer(data, dtype="<f4" if scale < 0 else ">f4", count=count, offset=pos)
    shape = (height, width) if channels == 1 else (height, width, 3)
    return values.reshape(shape)[::-1].astype(np.float32)
