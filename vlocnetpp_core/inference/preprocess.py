"""Camera frames in, numpy arrays out: decoding raw buffers by encoding, depth units, resizing. No torch here
(``vlocnetpp extract`` uses it); :mod:`.network_input` makes the network's tensors of these arrays.

Shared by the ROS node, bag replay and the offline tools, so every path
turns the same bytes into the same pixels. No ROS types here: a raw image is its ``data``
buffer plus ``width``, ``height``, ``step`` (bytes per row, may include padding), ``encoding``
and ``is_bigendian``, as in ``sensor_msgs/Image``.

Every problem with a frame raises :class:`FrameError`, whose ``reason`` is a short fixed
keyword (counted by the node's diagnostics) and whose message says what was wrong.
:func:`check_raw` and :func:`check_compressed` run the checks that need only the header and the
length of ``data`` (no pixel is touched), so the node can refuse a malformed message in its
subscription callback before it takes the mailbox slot of a good frame; compressed images must
be PNG or JPEG and may not declare more than :data:`MAX_DECODED_PIXELS` (a small PNG of a huge
blank image would otherwise make the decoder allocate gigabytes).
"""

from __future__ import annotations

import struct
from collections.abc import Iterable

import cv2
import numpy as np

# Colour encodings the localizer accepts: channels and the cv2 conversion to RGB (None: already RGB).
IMAGE_ENCODINGS: dict[str, tuple[int, int | None]] = {
    "rgb8": (3, None),
    "bgr8": (3, cv2.COLOR_BGR2RGB),
    "rgba8": (4, cv2.COLOR_RGBA2RGB),
    "bgra8": (4, cv2.COLOR_BGRA2RGB),
    "mono8": (1, cv2.COLOR_GRAY2RGB),
}
# Depth encodings: numpy dtype and the factor to metres (0 stays "invalid").
DEPTH_ENCODINGS: dict[str, tuple[np.dtype, float]] = {
    "32FC1": (np.dtype(np.float32), 1.0),
    "16UC1": (np.dtype(np.uint16), 1e-3),
}
# Largest compressed image decoded: 8192 x 8192 (an 8K UHD frame is 7680 x 4320), 192 MiB as RGB.
MAX_DECODED_PIXELS = 1 << 26

REASONS = (
    "unsupported_encoding",  # encoding not in IMAGE_ENCODINGS (or DEPTH_ENCODINGS for depth)
    "empty_image",  # width or height is zero
    "bad_step",  # step smaller than one row of pixels
    "truncated_data",  # fewer bytes than step * height
    "data_size_mismatch",  # more bytes than step * height (width/height do not describe the buffer)
    "bad_array",  # an array whose shape or dtype does not fit its encoding
    "decode_failed",  # a compressed image that is not a PNG or JPEG or cannot be decoded
    "image_too_large",  # a compressed image whose header declares more than MAX_DECODED_PIXELS
    "depth_size",  # depth image of another size than the colour image
)


