"""The map file's header, checked field by field before any array is touched.

A header whose checksum is valid can still have been written by something else than
ReferenceMap.save: by hand, by another tool, or on purpose. parse_header refuses anything that
save would not have written, each failure a MapFileError naming the field: the JSON's size and
nesting, every field's type, a dtype per array (so no array's bytes are read as another type),
non-negative shapes consistent with n_references and the descriptor, offsets aligned, inside
the file, past the header and not overlapping.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

import numpy as np

from mf_lpr_ros.config import descriptor_params_from_dict
from mf_lpr_ros.errors import ConfigError, MapFileError
from mf_lpr_ros.params import DescriptorParams

MAX_HEADER_BYTES = 16 << 20
MAX_NESTING = 32
ALIGN = 64
MAX_REFERENCES = 1 << 32
# The dtype save writes for each array, and its shape with n = n_references and D = size.
ARRAY_DTYPES = {"occupancy_bits": "|u1", "poses": "<f8", "stamps": "<f8",
                "source_indices": "<i8", "cloud_points": "<f4", "cloud_offsets": "<i8",
                "site_points": "<f4", "site_tile_keys": "<i8", "site_tile_offsets": "<i8"}
SITE_ARRAYS = ("site_points", "site_tile_keys", "site_tile_offsets")
REQUIRED_ARRAYS = ("occupancy_bits", "poses", "stamps", "source_indices")
_ENTRY_KEYS = {"offset", "dtype", "shape", "crc32"}


@dataclass(frozen=True)
class ArrayEntry:
    """Where one array lies in the file, its type and shape, and its CRC32."""

    offset: int
    dtype: np.dtype
    shape: tuple[int, ...]
    crc32: int

    @property
    def nbytes(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64)) * self.dtype.itemsize


@dataclass(frozen=True)
class MapHeader:
    params: DescriptorParams
    n_references: int
    frame_id: str
    sensor_frame_id: str
    metadata: dict
    arrays: dict[str, ArrayEntry]
    # (tile_m, half_m) of the site cloud (core.site_cloud), None without one.
    site_cloud: tuple[float, float] | None = None


def parse_header(header_bytes: bytes, data_start: int, file_size: int) -> MapHeader:
    """The checked header (see the module doc); data_start is where the header ends."""
    header = _decoded(header_bytes)
    _require(isinstance(header, dict), "the header", "a JSON object", header)
    n_refs = header.get("n_references")
    _require(_is_int(n_refs) and 0 <= n_refs < MAX_REFERENCES, "n_references",
             "a non-negative integer", n_refs)
    for name in ("frame_id", "sensor_frame_id", "writer"):
        _require(isinstance(header.get(name, ""), str), name, "a string", header.get(name))
    version = header.get("format_version", 1)
    _require(_is_int(version), "format_version", "an integer", version)
    metadata = header.get("metadata", {})
    _require(isinstance(metadata, dict), "metadata", "a JSON object", metadata)
    descriptor = header.get("descriptor")
    _require(isinstance(descriptor, dict), "descriptor", "a JSON object", descriptor)
    try:
        # Maps written before the disc crop existed were cropped square.
        params = descriptor_params_from_dict({"crop": "square", **descriptor})
    except ConfigError as error:
        raise MapFileError(f"invalid map header: descriptor: {error}") from None
    site_cloud = _site_cloud(header.get("site_cloud"), version)
    arrays = _array_table(header.get("arrays"), n_refs, params)
    _require(("site_points" in arrays) == (site_cloud is not None), "arrays",
             f"to hold {list(SITE_ARRAYS)} exactly when the header has site_cloud",
             sorted(arrays))
    _check_extents(arrays, data_start, file_size)
    return MapHeader(params, n_refs, header.get("frame_id", "map"),
                     header.get("sensor_frame_id", ""), metadata, arrays, site_cloud)


def _site_cloud(site: Any, version: int) -> tuple[float, float] | None:
    if site is None:
        return None
    _require(version >= 2, "site_cloud", "absent from a version 1 map", site)
    _require(isinstance(site, dict) and set(site) == {"tile_m", "half_m"}, "site_cloud",
             "an object with exactly ['half_m', 'tile_m']", site)
    for name in ("tile_m", "half_m"):
        value = site[name]
        _require(isinstance(value, (int, float)) and not isinstance(value, bool)
                 and 0 < value < 1e6, f"site_cloud.{name}", "a positive number of metres",
                 value)
    return float(site["tile_m"]), float(site["half_m"])


def check_cloud_offsets(offsets: np.ndarray, n_points: int) -> None:
    """Reference clouds' offsets: from 0, never decreasing, ending at the number of points."""
    if len(offsets) and (offsets[0] != 0 or offsets[-1] != n_points
                         or bool((np.diff(offsets) < 0).any())):
        raise MapFileError("invalid map: cloud_offsets must run from 0 to the number of cloud "
                           "points without decreasing")


