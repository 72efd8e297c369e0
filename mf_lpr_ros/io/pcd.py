"""Reader for PCD files (ascii, binary and binary_compressed), x, y, z (+ any other fields,
ignored). The header is checked before any data is read: every count, size and type, the number
of points against WIDTH x HEIGHT, and (compressed) both sizes the file claims; each failure is a
DatasetError naming the file and the problem.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mf_lpr_ros.errors import DatasetError
from mf_lpr_ros.optional import require

_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4",
          ("I", 8): "i8", ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}
ENCODINGS = ("ascii", "binary", "binary_compressed")
MAX_HEADER_BYTES = 1 << 16
MAX_POINTS = 1 << 31
_COMPRESSED_SIZES = struct.Struct("<II")


@dataclass(frozen=True)
class PcdHeader:
    """A checked PCD header: the fields (name, numpy type, count), the points and the encoding,
    and where the data starts."""

    fields: tuple[tuple[str, str, int], ...]
    n_points: int
    encoding: str
    data_start: int

    @property
    def record_dtype(self) -> np.dtype:
        return np.dtype([(name, kind, (count,) if count > 1 else ())
                         for name, kind, count in self.fields])


def read_pcd(path: str | Path) -> np.ndarray:
    """The x, y, z of a PCD file as (N, 3) float32."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as error:
        raise DatasetError(f"cannot read PCD {path}: {error}") from error
    header = parse_pcd_header(raw, path)
    if header.encoding == "ascii":
        return _ascii_points(raw, header, path)
    if header.encoding == "binary":
        needed = header.n_points * header.record_dtype.itemsize
        if len(raw) - header.data_start < needed:
            raise DatasetError(f"{path}: truncated PCD ({len(raw) - header.data_start} data "
                               f"bytes, {needed} expected)")
        if len(raw) - header.data_start > needed:
            # The header does not describe the data: reading it would misplace every field.
            raise DatasetError(f"{path}: {len(raw) - header.data_start} bytes of point data, "
                               f"the header describes {needed}")
        records = np.frombuffer(raw, dtype=header.record_dtype, count=header.n_points,
                                offset=header.data_start)
        return np.stack([records["x"], records["y"], records["z"]], axis=1).astype(np.float32)
    return _compressed_points(raw, header, path)


def parse_pcd_header(raw: bytes, path: Path) -> PcdHeader:
    """The header of a PCD file's bytes, checked (see the module doc)."""
    values: dict[str, list[str]] = {}
    offset = 0
    while True:
        end = raw.find(b"\n", offset, MAX_HEADER_BYTES)
        if end < 0:
            raise DatasetError(f"{path}: PCD header has no DATA line in its first "
                               f"{MAX_HEADER_BYTES} bytes")
        line = raw[offset:end].decode("ascii", errors="replace").strip()
        offset = end + 1
        if not line or line.startswith("#"):
            continue
        key, *items = line.split()
        values[key.upper()] = items
        if key.upper() == "DATA":
            break
    try:
        names = values["FIELDS"]
        sizes = [int(s) for s in values["SIZE"]]
        types = [t.upper() for t in values["TYPE"]]
        counts = [int(c) for c in values.get("COUNT", ["1"] * len(names))]
        n_points = int(values["POINTS"][0])
        encoding = values["DATA"][0].lower()
    except (KeyError, ValueError, IndexError) as error:
        raise DatasetError(f"{path}: malformed PCD header ({error})") from None
    if not len(names) == len(sizes) == len(types) == len(counts):
        raise DatasetError(f"{path}: PCD header lists {len(names)} FIELDS, {len(sizes)} SIZE, "
                           f"{len(types)} TYPE and {len(counts)} COUNT entries")
    if not 0 <= n_points < MAX_POINTS:
        raise DatasetError(f"{path}: PCD POINTS must be in [0, {MAX_POINTS}), got {n_points}")
    _check_width_height(values, n_points, path)
    if encoding not in ENCODINGS:
        raise DatasetError(f"{path}: PCD encoding {encoding!r} is not one of {ENCODINGS}")
    if not {"x", "y", "z"} <= set(names):
        raise DatasetError(f"{path}: PCD has no x, y, z fields (fields: {names})")
    fields = []
    for name, size, kind, count in zip(names, sizes, types, counts):
        if (kind, size) not in _TYPES:
            raise DatasetError(f"{path}: unsupported PCD field type {kind}{size} for {name!r}")
        if not 1 <= count <= 1 << 16:
            raise DatasetError(f"{path}: PCD COUNT of {name!r} must be in [1, 65536], "
                               f"got {count}")
        unique = name if name != "_" else f"_pad{len(fields)}"
        if unique in (field[0] for field in fields):
            raise DatasetError(f"{path}: PCD field {name!r} is listed twice")
        fields.append((unique, _TYPES[(kind, size)], count))
    return PcdHeader(tuple(fields), n_points, encoding, offset)


