"""The reference map: descriptors, poses and provenance, stored as one versioned file.

Layout (little-endian):

    magic  b"MFLPRMAP"                       8 bytes
    format version                           uint32
    header length H                          uint32
    CRC32 of the header                      uint32
    header: UTF-8 JSON, H bytes              parameters, frames, array table
    padding to a 64-byte boundary, then each array at its recorded offset

Version 2 adds the site cloud (three arrays and the header's "site_cloud": tile_m, half_m);
a map without one is written as version 1.

Every array carries its CRC32 in the header. Occupancy is stored as packed bits. Loading
memory-maps the arrays, so a large map costs page cache, not twice its size in RAM; all checks
(magic, version, header and array checksums, sizes) happen at load, never mid-search.
Saving writes a temporary file in the same directory, fsyncs it and renames it over the old
map, so a crash leaves either the old or the new map, never a torn one.
"""

from __future__ import annotations

import copy
import json
import os
import struct
import threading
import zlib
from dataclasses import asdict
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from mf_lpr_ros.core.map_header import (
    ALIGN,
    MAX_HEADER_BYTES,
    ArrayEntry,
    check_cloud_offsets,
    parse_header,
)
from mf_lpr_ros.core.pose import planar
from mf_lpr_ros.core.site_cloud import SiteCloud
from mf_lpr_ros.errors import MapFileError, MapParameterMismatch
from mf_lpr_ros.params import DescriptorParams
from mf_lpr_ros.version import __version__

MAGIC = b"MFLPRMAP"
# Version 2 added the site cloud. A map without one is written as version 1, the same bytes as
# before, so earlier builds still read it; one with a site cloud is refused by them by version.
FORMAT_VERSION = 2
# metadata["kind"] of a map rendered from a global point cloud (pipeline.global_map): its
# references are complete virtual views, not scans.
GLOBAL_MAP_KIND = "global_map_grid"
_PREAMBLE = struct.Struct("<8sIII")
_ALIGN = ALIGN
_CRC_BLOCK = 1 << 24


