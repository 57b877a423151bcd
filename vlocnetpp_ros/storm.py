"""Malformed inputs for the localizer node, class by class: what the storm test (``test/test_node_storm.py``)
and the soak benchmark (:mod:`vlocnetpp_ros.soak`) send it.

Each :class:`BadClass` makes one kind of bad message for one input of the node (``image``: raw
``sensor_msgs/Image``; ``compressed``: ``CompressedImage``; ``depth``: depth ``Image``;
``camera_info``) and names the diagnostics key the node counts it under when the key follows
from the message alone (``key``), or None when the outcome depends on timing (a well-formed frame
with a strange stamp is processed or dropped; a depth image is judged against the colour frame with
its stamp). Sizes are drawn at random around ``width x height``; a generator is deterministic for
a seeded ``numpy.random.Generator``.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from builtin_interfaces.msg import Time
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Header

INPUTS = ("image", "compressed", "depth", "camera_info")
FAR_FUTURE_S = 2**31 - 1  # the largest builtin_interfaces/Time.sec


@dataclass(frozen=True)
class BadClass:
    """One class of malformed message: ``make(rng, stamp_s, width, height)`` for input ``kind``."""

    name: str
    kind: str  # one of INPUTS
    key: str | None  # diagnostics key counting it, when that follows from the message alone
    make: Callable[[np.random.Generator, float, int, int], object]


def _header(stamp_s: float) -> Header:
    sec, nanosec = divmod(int(round(stamp_s * 1e9)), 1_000_000_000)
    return Header(stamp=Time(sec=int(sec), nanosec=int(nanosec)), frame_id="camera")


def _raw(
    stamp_s: float,
    width: int,
    height: int,
    encoding: str,
    step: int,
    size: int,
    bigendian: bool = False,
    fill: bytes | None = None,
) -> Image:
    data = fill if fill is not None else bytes(max(0, size))
    return Image(
        header=_header(stamp_s),
        width=int(width),
        height=int(height),
        encoding=encoding,
        step=int(step),
        is_bigendian=int(bigendian),
        data=data,
    )


def _odd_encoding(rng: np.random.Generator) -> str:
    choices = (
        "yuv422",
        "",
        "bayer_rggb8",
        "rgb16",
        "8UC3",
        "32FC1",
        "16UC1",
        "mono16",
        "x" * int(rng.integers(41, 300)),
    )
    return choices[int(rng.integers(len(choices)))]


def _rgb(rng: np.random.Generator, width: int, height: int) -> bytes:
    return rng.integers(0, 256, width * height * 3, dtype=np.uint8).tobytes()


def _depth_values(value: float, width: int, height: int) -> bytes:
    return np.full((height, width), value, np.float32).tobytes()


def _png_bomb(width: int = 30_000, height: int = 30_000) -> bytes:
    """A valid PNG header declaring ``width x height`` grey pixels (a 2.7 GB image once decoded to RGB) with a few bytes
    of data."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(bytes(4096))) + chunk(b"IEND", b"")
    )


_BOMB = _png_bomb()


def _compressed(stamp_s: float, data: bytes, fmt: str = "png") -> CompressedImage:
    return CompressedImage(header=_header(stamp_s), format=fmt, data=data)


def _png_header(width: int, height: int) -> bytes:
    """The first 33 bytes of a PNG (signature and IHDR) of an RGB image, without any pixel data."""
    return _png_bomb(width, height)[:33]