def _decoded(header_bytes: bytes) -> Any:
    if len(header_bytes) > MAX_HEADER_BYTES:
        raise MapFileError(f"invalid map header: {len(header_bytes)} bytes, more than the "
                           f"{MAX_HEADER_BYTES} a map header may hold")
    try:
        header = json.loads(header_bytes.decode("utf-8"))
    except RecursionError:
        raise MapFileError(f"invalid map header: nested deeper than {MAX_NESTING} "
                           "levels") from None
    except (UnicodeDecodeError, ValueError) as error:
        raise MapFileError(f"invalid map header: not UTF-8 JSON ({error})") from None
    _check_nesting(header)
    return header


def _check_nesting(value: Any) -> None:
    level = [value]
    for _ in range(MAX_NESTING + 1):
        level = [child for item in level if isinstance(item, (dict, list))
                 for child in (item.values() if isinstance(item, dict) else item)]
        if not level:
            return
    raise MapFileError(f"invalid map header: nested deeper than {MAX_NESTING} levels")


def _array_table(table: Any, n_refs: int, params: DescriptorParams) -> dict[str, ArrayEntry]:
    _require(isinstance(table, dict), "arrays", "a JSON object (array name -> entry)", table)
    unknown = sorted(set(table) - set(ARRAY_DTYPES))
    _require(not unknown, "arrays", f"names among {sorted(ARRAY_DTYPES)}", unknown)
    missing = [name for name in REQUIRED_ARRAYS if name not in table]
    _require(not missing, "arrays", f"to hold {list(REQUIRED_ARRAYS)}", f"missing {missing}")
    _require(("cloud_points" in table) == ("cloud_offsets" in table), "arrays",
             "to hold cloud_points and cloud_offsets together or neither", sorted(table))
    _require(len({name in table for name in SITE_ARRAYS}) == 1, "arrays",
             f"to hold {list(SITE_ARRAYS)} together or none of them", sorted(table))
    entries = {name: _entry(name, entry) for name, entry in table.items()}
    expected = {"occupancy_bits": (n_refs, params.size * params.size // 8),
                "poses": (n_refs, 4, 4), "stamps": (n_refs,), "source_indices": (n_refs,),
                "cloud_offsets": (n_refs + 1,)}
    for name in ("cloud_points", "site_points"):
        if name in entries:
            expected[name] = (*entries[name].shape[:1], 3)
    if "site_tile_keys" in entries:
        keys_shape = entries["site_tile_keys"].shape
        _require(len(keys_shape) == 1, "arrays.site_tile_keys.shape", "[tiles]",
                 list(keys_shape))
        expected["site_tile_keys"] = keys_shape
        expected["site_tile_offsets"] = (keys_shape[0] + 1,)
    for name, entry in entries.items():
        _require(entry.shape == expected[name], f"arrays.{name}.shape",
                 f"{list(expected[name])} for {n_refs} references", list(entry.shape))
    return entries


def _entry(name: str, entry: Any) -> ArrayEntry:
    _require(isinstance(entry, dict) and set(entry) == _ENTRY_KEYS, f"arrays.{name}",
             f"an object with exactly {sorted(_ENTRY_KEYS)}", entry)
    offset, dtype, shape, crc = (entry[key] for key in ("offset", "dtype", "shape", "crc32"))
    _require(_is_int(offset) and offset >= 0 and offset % ALIGN == 0, f"arrays.{name}.offset",
             f"a non-negative multiple of {ALIGN}", offset)
    _require(dtype == ARRAY_DTYPES[name], f"arrays.{name}.dtype", repr(ARRAY_DTYPES[name]),
             dtype)
    _require(isinstance(shape, list) and len(shape) <= 3
             and all(_is_int(n) and 0 <= n < 1 << 40 for n in shape),
             f"arrays.{name}.shape", "a list of at most 3 non-negative integers", shape)
    _require(_is_int(crc) and 0 <= crc < 1 << 32, f"arrays.{name}.crc32",
             "an unsigned 32-bit integer", crc)
    return ArrayEntry(offset, np.dtype(dtype), tuple(shape), crc)


def _check_extents(arrays: dict[str, ArrayEntry], data_start: int, file_size: int) -> None:
    end = data_start
    # An empty array occupies no bytes, so it may share its offset with the next array.
    for name, entry in sorted(arrays.items(), key=lambda item: (item[1].offset,
                                                                 item[1].nbytes > 0)):
        _require(entry.offset >= end, f"arrays.{name}.offset",
                 f">= {end} (past the header and the arrays before it)", entry.offset)
        end = entry.offset + entry.nbytes
        if end > file_size:
            raise MapFileError(f"truncated map file (array {name!r} needs bytes up to {end}, "
                               f"file has {file_size})")


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _require(ok: bool, field: str, expectation: str, value: Any) -> None:
    if not ok:
        shown = repr(value)
        shown = shown if len(shown) <= 80 else shown[:77] + "..."
        raise MapFileError(f"invalid map header: {field} must be {expectation}, got {shown}")
