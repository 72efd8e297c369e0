"""Reader for PCD files (ascii and binary), x, y, z (+ any other fields, ignored)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mf_lpr_ros.errors import DatasetError

_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4",
          ("I", 8): "i8", ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}


def read_pcd(path: str | Path) -> np.ndarray:
    """The x, y, z of a PCD file as (N, 3) float32."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as error:
        raise DatasetError(f"cannot read PCD {path}: {error}") from error
    header: dict[str, list[str]] = {}
    offset = 0
    while True:
        end = raw.find(b"\n", offset)
        if end < 0:
            raise DatasetError(f"{path}: PCD header has no DATA line")
        line = raw[offset:end].decode("ascii", errors="replace").strip()
        offset = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        header[key.upper()] = values
        if key.upper() == "DATA":
            break
    try:
        names = header["FIELDS"]
        sizes = [int(s) for s in header["SIZE"]]
        types = header["TYPE"]
        counts = [int(c) for c in header.get("COUNT", ["1"] * len(names))]
        n_points = int(header["POINTS"][0])
        encoding = header["DATA"][0].lower()
    except (KeyError, ValueError, IndexError) as error:
        raise DatasetError(f"{path}: malformed PCD header ({error})") from error
    if not {"x", "y", "z"} <= set(names):
        raise DatasetError(f"{path}: PCD has no x, y, z fields (fields: {names})")
    dtype_fields = []
    for name, size, kind, count in zip(names, sizes, types, counts):
        if (kind, size) not in _TYPES:
            raise DatasetError(f"{path}: unsupported PCD field type {kind}{size} for {name!r}")
        dtype_fields.append((name if name != "_" else f"_pad{len(dtype_fields)}",
                             _TYPES[(kind, size)], (count,) if count > 1 else ()))
    dtype = np.dtype(dtype_fields)
    if encoding == "binary":
        needed = n_points * dtype.itemsize
        if len(raw) - offset < needed:
            raise DatasetError(f"{path}: truncated PCD ({len(raw) - offset} data bytes, "
                               f"{needed} expected)")
        records = np.frombuffer(raw, dtype=dtype, count=n_points, offset=offset)
    elif encoding == "ascii":
        table = np.loadtxt(raw[offset:].decode().splitlines(), ndmin=2)
        if len(table) != n_points:
            raise DatasetError(f"{path}: {len(table)} ASCII rows for {n_points} points")
        columns = {}
        column = 0
        for name, _, _, count in zip(names, sizes, types, counts):
            columns[name] = table[:, column]
            column += count
        return np.stack([columns["x"], columns["y"], columns["z"]], axis=1).astype(np.float32)
    else:
        raise DatasetError(f"{path}: PCD encoding {encoding!r} is not supported "
                           "(use ascii or binary)")
    return np.stack([records["x"], records["y"], records["z"]], axis=1).astype(np.float32)
