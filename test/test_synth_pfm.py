"""PFM depth files: exact round trip, both byte orders, and clear errors that name the file."""

from __future__ import annotations

import numpy as np
import pytest

from vlocnetpp_core.data.pfm import read_pfm, write_pfm
from vlocnetpp_core.errors import DataError


@pytest.mark.parametrize("shape", [(7, 5), (4, 6, 3)])
def test_round_trip_is_exact(tmp_path, shape):
    a = np.random.default_rng(0).normal(size=shape).astype(np.float32) * 100
    a.flat[0] = 0.0
    p = tmp_path / "d.pfm"
    write_pfm(p, a)
    b = read_pfm(p)
    assert b.dtype == np.float32 and b.shape == a.shape
    assert np.array_equal(a, b)


def test_layout_follows_the_spec(tmp_path):
    """Header 'Pf', 'W H', negative scale (little-endian), then rows bottom-to-top."""
    a = np.arange(6, dtype=np.float32).reshape(2, 3)  # top row 0 1 2, bottom row 3 4 5
    p = tmp_path / "d.pfm"
    write_pfm(p, a)
    data = p.read_bytes()
    assert data.startswith(b"Pf\n3 2\n-1.0\n")
    assert np.array_equal(np.frombuffer(data[len(b"Pf\n3 2\n-1.0\n") :], "<f4"), [3, 4, 5, 0, 1, 2])


def test_reads_big_endian(tmp_path):
    p = tmp_path / "be.pfm"
    p.write_bytes(b"Pf\n2 1\n1.0\n" + np.array([1.5, -2.0], ">f4").tobytes())
    assert np.array_equal(read_pfm(p), [[1.5, -2.0]])


@pytest.mark.parametrize(
    "content, words",
    [
        (b"P6\n2 2\n255\n" + bytes(12), "not a PFM"),
        (b"Pf\n2 two\n-1.0\n" + bytes(16), "bad PFM header"),
        (b"Pf\n4 4\n-1.0\n" + bytes(20), "truncated PFM data"),
        (b"Pf\n4 4", "truncated PFM header"),
    ],
)
def test_bad_files_name_the_file(tmp_path, content, words):
    p = tmp_path / "bad.pfm"
    p.write_bytes(content)
    with pytest.raises(DataError, match=words) as err:
        read_pfm(p)
    assert str(p) in str(err.value)


def test_missing_file(tmp_path):
    with pytest.raises(DataError, match="missing.pfm"):
        read_pfm(tmp_path / "missing.pfm")
