"""Reader for PLY files (ascii, binary little- and big-endian): the vertex x, y, z."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mf_lpr_ros.errors import DatasetError

_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
          "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4",
          "uint32": "u4", "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_ENDIAN = {"binary_little_endian": "<", "binary_big_endian": ">"}
MAX_HEADER_BYTES = 1 << 16
MAX_ELEMENTS = 1 << 31


def read_ply(path: str | Path) -> np.ndarray:
    """The x, y, z of a PLY file's vertices as (N, 3) float32. Elements before the vertices
    must have fixed-size records (no lists), which is how point-cloud PLYs are written."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as error:
        raise DatasetError(f"cannot read PLY {path}: {error}") from error
    if not raw.startswith(b"ply"):
        raise DatasetError(f"{path}: not a PLY file (no 'ply' magic)")
    end = raw.find(b"end_header", 0, MAX_HEADER_BYTES)
    if end < 0:
        raise DatasetError(f"{path}: PLY header has no end_header in its first "
                           f"{MAX_HEADER_BYTES} bytes")
    body = raw.find(b"\n", end) + 1
    if body == 0:
        raise DatasetError(f"{path}: truncated PLY (nothing after end_header)")
    encoding, elements = _parse_header(path, raw[:end])
    before, n_vertices, properties = _vertex_element(path, elements)
    if encoding == "ascii":
        return _ascii_vertices(path, raw[body:], sum(count for _, count, _ in before),
                               n_vertices, properties)
    endian = _ENDIAN[encoding]
    offset = body + sum(count * np.dtype([(n, endian + t) for n, t in props]).itemsize
                        for _, count, props in before)
    dtype = np.dtype([(name, endian + kind) for name, kind in properties])
    if len(raw) - offset < n_vertices * dtype.itemsize:
        raise DatasetError(f"{path}: truncated PLY ({len(raw) - offset} vertex bytes, "
                           f"{n_vertices * dtype.itemsize} expected)")
    if elements[-1][0] == "vertex" and len(raw) - offset > n_vertices * dtype.itemsize:
        # The header does not describe the data: reading it would misplace every property.
        raise DatasetError(f"{path}: {len(raw) - offset} bytes of vertex data, the header "
                           f"describes {n_vertices * dtype.itemsize}")
    records = np.frombuffer(raw, dtype=dtype, count=n_vertices, offset=offset)
    return np.stack([records["x"], records["y"], records["z"]], axis=1).astype(np.float32)


_Element = tuple[str, int, list[tuple[str, str]]]


def _parse_header(path: Path, header: bytes) -> tuple[str, list[_Element]]:
    """The encoding and the elements (name, count, [(property, type)]) of a PLY header."""
    encoding = None
    elements: list[_Element] = []
    for line in header.decode("ascii", errors="replace").splitlines()[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        try:
            if words[0] == "format":
                encoding = words[1]
            elif words[0] == "element":
                count = int(words[2])
                if not 0 <= count < MAX_ELEMENTS:
                    raise ValueError(f"count {count}")
                elements.append((words[1], count, []))
            elif words[0] == "property":
                name = words[-1] if words[1] == "list" else words[2]
                if name in (known for known, _ in elements[-1][2]):
                    raise ValueError(f"property {name!r} listed twice")
                elements[-1][2].append((name, "list" if words[1] == "list"
                                        else _TYPES[words[1]]))
        except (IndexError, KeyError, ValueError) as error:
            raise DatasetError(f"{path}: malformed PLY header line {line!r} "
                               f"({error})") from None
    if encoding not in ("ascii", *_ENDIAN):
        raise DatasetError(f"{path}: PLY format {encoding!r} is not supported")
    return encoding, elements


def _vertex_element(path: Path, elements: list[_Element]
                    ) -> tuple[list[_Element], int, list[tuple[str, str]]]:
    """The elements before the vertices, the vertex count and the vertex properties."""
    names = [element[0] for element in elements]
    if "vertex" not in names:
        raise DatasetError(f"{path}: PLY has no vertex element")
    before = elements[:names.index("vertex")]
    _, n_vertices, properties = elements[names.index("vertex")]
    if any(kind == "list" for _, _, props in before + [elements[names.index("vertex")]]
           for _, kind in props):
        raise DatasetError(f"{path}: list properties before or in the vertex element are not "
                           "supported")
    if not {"x", "y", "z"} <= {name for name, _ in properties}:
        raise DatasetError(f"{path}: PLY vertices have no x, y, z (properties: {properties})")
    return before, n_vertices, properties


def _ascii_vertices(path: Path, body: bytes, skip: int, n_vertices: int,
                    properties: list[tuple[str, str]]) -> np.ndarray:
    lines = body.decode("ascii", errors="replace").splitlines()
    try:
        table = np.loadtxt(lines[skip:skip + n_vertices], ndmin=2)
    except ValueError as error:
        raise DatasetError(f"{path}: malformed ASCII PLY vertices ({error})") from error
    if len(table) != n_vertices or (n_vertices and table.shape[1] != len(properties)):
        raise DatasetError(f"{path}: {len(table)} ASCII vertices of {table.shape[1]} values "
                           f"for {n_vertices} of {len(properties)} declared")
    columns = [name for name, _ in properties]
    return table[:, [columns.index(c) for c in ("x", "y", "z")]].astype(np.float32)