def _check_width_height(values: dict[str, list[str]], n_points: int, path: Path) -> None:
    if "WIDTH" not in values or "HEIGHT" not in values:
        return
    try:
        width, height = int(values["WIDTH"][0]), int(values["HEIGHT"][0])
    except (ValueError, IndexError) as error:
        raise DatasetError(f"{path}: malformed PCD WIDTH or HEIGHT ({error})") from None
    if width < 0 or height < 0 or width * height != n_points:
        raise DatasetError(f"{path}: PCD WIDTH x HEIGHT ({width} x {height}) is not POINTS "
                           f"({n_points})")


def _ascii_points(raw: bytes, header: PcdHeader, path: Path) -> np.ndarray:
    width = sum(count for _, _, count in header.fields)
    try:
        # No data rows is an empty table (checked against POINTS below), not a numpy warning.
        rows = [line for line in raw[header.data_start:].decode("ascii").splitlines()
                if line.strip() and not line.lstrip().startswith("#")]
        table = np.loadtxt(rows, ndmin=2) if rows else np.zeros((0, width))
    except (UnicodeDecodeError, ValueError) as error:
        raise DatasetError(f"{path}: malformed ASCII PCD data ({error})") from None
    if table.shape != (header.n_points, width) and header.n_points:
        raise DatasetError(f"{path}: {table.shape[0]} ASCII rows of {table.shape[1]} values "
                           f"for {header.n_points} points of {width}")
    columns, column = {}, 0
    for name, _, count in header.fields:
        columns[name] = table[:, column] if header.n_points else np.zeros(0)
        column += count
    return np.stack([columns["x"], columns["y"], columns["z"]], axis=1).astype(np.float32)


def _compressed_points(raw: bytes, header: PcdHeader, path: Path) -> np.ndarray:
    """PCL's binary_compressed: two uint32 sizes, then an LZF stream of the fields one after
    the other (all x, then all y, ...)."""
    start = header.data_start
    if len(raw) - start < _COMPRESSED_SIZES.size:
        raise DatasetError(f"{path}: truncated compressed PCD (no sizes after DATA)")
    compressed, uncompressed = _COMPRESSED_SIZES.unpack_from(raw, start)
    expected = header.n_points * header.record_dtype.itemsize
    if uncompressed != expected:
        raise DatasetError(f"{path}: compressed PCD claims {uncompressed} bytes of data; "
                           f"{header.n_points} points of its fields need {expected}")
    payload = raw[start + _COMPRESSED_SIZES.size:]
    if compressed > len(payload):
        raise DatasetError(f"{path}: truncated compressed PCD ({len(payload)} bytes, "
                           f"{compressed} claimed)")
    if compressed < len(payload):
        raise DatasetError(f"{path}: {len(payload)} bytes of compressed data, the header "
                           f"claims {compressed}")
    if expected == 0:
        return np.zeros((0, 3), dtype=np.float32)
    lzf = require("lzf")
    try:
        data = lzf.decompress(payload[:compressed], expected)
    except ValueError as error:
        raise DatasetError(f"{path}: corrupt compressed PCD data ({error})") from None
    if data is None or len(data) != expected:
        raise DatasetError(f"{path}: corrupt compressed PCD data (does not decompress to the "
                           f"{expected} bytes its header describes)")
    columns, offset = {}, 0
    for name, kind, count in header.fields:
        values = np.frombuffer(data, dtype=kind, count=header.n_points * count, offset=offset)
        columns[name] = values.reshape(header.n_points, count)[:, 0]
        offset += values.nbytes
    return np.stack([columns["x"], columns["y"], columns["z"]], axis=1).astype(np.float32)