BAD_CLASSES: tuple[BadClass, ...] = (
    # raw camera images
    BadClass(
        "unknown_encoding",
        "image",
        "rejected.unsupported_encoding",
        lambda r, s, w, h: _raw(s, w, h, _odd_encoding(r), 3 * w, 3 * w * h),
    ),
    BadClass(
        "zero_size",
        "image",
        "rejected.empty_image",
        lambda r, s, w, h: _raw(s, *((0, h), (w, 0), (0, 0))[int(r.integers(3))], "rgb8", 3 * w, 0),
    ),
    BadClass(
        "lying_step",
        "image",
        "rejected.bad_step",
        lambda r, s, w, h: _raw(s, w, h, "rgb8", int(r.integers(0, 3 * w)), 3 * w * h),
    ),
    BadClass(
        "truncated",
        "image",
        "rejected.truncated_data",
        lambda r, s, w, h: _raw(s, w, h, "bgr8", 3 * w, 3 * w * h - int(r.integers(1, 3 * w * h))),
    ),
    BadClass(
        "huge_header",
        "image",
        "rejected.truncated_data",
        lambda r, s, w, h: _raw(s, 2**20, 2**20, "rgb8", 3 * 2**20, 100),
    ),
    BadClass(
        "oversized",
        "image",
        "rejected.data_size_mismatch",
        lambda r, s, w, h: _raw(s, w, h, "mono8", w, w * h + int(r.integers(1, 4096))),
    ),
    BadClass(
        "big_endian",
        "image",
        None,
        lambda r, s, w, h: _raw(s, w, h, "rgb8", 3 * w, 0, bigendian=True, fill=_rgb(r, w, h)),
    ),
    BadClass("stamp_zero", "image", None, lambda r, s, w, h: _raw(0.0, w, h, "rgb8", 3 * w, 0, fill=_rgb(r, w, h))),
    BadClass(
        "stamp_backwards",
        "image",
        None,
        lambda r, s, w, h: _raw(max(0.0, s - 50.0), w, h, "rgb8", 3 * w, 0, fill=_rgb(r, w, h)),
    ),
    BadClass(
        "stamp_far_future",
        "image",
        None,
        lambda r, s, w, h: _raw(FAR_FUTURE_S, w, h, "rgb8", 3 * w, 0, fill=_rgb(r, w, h)),
    ),
    # compressed camera images
    BadClass(
        "random_bytes",
        "compressed",
        "rejected.decode_failed",
        lambda r, s, w, h: _compressed(
            s, r.integers(0, 256, int(r.integers(0, 4096)), dtype=np.uint8).tobytes(), "jpeg"
        ),
    ),
    BadClass(
        "jpeg_garbage",
        "compressed",
        "rejected.decode_failed",
        lambda r, s, w, h: _compressed(
            s, b"\xff\xd8\xff\xdb" + r.integers(0, 256, 2000, dtype=np.uint8).tobytes(), "jpeg"
        ),
    ),
    BadClass("png_bomb", "compressed", "rejected.image_too_large", lambda r, s, w, h: _compressed(s, _BOMB)),
    BadClass("png_without_pixels", "compressed", None, lambda r, s, w, h: _compressed(s, _png_header(w, h))),
    # depth images
    BadClass(
        "depth_nan",
        "depth",
        None,
        lambda r, s, w, h: _raw(s, w, h, "32FC1", 4 * w, 0, fill=_depth_values(np.nan, w, h)),
    ),
    BadClass(
        "depth_inf",
        "depth",
        None,
        lambda r, s, w, h: _raw(s, w, h, "32FC1", 4 * w, 0, fill=_depth_values(np.inf, w, h)),
    ),
    BadClass(
        "depth_negative",
        "depth",
        None,
        lambda r, s, w, h: _raw(s, w, h, "32FC1", 4 * w, 0, fill=_depth_values(-2.0, w, h)),
    ),
    BadClass("depth_wrong_size", "depth", None, lambda r, s, w, h: _raw(s, w // 2, h, "16UC1", w, w * h)),
    BadClass(
        "depth_unknown_encoding",
        "depth",
        "ignored.depth_unsupported_encoding",
        lambda r, s, w, h: _raw(
            s, w, h, _odd_encoding(r).replace("32FC1", "rgb8").replace("16UC1", "mono8"), 4 * w, 4 * w * h
        ),
    ),
    BadClass(
        "depth_truncated",
        "depth",
        "ignored.depth_truncated_data",
        lambda r, s, w, h: _raw(s, w, h, "32FC1", 4 * w, 4 * w * h - int(r.integers(1, 4 * w * h))),
    ),
    BadClass(
        "depth_oversized",
        "depth",
        "ignored.depth_data_size_mismatch",
        lambda r, s, w, h: _raw(s, w, h, "16UC1", 2 * w, 2 * w * h + int(r.integers(1, 4096))),
    ),
    BadClass("depth_zero_size", "depth", "ignored.depth_empty_image", lambda r, s, w, h: _raw(s, 0, h, "32FC1", 0, 0)),
    BadClass(
        "depth_lying_step",
        "depth",
        "ignored.depth_bad_step",
        lambda r, s, w, h: _raw(s, w, h, "32FC1", 2 * w, 4 * w * h),
    ),
    # camera info
    BadClass(
        "info_nan",
        "camera_info",
        "ignored.camera_info_invalid",
        lambda r, s, w, h: CameraInfo(header=_header(s), width=w, height=h, k=[float("nan")] * 9),
    ),
    BadClass(
        "info_zero_size",
        "camera_info",
        "ignored.camera_info_invalid",
        lambda r, s, w, h: CameraInfo(
            header=_header(s), width=0, height=0, k=[100.0, 0, w / 2, 0, 100.0, h / 2, 0, 0, 1]
        ),
    ),
    BadClass(
        "info_negative_focal",
        "camera_info",
        "ignored.camera_info_invalid",
        lambda r, s, w, h: CameraInfo(
            header=_header(s), width=w, height=h, k=[-100.0, 0, w / 2, 0, 100.0, h / 2, 0, 0, 1]
        ),
    ),
)


def classes_for(kinds: tuple[str, ...] | list[str]) -> list[BadClass]:
    """The classes of the given inputs (a node subscribes to ``image`` or ``compressed``, not both)."""
    unknown = set(kinds) - set(INPUTS)
    if unknown:
        raise ValueError(f"unknown inputs {sorted(unknown)}; expected some of {', '.join(INPUTS)}")
    return [c for c in BAD_CLASSES if c.kind in kinds]


def bad_messages(
    rng: np.random.Generator, classes: list[BadClass], count: int, stamp_s: float, width: int, height: int
):
    """``count`` ``(class, message)`` pairs, classes drawn uniformly, stamps ``stamp_s`` (the strange-stamp classes
    choose their own)."""
    for k in rng.integers(0, len(classes), count):
        cls = classes[int(k)]
        yield cls, cls.make(rng, stamp_s, width, height)