class FrameError(ValueError):
    """A frame that cannot be used; ``reason`` is one keyword of :data:`REASONS` (or ``nan_output``)."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


# --------------------------------------------------------------------------- raw buffers


_LAYOUTS: dict[str, tuple[int, np.dtype]] = {
    **{enc: (channels, np.dtype(np.uint8)) for enc, (channels, _) in IMAGE_ENCODINGS.items()},
    **{enc: (1, dtype) for enc, (dtype, _) in DEPTH_ENCODINGS.items()},
}


def check_raw(
    size: int, width: int, height: int, step: int, encoding: str, allowed: Iterable[str] | None = None
) -> tuple[int, np.dtype, int]:
    """The checks of :func:`decode_raw` on a buffer of ``size`` bytes, from the header alone (O(1)).

    Returns ``(channels, dtype, row bytes)``; raises :class:`FrameError` (``unsupported_encoding``,
    ``empty_image``, ``bad_step``, ``truncated_data``, ``data_size_mismatch``).
    """
    allowed = tuple(_LAYOUTS if allowed is None else allowed)
    if encoding not in allowed:
        shown = encoding if len(encoding) <= 40 else encoding[:40] + "..."
        raise FrameError(
            "unsupported_encoding", f"unsupported encoding {shown!r}; expected one of {', '.join(allowed)}"
        )
    channels, dtype = _LAYOUTS[encoding]
    width, height, step, size = int(width), int(height), int(step), int(size)
    if width <= 0 or height <= 0:
        raise FrameError("empty_image", f"{encoding} image is {width}x{height}: nothing to process")
    row = width * channels * dtype.itemsize
    if step < row:
        raise FrameError(
            "bad_step", f"{encoding} image {width}x{height}: step {step} is smaller than a row of {row} bytes"
        )
    if size < step * height:
        raise FrameError(
            "truncated_data",
            f"{encoding} image {width}x{height}, step {step}: {size} data bytes, expected {step * height}",
        )
    if size > step * height:
        raise FrameError(
            "data_size_mismatch",
            f"{encoding} image {width}x{height}, step {step}: "
            f"{size} data bytes, expected {step * height} (wrong width/height?)",
        )
    return channels, dtype, row


def decode_raw(
    data,
    width: int,
    height: int,
    step: int,
    encoding: str,
    is_bigendian: bool = False,
    allowed: Iterable[str] | None = None,
) -> np.ndarray:
    """Pixels of a raw image buffer: ``(H, W)`` for one channel, else ``(H, W, C)``, in the
    buffer's own channel order and the encoding's dtype (native byte order, always a copy).

    ``data`` is anything with the buffer protocol (bytes, array.array, numpy); row padding
    (``step`` larger than a row) is skipped. ``allowed`` restricts the encodings (default: the
    colour and depth encodings together). Raises :class:`FrameError` (see :func:`check_raw`).
    """
    buf = np.frombuffer(data, dtype=np.uint8)
    channels, dtype, row = check_raw(buf.size, width, height, step, encoding, allowed)
    height, width = int(height), int(width)
    rows = buf.reshape(height, int(step))[:, :row].copy()
    pixels = rows.view(dtype.newbyteorder(">" if is_bigendian else "<")).astype(dtype, copy=False)
    return pixels.reshape(height, width) if channels == 1 else pixels.reshape(height, width, channels)


# --------------------------------------------------------------------------- colour


def to_rgb(image: np.ndarray, encoding: str) -> np.ndarray:
    """``(H, W, 3) uint8`` RGB of an 8-bit image array in ``encoding`` (see :data:`IMAGE_ENCODINGS`)."""
    if encoding not in IMAGE_ENCODINGS:
        raise FrameError(
            "unsupported_encoding",
            f"unsupported image encoding {encoding!r}; expected one of {', '.join(IMAGE_ENCODINGS)}",
        )
    channels, code = IMAGE_ENCODINGS[encoding]
    a = np.asarray(image)
    fits = a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 1) if channels == 1 else a.ndim == 3 and a.shape[2] == channels
    if a.dtype != np.uint8 or not fits:
        raise FrameError(
            "bad_array", f"array {a.shape} {a.dtype} does not fit encoding {encoding} ({channels} x uint8)"
        )
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise FrameError("empty_image", f"{encoding} image is {a.shape[1]}x{a.shape[0]}: nothing to process")
    if code is None:
        return a
    return cv2.cvtColor(np.ascontiguousarray(a), code)


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_JPEG_FRAME_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}  # SOF0..SOF15 (not DHT, JPG, DAC)


def compressed_size(data) -> tuple[str, int, int]:
    """``(format, width, height)`` that the header of a PNG (``IHDR``) or JPEG (first frame marker) buffer
    declares, without decoding; ``decode_failed`` for anything else. Reads a few bytes per JPEG segment."""
    buf = memoryview(data).cast("B") if not isinstance(data, bytes) else data
    n = len(buf)
    if n >= 24 and bytes(buf[:8]) == _PNG_SIGNATURE and bytes(buf[12:16]) == b"IHDR":
        width, height = struct.unpack(">II", bytes(buf[16:24]))
        return "png", width, height
    if n >= 4 and buf[0] == 0xFF and buf[1] == 0xD8:
        i = 2
        while i + 4 <= n and buf[i] == 0xFF:
            marker = buf[i + 1]
            if marker == 0xFF:  # fill byte
                i += 1
            elif marker == 0x01 or 0xD0 <= marker <= 0xD7:  # markers without a length
                i += 2
            elif marker in _JPEG_FRAME_MARKERS and i + 9 <= n:
                return "jpeg", (buf[i + 7] << 8) | buf[i + 8], (buf[i + 5] << 8) | buf[i + 6]
            elif (
                marker in (0xD9, 0xDA) or (buf[i + 2] << 8 | buf[i + 3]) < 2
            ):  # end or scan before a frame header, bad length
                break
            else:
                i += 2 + (buf[i + 2] << 8 | buf[i + 3])
    raise FrameError("decode_failed", f"the {n}-byte compressed image is not a PNG or JPEG with a readable header")


def check_compressed(data) -> tuple[int, int]:
    """``(width, height)`` of a PNG / JPEG buffer from its header; :class:`FrameError` ``decode_failed`` when it is
    neither, ``image_too_large`` when it declares more than :data:`MAX_DECODED_PIXELS`."""
    fmt, width, height = compressed_size(data)
    if width * height > MAX_DECODED_PIXELS:
        raise FrameError(
            "image_too_large",
            f"the {fmt} image declares {width}x{height} pixels, more than the {MAX_DECODED_PIXELS} decoded at most",
        )
    return width, height


def decode_compressed(data) -> np.ndarray:
    """``(H, W, 3) uint8`` RGB of a PNG / JPEG buffer (``sensor_msgs/CompressedImage.data``); checked by
    :func:`check_compressed` before the decoder allocates anything."""
    check_compressed(data)
    buf = np.frombuffer(data, dtype=np.uint8)
    bgr = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    if bgr is None:
        raise FrameError("decode_failed", f"cannot decode the {buf.size}-byte compressed image (PNG or JPEG expected)")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


# --------------------------------------------------------------------------- depth


def depth_to_metres(depth: np.ndarray, encoding: str) -> np.ndarray:
    """``(H, W) float32`` metres of a ``32FC1`` (metres) or ``16UC1`` (millimetres) depth array.

    Invalid pixels (0, negative, NaN, infinite) become 0, the "no depth" value of the model.
    """
    if encoding not in DEPTH_ENCODINGS:
        raise FrameError(
            "unsupported_encoding",
            f"unsupported depth encoding {encoding!r}; expected one of {', '.join(DEPTH_ENCODINGS)}",
        )
    a = np.asarray(depth)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    dtype, scale = DEPTH_ENCODINGS[encoding]
    if a.ndim != 2 or a.dtype != dtype:
        raise FrameError(
            "bad_array", f"depth array {a.shape} {a.dtype} does not fit encoding {encoding} (H x W {dtype})"
        )
    metres = a.astype(np.float32) * np.float32(scale)
    metres[~np.isfinite(metres) | (metres < 0)] = 0.0
    return metres


# --------------------------------------------------------------------------- resizing


def resize_image(rgb: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``rgb (H, W, 3) uint8`` resized to ``size = (W', H')``: area averaging when either side shrinks, else
    bilinear. The one image resize of the package: training transforms, evaluation and the node all use it."""
    w, h = size
    if rgb.shape[1] == w and rgb.shape[0] == h:
        return rgb
    shrink = w < rgb.shape[1] or h < rgb.shape[0]
    return cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)


def resize_nearest(array: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``(H, W)`` depth (float32 metres) or labels (uint8) resized to ``size = (W', H')`` with exact,
    pixel-centre aligned nearest neighbour (source pixel ``floor((x + 0.5) * W / W')``): values are never
    blended, so invalid depth stays invalid and labels stay labels."""
    w, h = size
    if array.shape[1] == w and array.shape[0] == h:
        return array
    return cv2.resize(array, (w, h), interpolation=cv2.INTER_NEAREST_EXACT)