class ReferenceMap:
    """Reference descriptors with their poses, stamps and provenance.

    occupancy_bits: (n, D*D/8) uint8, packed high-resolution occupancy (patch cap applied).
    poses: (n, 4, 4) world_T_sensor. stamps: (n,) seconds. source_indices: (n,) index of each
    reference's scan in the sequence it came from. Optional reference clouds (for ICP) are
    kept either per reference, as one (P, 3) float32 array with (n+1,) offsets, or once for
    the whole site (core.site_cloud; a grid rendered from a global cloud), from which each
    reference's cloud is cut when it is asked for.
    """

    def __init__(self, params: DescriptorParams, *, frame_id: str = "map",
                 sensor_frame_id: str = "", metadata: dict[str, Any] | None = None) -> None:
        self.params = params
        self.frame_id = frame_id
        self.sensor_frame_id = sensor_frame_id
        self.metadata = dict(metadata or {})
        n_bytes = params.size * params.size // 8
        self._occupancy_bits = np.zeros((0, n_bytes), dtype=np.uint8)
        self._poses = np.zeros((0, 4, 4))
        self._stamps = np.zeros(0)
        self._source_indices = np.zeros(0, dtype=np.int64)
        self.cloud_points: np.ndarray | None = None
        self.cloud_offsets: np.ndarray | None = None
        self.site_cloud: SiteCloud | None = None
        self._pending: list[tuple[np.ndarray, np.ndarray, float, int, np.ndarray | None]] = []
        # A node appends from its scan callback while a timer saves: appends, the flush of
        # pending references and save's snapshot of the arrays happen one at a time.
        self._lock = threading.RLock()
        # Set by load: the file, its header checksum (which changes with any content, so files
        # derived from the map, the prefilter cache, know which map they belong to) and how
        # many references the file holds (later appends are not in it).
        self.source_path: Path | None = None
        self.content_key: str | None = None
        self.source_references = 0

    @classmethod
    def from_arrays(cls, params: DescriptorParams, occupancy_bits: np.ndarray, poses: np.ndarray,
                    stamps: np.ndarray, source_indices: np.ndarray, *, frame_id: str = "map",
                    metadata: dict[str, Any] | None = None) -> "ReferenceMap":
        """A map of many references at once (packed occupancy as occupancy_bits holds it):
        appending a million one by one costs minutes."""
        reference_map = cls(params, frame_id=frame_id, metadata=metadata)
        n_bytes = params.size * params.size // 8
        count = len(stamps)
        if occupancy_bits.shape != (count, n_bytes) or occupancy_bits.dtype != np.uint8:
            raise ValueError(f"occupancy_bits must be ({count}, {n_bytes}) uint8, got "
                             f"{occupancy_bits.shape} {occupancy_bits.dtype}")
        if poses.shape != (count, 4, 4) or not np.isfinite(poses).all():
            raise ValueError(f"poses must be ({count}, 4, 4) and finite")
        if len(source_indices) != count:
            raise ValueError(f"source_indices must hold {count} entries")
        reference_map._occupancy_bits = occupancy_bits
        reference_map._poses = np.asarray(poses, dtype=np.float64)
        reference_map._stamps = np.asarray(stamps, dtype=np.float64)
        reference_map._source_indices = np.asarray(source_indices, dtype=np.int64)
        return reference_map

    def __len__(self) -> int:
        self._flush_pending()
        return len(self._stamps)

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        del state["_lock"]
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._lock = threading.RLock()

    @property
    def occupancy_bits(self) -> np.ndarray:
        """(n, D*D/8) packed occupancy of every reference, those just appended included."""
        self._flush_pending()
        return self._occupancy_bits

    @property
    def poses(self) -> np.ndarray:
        """(n, 4, 4) world_T_sensor of every reference, those just appended included."""
        self._flush_pending()
        return self._poses

    @property
    def stamps(self) -> np.ndarray:
        self._flush_pending()
        return self._stamps

    @property
    def source_indices(self) -> np.ndarray:
        self._flush_pending()
        return self._source_indices

    @property
    def planar_poses(self) -> np.ndarray:
        """(n, 3) x, y, yaw of every reference."""
        self._flush_pending()
        return planar(self.poses)

    @property
    def has_clouds(self) -> bool:
        """Every reference has a cloud (its own or cut from the site cloud)."""
        self._flush_pending()
        return self.cloud_offsets is not None or self.site_cloud is not None

    @property
    def has_reference_clouds(self) -> bool:
        """Clouds are kept per reference, so every reference appended needs its own."""
        self._flush_pending()
        return self.cloud_offsets is not None

    def set_site_cloud(self, site_cloud: SiteCloud) -> None:
        """Give every reference, present and future, its cloud from site_cloud."""
        with self._lock:
            if self.cloud_offsets is not None or any(entry[4] is not None
                                                     for entry in self._pending):
                raise ValueError("this map keeps a cloud per reference; a site cloud would "
                                 "be a second source of the same clouds")
            self.site_cloud = site_cloud

    def append(self, occupancy: np.ndarray, pose: np.ndarray, stamp: float,
               source_index: int = -1, cloud: np.ndarray | None = None) -> int:
        """Add one reference; returns its index. Cheap: arrays are grown in batches."""
        size = self.params.size
        if occupancy.shape != (size, size):
            raise ValueError(f"occupancy must be ({size}, {size}), got {occupancy.shape}")
        pose = np.asarray(pose, dtype=np.float64)
        if pose.shape != (4, 4) or not np.isfinite(pose).all():
            raise ValueError("reference pose must be a finite 4x4 matrix")
        packed = np.packbits(occupancy.astype(bool).ravel())
        kept = None if cloud is None else np.asarray(cloud, dtype=np.float32)[:, :3]
        with self._lock:
            if cloud is not None and self.site_cloud is not None:
                raise ValueError("this map's clouds are cut from its site cloud; add "
                                 "references without one")
            if cloud is not None and self._pending_or_stored_without_clouds():
                raise ValueError("this map keeps no reference clouds; add every reference "
                                 "without one")
            if cloud is None and self.cloud_offsets is not None:
                raise ValueError("this map keeps reference clouds; every reference needs one")
            self._pending.append((packed, pose, float(stamp), int(source_index), kept))
            return len(self._stamps) + len(self._pending) - 1

    def _pending_or_stored_without_clouds(self) -> bool:
        if len(self._stamps) and self.cloud_offsets is None:
            return True
        return any(entry[4] is None for entry in self._pending)

    def _flush_pending(self) -> None:
        with self._lock:
            if self._pending:
                self._flush_locked()

    def _flush_locked(self) -> None:
        packed, poses, stamps, sources, clouds = zip(*self._pending)
        self._pending = []
        self._occupancy_bits = np.concatenate([self._occupancy_bits, np.stack(packed)])
        self._poses = np.concatenate([self._poses, np.stack(poses)])
        self._stamps = np.concatenate([self._stamps, np.array(stamps)])
        self._source_indices = np.concatenate([self._source_indices,
                                               np.array(sources, np.int64)])
        if clouds[0] is not None:
            old_points = self.cloud_points if self.cloud_points is not None else np.zeros((0, 3),
                                                                                         np.float32)
            old_offsets = self.cloud_offsets if self.cloud_offsets is not None else np.zeros(1,
                                                                                            np.int64)
            lengths = np.array([len(c) for c in clouds], dtype=np.int64)
            self.cloud_points = np.concatenate([old_points, *clouds])
            self.cloud_offsets = np.concatenate([old_offsets,
                                                 old_offsets[-1] + np.cumsum(lengths)])

    def occupancy(self, index: int | slice | np.ndarray) -> np.ndarray:
        """Unpacked occupancy of reference(s): (D, D) or (k, D, D) bool."""
        self._flush_pending()
        size = self.params.size
        bits = self.occupancy_bits[index]
        unpacked = np.unpackbits(bits, axis=-1, count=size * size).astype(bool)
        return unpacked.reshape(bits.shape[:-1] + (size, size))

    def cloud(self, index: int) -> np.ndarray:
        """(P, 3) float32 cloud of reference index, in its frame."""
        self._flush_pending()
        if self.site_cloud is not None:
            return self.site_cloud.around(self._poses[index])
        if self.cloud_offsets is None or self.cloud_points is None:
            raise MapFileError("this map keeps no reference clouds (build it with clouds kept)")
        start, stop = self.cloud_offsets[index], self.cloud_offsets[index + 1]
        return np.asarray(self.cloud_points[start:stop])

    def check_params(self, params: DescriptorParams) -> None:
        """Refuse descriptor parameters that differ from the ones the map was built with."""
        ours, theirs = asdict(self.params), asdict(params)
        differing = {k: (ours[k], theirs[k]) for k in ours if ours[k] != theirs[k]}
        if differing:
            detail = ", ".join(f"{k}: map has {a!r}, requested {b!r}"
                               for k, (a, b) in differing.items())
            raise MapParameterMismatch(
                f"descriptor parameters differ from the map's ({detail}); rebuild the map or use "
                "the map's parameters")

    def save(self, path: str | Path) -> None:
        """Write the map atomically (temporary file, fsync, rename): the references it held
        when called, even while another thread appends."""
        path = Path(path)
        with self._lock:
            self._flush_pending()
            # The arrays are replaced, never changed in place, on appending: these stay whole.
            arrays = {
                "occupancy_bits": np.ascontiguousarray(self._occupancy_bits),
                "poses": np.ascontiguousarray(self._poses, dtype="<f8"),
                "stamps": np.ascontiguousarray(self._stamps, dtype="<f8"),
                "source_indices": np.ascontiguousarray(self._source_indices, dtype="<i8"),
            }
            if self.cloud_offsets is not None and self.cloud_points is not None:
                arrays["cloud_points"] = np.ascontiguousarray(self.cloud_points, dtype="<f4")
                arrays["cloud_offsets"] = np.ascontiguousarray(self.cloud_offsets, dtype="<i8")
            if self.site_cloud is not None:
                arrays["site_points"] = np.ascontiguousarray(self.site_cloud.points, dtype="<f4")
                arrays["site_tile_keys"] = np.ascontiguousarray(self.site_cloud.tile_keys,
                                                                dtype="<i8")
                arrays["site_tile_offsets"] = np.ascontiguousarray(self.site_cloud.tile_offsets,
                                                                   dtype="<i8")
            metadata = copy.deepcopy(self.metadata)
            site = (None if self.site_cloud is None else
                    {"tile_m": self.site_cloud.tile_m, "half_m": self.site_cloud.half_m})
        table: dict[str, dict[str, Any]] = {}
        version = 1 if site is None else FORMAT_VERSION
        header: dict[str, Any] = {
            "format_version": version,
            "writer": f"mf_lpr_ros {__version__}",
            "n_references": int(len(arrays["stamps"])),
            "descriptor": asdict(self.params),
            "frame_id": self.frame_id,
            "sensor_frame_id": self.sensor_frame_id,
            "metadata": metadata,
            "arrays": table,
        }
        if site is not None:
            header["site_cloud"] = site
        # Offsets depend on the header size, which depends on the offsets: iterate to a fixpoint.
        header_bytes = b""
        for _ in range(4):
            offset = aligned(_PREAMBLE.size + len(header_bytes))
            for name, array in arrays.items():
                table[name] = {"offset": offset, "dtype": array.dtype.str,
                               "shape": list(array.shape),
                               "crc32": array_crc32(array)}
                offset = aligned(offset + array.nbytes)
            encoded = json.dumps(header, sort_keys=True).encode()
            if encoded == header_bytes:
                break
            header_bytes = encoded
        preamble = _PREAMBLE.pack(MAGIC, version, len(header_bytes),
                                  zlib.crc32(header_bytes))
        write_atomically(path, preamble + header_bytes, arrays, table)

    @classmethod
    def load(cls, path: str | Path, *, verify: bool = True) -> "ReferenceMap":
        """Load and validate a map; raises MapFileError naming the problem."""
        path = Path(path)
        try:
            handle = open(path, "rb")
        except OSError as error:
            raise MapFileError(f"cannot read map file {path}: {error}") from error
        # The header and every array from one open file: a save renames a new map over the
        # path, and a map saved between two opens would mix two files' parts.
        with handle:
            header_bytes, header_crc, size = _read_header(handle, path)
            if zlib.crc32(header_bytes) != header_crc:
                raise MapFileError(f"{path}: corrupt map header (checksum mismatch)")
            try:
                header = parse_header(header_bytes, _PREAMBLE.size + len(header_bytes), size)
                loaded = _map_arrays(handle, header.arrays, verify)
                if "cloud_offsets" in loaded:
                    check_cloud_offsets(loaded["cloud_offsets"], len(loaded["cloud_points"]))
                site_cloud = None
                if header.site_cloud is not None:
                    site_cloud = SiteCloud(loaded["site_points"], loaded["site_tile_keys"],
                                           loaded["site_tile_offsets"], *header.site_cloud)
                    problem = site_cloud.check()
                    if problem is not None:
                        raise MapFileError(f"invalid map: {problem}")
            except MapFileError as error:
                raise MapFileError(f"{path}: {error}") from None
        reference_map = cls(header.params, frame_id=header.frame_id,
                            sensor_frame_id=header.sensor_frame_id, metadata=header.metadata)
        reference_map.source_path = path
        reference_map.content_key = f"{header_crc:08x}"
        reference_map.source_references = len(loaded["stamps"])
        reference_map._occupancy_bits = loaded["occupancy_bits"]
        reference_map._poses = loaded["poses"]
        reference_map._stamps = loaded["stamps"]
        reference_map._source_indices = loaded["source_indices"]
        if "cloud_offsets" in loaded:
            reference_map.cloud_points = loaded["cloud_points"]
            reference_map.cloud_offsets = loaded["cloud_offsets"]
        reference_map.site_cloud = site_cloud
        return reference_map


