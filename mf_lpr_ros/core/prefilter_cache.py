"""The prefilter's reference features cached beside a map file, so a large map starts in seconds.

Computing the polar-spectrum features takes ~0.1 ms a reference (25 s at 250,000); reading
them back is a memory map. The cache is `<map>.prefilter`:

    magic  b"MFLPRPFX"                       8 bytes
    header length H                          uint32
    CRC32 of the header                      uint32
    header: UTF-8 JSON, H bytes              the map's content key, features version, array
    padding to a 64-byte boundary, then the (harmonics, n, radii) complex64 features

It belongs to one map: the map's content key (its header checksum and reference count) and
the features' version must match, and the array's checksum must hold, or the cache is stale and
is rebuilt. It is written atomically, like the map.
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from pathlib import Path

import numpy as np

from mf_lpr_ros.core.map_store import aligned, array_crc32, write_atomically

CACHE_SUFFIX = ".prefilter"
# Raised whenever PolarSpectrumIndex.features changes what it computes.
FEATURES_VERSION = 2
_MAGIC = b"MFLPRPFX"
_PREAMBLE = struct.Struct("<8sII")
_MAX_HEADER_BYTES = 1 << 16


def cache_path(map_path: Path) -> Path:
    """Where the prefilter cache of the map at map_path lives."""
    return map_path.with_name(map_path.name + CACHE_SUFFIX)


def load_features(path: Path, content_key: str, shape: tuple[int, int, int]
                  ) -> tuple[np.ndarray | None, str]:
    """The cached features (memory-mapped, checked) of the map with content_key, expected
    (harmonics, n, radii), and why not when they cannot be used: (None, reason)."""
    try:
        handle = open(path, "rb")
    except FileNotFoundError:
        return None, f"no cache at {path}"
    except OSError as error:
        return None, f"cannot read {path}: {error}"
    # The header and the features from one open file: another process may write the cache
    # again meanwhile (ReferenceMap.load reads a map so too).
    with handle:
        try:
            preamble = handle.read(_PREAMBLE.size)
            if len(preamble) < _PREAMBLE.size:
                return None, f"{path} is truncated"
            magic, header_length, header_crc = _PREAMBLE.unpack(preamble)
            if magic != _MAGIC or header_length > _MAX_HEADER_BYTES:
                return None, f"{path} is not a prefilter cache"
            header_bytes = handle.read(header_length)
            size = os.fstat(handle.fileno()).st_size
        except OSError as error:
            return None, f"cannot read {path}: {error}"
        if zlib.crc32(header_bytes) != header_crc:
            return None, f"{path} has a corrupt header"
        try:
            header = json.loads(header_bytes)
            offset = int(header["offset"])
        except (ValueError, KeyError, TypeError):
            return None, f"{path} has an unreadable header"
        if header.get("features_version") != FEATURES_VERSION:
            return None, f"{path} holds features of another version"
        if header.get("content_key") != content_key:
            return None, f"prefilter cache {path} belongs to another version of the map"
        if tuple(header.get("shape", ())) != shape or header.get("dtype") != "<c8":
            return None, f"{path} holds features of another shape ({header.get('shape')})"
        if size < offset + int(np.prod(shape)) * 8:
            return None, f"{path} is truncated"
        features = np.memmap(handle, dtype="<c8", mode="r", offset=offset, shape=shape)
    if array_crc32(features) != header.get("crc32"):
        return None, f"{path} is corrupt (checksum mismatch)"
    return features, f"loaded from {path}"


def save_features(path: Path, content_key: str, features: np.ndarray) -> str:
    """Write the cache atomically; returns what happened (a read-only directory is not an
    error: the next start computes the features again)."""
    features = np.ascontiguousarray(features, dtype="<c8")
    header = {"features_version": FEATURES_VERSION, "content_key": content_key,
              "shape": list(features.shape), "dtype": "<c8", "crc32": array_crc32(features),
              "offset": 0}
    header_bytes = b""
    for _ in range(4):
        header["offset"] = aligned(_PREAMBLE.size + len(header_bytes))
        encoded = json.dumps(header, sort_keys=True).encode()
        if encoded == header_bytes:
            break
        header_bytes = encoded
    head = _PREAMBLE.pack(_MAGIC, len(header_bytes), zlib.crc32(header_bytes)) + header_bytes
    try:
        write_atomically(path, head, {"features": features},
                         {"features": {"offset": header["offset"]}})
    except OSError as error:
        return f"not cached ({path}: {error})"
    return f"cached at {path}"
