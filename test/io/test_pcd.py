"""PCD files from the wild: binary_compressed written by an independent writer (open3d) reads as
its binary twin; hostile headers and payloads are refused by name."""

from __future__ import annotations

import struct
import warnings

import numpy as np
import pytest

from mf_lpr_ros.errors import DatasetError
from mf_lpr_ros.io.pcd import read_pcd

o3d = pytest.importorskip("open3d")
pytest.importorskip("lzf", reason="python-neo-lzf (make setup installs it) reads compressed PCD")


def write_with_open3d(path, points: np.ndarray, compressed: bool) -> None:
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    assert o3d.io.write_point_cloud(str(path), cloud, write_ascii=False, compressed=compressed)


@pytest.fixture
def twins(tmp_path):
    points = np.cumsum(np.random.default_rng(3).normal(size=(5000, 3)), axis=0)
    write_with_open3d(tmp_path / "binary.pcd", points, compressed=False)
    write_with_open3d(tmp_path / "compressed.pcd", points, compressed=True)
    assert b"DATA binary_compressed" in (tmp_path / "compressed.pcd").read_bytes()[:400]
    return points, tmp_path / "binary.pcd", tmp_path / "compressed.pcd"


def test_compressed_pcd_reads_as_its_binary_twin(twins):
    points, binary, compressed = twins
    np.testing.assert_array_equal(read_pcd(compressed), read_pcd(binary))
    np.testing.assert_allclose(read_pcd(compressed), points, rtol=1e-6, atol=1e-4)


def _data_start(raw: bytes) -> int:
    return raw.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n")


@pytest.mark.parametrize("damage, expected", [
    ("claims more data", "claims"),
    ("claims a longer stream", "truncated compressed PCD"),
    ("stream cut", "corrupt compressed PCD|truncated"),
    ("stream scrambled", "corrupt compressed PCD"),
    ("points disagree with width", "WIDTH x HEIGHT"),
    ("negative points", "POINTS must be"),
    ("field lists disagree", "FIELDS"),
])
def test_damaged_compressed_pcd_is_refused_by_name(twins, damage, expected):
    _, _, compressed = twins
    raw = bytearray(compressed.read_bytes())
    start = _data_start(bytes(raw))
    packed, unpacked = struct.unpack_from("<II", raw, start)
    if damage == "claims more data":
        struct.pack_into("<II", raw, start, packed, unpacked + 12)
    elif damage == "claims a longer stream":
        struct.pack_into("<II", raw, start, len(raw), unpacked)
    elif damage == "stream cut":
        raw = raw[:start + 8 + packed // 2]
        struct.pack_into("<II", raw, start, packed // 2, unpacked)
    elif damage == "stream scrambled":
        payload = np.frombuffer(bytes(raw[start + 8:]), np.uint8).copy()
        np.random.default_rng(0).shuffle(payload)
        raw[start + 8:] = payload.tobytes()
    elif damage == "points disagree with width":
        raw = bytearray(bytes(raw).replace(b"WIDTH 5000", b"WIDTH 4000"))
    elif damage == "negative points":
        raw = bytearray(bytes(raw).replace(b"POINTS 5000", b"POINTS -5").replace(
            b"WIDTH 5000", b"WIDTH -5"))
    elif damage == "field lists disagree":
        raw = bytearray(bytes(raw).replace(b"SIZE 4 4 4", b"SIZE 4 4"))
    compressed.write_bytes(bytes(raw))
    with pytest.raises(DatasetError, match=expected):
        read_pcd(compressed)


@pytest.mark.parametrize("points, rows, expected", [
    (2, "", "0 ASCII rows"),
    (2, "# no rows\n\n", "0 ASCII rows"),
    (2, "1 2 3\n", "1 ASCII rows"),
    (0, "", None),
])
def test_ascii_pcd_rows_are_counted_against_points(tmp_path, points, rows, expected):
    path = tmp_path / "cloud.pcd"
    path.write_text("VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
                    f"WIDTH {points}\nHEIGHT 1\nPOINTS {points}\nDATA ascii\n{rows}")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        if expected is None:
            assert read_pcd(path).shape == (0, 3)
        else:
            with pytest.raises(DatasetError, match=expected):
                read_pcd(path)