def _read_header(handle: BinaryIO, path: Path) -> tuple[bytes, int, int]:
    """The header bytes, their stored CRC and the file size of the open map file at path,
    after the preamble's checks."""
    try:
        size = os.fstat(handle.fileno()).st_size
        preamble = handle.read(_PREAMBLE.size)
        if len(preamble) < _PREAMBLE.size:
            raise MapFileError(f"{path}: truncated map file ({size} bytes, no header)")
        magic, version, header_len, header_crc = _PREAMBLE.unpack(preamble)
        if magic != MAGIC:
            raise MapFileError(f"{path}: not an mf_lpr_ros map (bad magic {magic!r})")
        if version > FORMAT_VERSION:
            raise MapFileError(
                f"{path}: map format version {version} was written by a newer mf_lpr_ros; "
                f"this build reads versions 1 to {FORMAT_VERSION}")
        if version < 1:
            raise MapFileError(f"{path}: unsupported map format version {version}")
        if header_len > MAX_HEADER_BYTES:
            raise MapFileError(f"{path}: invalid map header length {header_len} (a header "
                               f"holds at most {MAX_HEADER_BYTES} bytes)")
        header_bytes = handle.read(header_len)
    except OSError as error:
        raise MapFileError(f"cannot read map file {path}: {error}") from error
    if len(header_bytes) < header_len:
        raise MapFileError(f"{path}: truncated map file (header cut at {size} bytes)")
    return header_bytes, header_crc, size


