"""Frame decoding shared by the node and the offline tools: encodings, row padding, bad buffers, depth units."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from vlocnetpp_core.camera.intrinsics import Intrinsics
from vlocnetpp_core.inference.network_input import network_input
from vlocnetpp_core.inference.preprocess import (
    DEPTH_ENCODINGS,
    IMAGE_ENCODINGS,
    FrameError,
    decode_compressed,
    decode_raw,
    depth_to_metres,
    to_rgb,
)

RNG = np.random.default_rng(5)
RGB = RNG.integers(0, 256, (7, 5, 3), dtype=np.uint8)


def _encode(rgb: np.ndarray, encoding: str) -> np.ndarray:
    code = {
        "rgb8": None,
        "bgr8": cv2.COLOR_RGB2BGR,
        "rgba8": cv2.COLOR_RGB2RGBA,
        "bgra8": cv2.COLOR_RGB2BGRA,
        "mono8": cv2.COLOR_RGB2GRAY,
    }[encoding]
    return rgb if code is None else cv2.cvtColor(rgb, code)


def _padded_buffer(a: np.ndarray, pad: int) -> tuple[bytes, int]:
    rows = a.reshape(a.shape[0], -1).view(np.uint8)
    step = rows.shape[1] + pad
    out = np.full((a.shape[0], step), 0xAB, np.uint8)
    out[:, : rows.shape[1]] = rows
    return out.tobytes(), step


@pytest.mark.parametrize("encoding", list(IMAGE_ENCODINGS))
@pytest.mark.parametrize("pad", [0, 3, 64])
def test_every_encoding_and_row_padding_decodes_to_the_same_rgb(encoding: str, pad: int):
    native = _encode(RGB, encoding)
    data, step = _padded_buffer(native, pad)
    pixels = decode_raw(data, 5, 7, step, encoding)
    assert np.array_equal(pixels, native)
    expected = cv2.cvtColor(native, cv2.COLOR_GRAY2RGB) if encoding == "mono8" else RGB
    assert np.array_equal(to_rgb(pixels, encoding), expected)


def test_depth_encodings_and_byte_order():
    mm = RNG.integers(0, 5000, (4, 6), dtype=np.uint16)
    mm[0, 0] = 0
    for bigendian in (False, True):
        raw = mm.astype(">u2" if bigendian else "<u2").tobytes()
        depth = depth_to_metres(decode_raw(raw, 6, 4, 12, "16UC1", bigendian), "16UC1")
        assert depth.dtype == np.float32
        np.testing.assert_allclose(depth, mm / 1000.0, rtol=1e-6)
    m = RNG.random((4, 6)).astype(np.float32) * 10
    m[1, 1], m[2, 2], m[3, 3] = np.nan, np.inf, -1.0
    data, step = _padded_buffer(m, 8)
    depth = depth_to_metres(decode_raw(data, 6, 4, step, "32FC1"), "32FC1")
    assert depth[1, 1] == depth[2, 2] == depth[3, 3] == 0.0  # invalid -> 0, the model's "no depth"
    ok = np.isfinite(m) & (m >= 0)
    assert np.array_equal(depth[ok], m[ok])


@pytest.mark.parametrize(
    ("width", "height", "step", "nbytes", "encoding", "reason"),
    [
        (5, 7, 15, 105, "yuv422", "unsupported_encoding"),
        (0, 7, 0, 0, "rgb8", "empty_image"),
        (5, 0, 15, 0, "rgb8", "empty_image"),
        (5, 7, 14, 105, "rgb8", "bad_step"),
        (5, 7, 15, 104, "rgb8", "truncated_data"),
        (5, 7, 15, 10, "rgb8", "truncated_data"),
        (4, 7, 12, 105, "rgb8", "data_size_mismatch"),
        (5, 7, 10, 70, "16UC1", "unsupported_encoding"),  # a depth encoding on the colour path
    ],
)
def test_bad_buffers_are_refused_with_a_reason(width, height, step, nbytes, encoding, reason):
    with pytest.raises(FrameError) as err:
        decode_raw(bytes(nbytes), width, height, step, encoding, allowed=IMAGE_ENCODINGS)
    assert err.value.reason == reason
    assert str(err.value)  # says what was wrong


def test_arrays_that_do_not_fit_their_encoding_are_refused():
    for array, encoding, reason in [
        (RGB, "rgba8", "bad_array"),
        (RGB.astype(np.float32), "rgb8", "bad_array"),
        (RGB[:, :, 0], "rgb8", "bad_array"),
        (np.zeros((0, 4, 3), np.uint8), "rgb8", "empty_image"),
        (RGB, "32FC1", "unsupported_encoding"),
    ]:
        with pytest.raises(FrameError) as err:
            to_rgb(array, encoding)
        assert err.value.reason == reason
    with pytest.raises(FrameError) as err:
        depth_to_metres(np.zeros((3, 3), np.float64), "32FC1")
    assert err.value.reason == "bad_array"
    with pytest.raises(FrameError) as err:
        depth_to_metres(np.zeros((3, 3), np.uint8), "8UC1")
    assert err.value.reason == "unsupported_encoding" and "8UC1" not in DEPTH_ENCODINGS


def test_compressed_images_decode_and_garbage_is_refused():
    ok, png = cv2.imencode(".png", cv2.cvtColor(RGB, cv2.COLOR_RGB2BGR))
    assert ok and np.array_equal(decode_compressed(png.tobytes()), RGB)
    for data in (b"", b"not an image at all"):
        with pytest.raises(FrameError) as err:
            decode_compressed(data)
        assert err.value.reason == "decode_failed"


def test_network_input_resizes_anisotropically_and_scales_the_intrinsics():
    rgb = RNG.integers(0, 256, (72, 160, 3), dtype=np.uint8)
    K = Intrinsics(100.0, 90.0, 79.5, 35.5, 160, 72)
    depth = np.full((72, 160), 4.0, np.float32)
    depth[:, :80] = 0.0
    image, Kt, d = network_input(rgb, (64, 48), K, depth)
    assert image.shape == (1, 3, 48, 64) and image.dtype == torch.float32
    assert 0.0 <= float(image.min()) and float(image.max()) <= 1.0
    np.testing.assert_allclose(Kt[0].numpy(), K.resized(64, 48).matrix(), rtol=1e-6)
    assert set(np.unique(d.numpy()).tolist()) == {0.0, 4.0}  # nearest neighbour: no blended edge values
    assert (d[0, 0, :, :32] == 0).all() and (d[0, 0, :, 32:] == 4.0).all()
    with pytest.raises(FrameError) as err:
        network_input(rgb, (64, 48), K, depth[:70])
    assert err.value.reason == "depth_size"


@pytest.mark.parametrize("size", [(64, 48), (80, 96), (224, 128)])  # 96x72 images: shrunk, one side each way, enlarged
def test_a_dataset_frame_and_the_same_image_through_the_node_give_identical_network_inputs(tmp_path, size):
    """Evaluation reads frames through the dataset transform; the node gets them as sensor_msgs/Image and
    the Localizer's preprocessing: both must hand the network the same pixels, intrinsics and depth."""
    from builtin_interfaces.msg import Time
    from data_fixtures import trajectory, write_deeploc_split
    from std_msgs.msg import Header

    from vlocnetpp_core.data import ClipDataset, make_transform, open_dataset
    from vlocnetpp_core.data.imageio import read_rgb
    from vlocnetpp_ros import conversions

    t, q = trajectory(2)
    write_deeploc_split(tmp_path, "test", [1, 2], t, q, depth="pfm")
    index = open_dataset(tmp_path, None, "test")
    clips = ClipDataset(index, 1, make_transform(False, size))
    for i, record in enumerate(index.records):
        item = clips[i]
        msg = conversions.array_to_image(read_rgb(record.image), "rgb8", Header(stamp=Time(), frame_id="camera"))
        image, K, depth = network_input(
            to_rgb(conversions.image_to_array(msg), msg.encoding), size, index.intrinsics, index.load(i).depth
        )
        assert torch.equal(image[0], item["image"][0])
        assert torch.allclose(K[0], item["K"][0], rtol=1e-6)
        assert torch.equal(depth[0], item["depth"][0])
