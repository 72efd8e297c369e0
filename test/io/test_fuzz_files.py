"""Property-based tests of the point-file readers: well-formed PCD (ascii, binary,
binary_compressed) and PLY (ascii, binary either endianness) files, then damaged. Whatever the
damage, a reader returns (N, 3) float32 points or raises DatasetError naming the file; a file
cut short or missing a header line reads as its original or is refused."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mf_lpr_ros.errors import DatasetError
from mf_lpr_ros.io.pcd import read_pcd
from mf_lpr_ros.io.ply import read_ply

FUZZ = settings(max_examples=120, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])
MANY = settings(max_examples=800, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])


def pcd_bytes(points: np.ndarray, encoding: str) -> bytes:
    n = len(points)
    header = (f"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\n"
              f"COUNT 1 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n"
              f"DATA {encoding}\n").encode()
    records = np.zeros((n, 4), dtype="<f4")
    records[:, :3] = points
    if encoding == "ascii":
        return header + "".join(" ".join(f"{v:.9g}" for v in row) + "\n"
                                for row in records).encode()
    if encoding == "binary":
        return header + records.tobytes()
    import lzf

    columns = np.ascontiguousarray(records.T).tobytes()
    packed = lzf.compress(columns) or b""
    return header + np.array([len(packed), len(columns)], "<u4").tobytes() + packed


def ply_bytes(points: np.ndarray, encoding: str) -> bytes:
    n = len(points)
    header = (f"ply\nformat {encoding} 1.0\ncomment fuzz\nelement vertex {n}\n"
              "property float x\nproperty float y\nproperty float z\nproperty uchar label\n"
              "end_header\n").encode()
    if encoding == "ascii":
        return header + "".join(f"{x:.9g} {y:.9g} {z:.9g} 7\n" for x, y, z in points).encode()
    order = "<" if encoding == "binary_little_endian" else ">"
    records = np.zeros(n, dtype=[("x", order + "f4"), ("y", order + "f4"), ("z", order + "f4"),
                                 ("label", "u1")])
    for k, name in enumerate("xyz"):
        records[name] = points[:, k]
    return header + records.tobytes()


FORMATS = {"pcd": (read_pcd, pcd_bytes, ["ascii", "binary", "binary_compressed"]),
           "ply": (read_ply, ply_bytes, ["ascii", "binary_little_endian",
                                         "binary_big_endian"])}


@st.composite
def damaged_files(draw, kind: str):
    """(original points, file bytes after the damage, whether the damage may only cut)."""
    _, write, encodings = FORMATS[kind]
    n = draw(st.integers(1, 40))
    points = np.array(draw(st.lists(st.floats(-1e3, 1e3, allow_nan=False, width=32),
                                    min_size=3 * n, max_size=3 * n)),
                      dtype=np.float32).reshape(n, 3)
    data = write(points, draw(st.sampled_from(encodings)))
    damage = draw(st.sampled_from(["cut", "drop header line", "flip byte", "replace token",
                                   "insert bytes"]))
    if damage == "cut":
        data = data[:draw(st.integers(0, len(data) - 1))]
    elif damage == "drop header line":
        lines = data.split(b"\n")
        header_lines = next(k for k, line in enumerate(lines)
                            if line.startswith((b"DATA", b"end_header")))
        drop = draw(st.integers(0, header_lines))
        data = b"\n".join(lines[:drop] + lines[drop + 1:])
    elif damage == "flip byte":
        position = draw(st.integers(0, len(data) - 1))
        data = data[:position] + bytes([data[position] ^ draw(st.integers(1, 255))]) + \
            data[position + 1:]
    elif damage == "replace token":
        words = data[:200].split(b" ")
        k = draw(st.integers(0, len(words) - 1))
        words[k] = draw(st.sampled_from([b"-1", b"0", b"99999999999", b"nan", b"x", b"F",
                                         b"list", b"binary_compressed", b"", b"8"]))
        data = b" ".join(words) + data[200:]
    else:
        position = draw(st.integers(0, len(data)))
        data = data[:position] + draw(st.binary(min_size=1, max_size=16)) + data[position:]
    return points, data, damage in ("cut", "drop header line")


def check_reads_or_refuses(kind: str, case, tmp_path) -> None:
    read = FORMATS[kind][0]
    points, data, only_removed = case
    path = tmp_path / f"fuzz.{kind}"
    path.write_bytes(data)
    try:
        result = read(path)
    except DatasetError as error:
        assert str(path) in str(error), "the message names the file"
        return
    assert result.dtype == np.float32 and result.ndim == 2 and result.shape[1] == 3
    if only_removed:
        np.testing.assert_array_equal(result, points)


@pytest.fixture(autouse=True)
def _needs_lzf():
    pytest.importorskip("lzf", reason="python-neo-lzf (make setup installs it)")


@FUZZ
@given(case=damaged_files("pcd"))
def test_damaged_pcd_reads_or_is_refused_by_name(tmp_path, case):
    check_reads_or_refuses("pcd", case, tmp_path)


@FUZZ
@given(case=damaged_files("ply"))
def test_damaged_ply_reads_or_is_refused_by_name(tmp_path, case):
    check_reads_or_refuses("ply", case, tmp_path)


@pytest.mark.slow
@MANY
@given(kind=st.sampled_from(["pcd", "ply"]), data=st.data())
def test_damaged_point_files_many_more(tmp_path, kind, data):
    check_reads_or_refuses(kind, data.draw(damaged_files(kind)), tmp_path)


@pytest.mark.parametrize("kind", sorted(FORMATS))
def test_well_formed_files_read_exactly(tmp_path, kind):
    read, write, encodings = FORMATS[kind]
    points = np.random.default_rng(1).normal(size=(30, 3)).astype(np.float32)
    for encoding in encodings:
        path = tmp_path / f"{encoding}.{kind}"
        path.write_bytes(write(points, encoding))
        np.testing.assert_array_equal(read(path), points)