def _map_arrays(handle: BinaryIO, table: dict[str, ArrayEntry], verify: bool
                ) -> dict[str, np.ndarray]:
    """Every array of the checked header's table, memory-mapped from the open map file (the
    mappings outlive the handle) and (verify) checksummed."""
    loaded: dict[str, np.ndarray] = {}
    for name, entry in table.items():
        if entry.nbytes == 0:
            array = np.zeros(entry.shape, dtype=entry.dtype)
        else:
            array = np.memmap(handle, dtype=entry.dtype, mode="r", offset=entry.offset,
                              shape=entry.shape)
        if verify and array_crc32(array) != entry.crc32:
            raise MapFileError(f"corrupt map file (checksum mismatch in {name!r})")
        loaded[name] = array
    return loaded


def aligned(offset: int) -> int:
    """offset rounded up to the 64-byte boundary every stored array starts on."""
    return (offset + _ALIGN - 1) // _ALIGN * _ALIGN


def _as_bytes(array: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(array).reshape(-1).view(np.uint8)


def array_crc32(array: np.ndarray) -> int:
    """CRC32 of an array's bytes, in blocks (a memory-mapped array is read once)."""
    view = _as_bytes(array)
    crc = 0
    for start in range(0, len(view), _CRC_BLOCK):
        crc = zlib.crc32(view[start: start + _CRC_BLOCK], crc)
    return crc


def write_atomically(path: Path, head: bytes, arrays: dict[str, np.ndarray],
                     table: dict[str, dict[str, Any]]) -> None:
    """Write head, then each array at table[name]["offset"], to a temporary file beside path;
    fsync it and rename it over path: a crash leaves the old file or the new, never a torn
    one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_temporaries(path)
    temporary = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with open(temporary, "wb") as handle:
            handle.write(head)
            for name, array in arrays.items():
                handle.write(b"\0" * (table[name]["offset"] - handle.tell()))
                handle.write(_as_bytes(array))
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
    directory = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(directory)
    finally:
        os.close(directory)


def _remove_stale_temporaries(path: Path) -> None:
    """Temporary files left by writers that were killed mid-save (their process is gone)."""
    for stale in path.parent.glob(f".{path.name}.tmp-*"):
        try:
            pid = int(stale.name.rsplit("-", 1)[1])
            os.kill(pid, 0)
        except ValueError:
            continue
        except ProcessLookupError:
            stale.unlink(missing_ok=True)
        except PermissionError:
            continue
