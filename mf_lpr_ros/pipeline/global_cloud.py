"""Global point clouds: read (PCD, PLY), written (binary PCD), accumulated from a posed sequence,
and held in tiles for rendering views."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from mf_lpr_ros.core.descriptor import finite_rows, one_point_per_voxel, rows_where
from mf_lpr_ros.core.pose import moved_points
from mf_lpr_ros.datasets.base import Sequence, read_kitti_poses, read_tum_poses
from mf_lpr_ros.errors import DatasetError, InvalidCloudError
from mf_lpr_ros.io.pcd import read_pcd
from mf_lpr_ros.io.ply import read_ply
from mf_lpr_ros.progress import progress_bar


def read_global_cloud(path: str | Path) -> np.ndarray:
    """The finite points (N, 3) float32 of a PCD or PLY global map; a clear error when the file
    is unreadable, of another format, or holds no finite point."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".pcd":
        points = read_pcd(path)
    elif suffix == ".ply":
        points = read_ply(path)
    else:
        raise DatasetError(f"{path}: a global map must be a .pcd or .ply file")
    points = rows_where(points, finite_rows(points))
    if not len(points):
        raise InvalidCloudError(f"{path}: the global map holds no finite point")
    return points


def read_trajectory(path: str | Path) -> np.ndarray:
    """(n, 4, 4) poses from a KITTI poses file (12 numbers a line) or a TUM file (8 columns)."""
    try:
        columns = np.loadtxt(path, ndmin=2, comments="#", max_rows=1).shape[1]
    except (OSError, ValueError) as error:
        raise DatasetError(f"cannot read trajectory {path}: {error}") from error
    if columns == 12:
        return read_kitti_poses(path)
    if columns == 8:
        return read_tum_poses(path)[1]
    raise DatasetError(f"{path}: a trajectory needs 12 numbers a line (KITTI) or 8 columns "
                       f"(TUM: key x y z qx qy qz qw), got {columns}")


def write_pcd(path: str | Path, points: np.ndarray) -> None:
    """points (N, 3) as a binary PCD, written atomically (temporary file, fsync, rename)."""
    path = Path(path)
    points = np.ascontiguousarray(points[:, :3], dtype="<f4")
    header = ("# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\n"
              "SIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
              f"WIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
              f"POINTS {len(points)}\nDATA binary\n").encode("ascii")
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(handle, "wb") as stream:
            stream.write(header)
            stream.write(points.tobytes())
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def accumulate(sequence: Sequence, voxel_m: float = 0.2, *, progress: bool = True,
               flush_every: int = 50) -> np.ndarray:
    """A global map (N, 3) float32 from a posed sequence: every scan in the world frame, one
    point per voxel_m voxel (deduplicated every flush_every scans, so memory follows the map's
    size, not the number of scans)."""
    if not voxel_m > 0:
        raise ValueError(f"voxel_m must be > 0, got {voxel_m!r}")
    if sequence.poses is None:
        raise ValueError(f"{sequence.name}: accumulating a map needs the scans' poses")
    merged = np.zeros((0, 3), dtype=np.float32)
    batch: list[np.ndarray] = []
    valid = np.flatnonzero(np.isfinite(sequence.poses).all(axis=(1, 2)))
    for scan in progress_bar(sequence.iter_scans(valid), total=len(valid), desc="accumulate",
                             enabled=progress, unit="scan"):
        if scan.problem:
            continue
        if scan.points is None:
            raise InvalidCloudError(f"{sequence.name}: accumulating needs point clouds, not "
                                    "density images")
        points = np.asarray(scan.points)[:, :3]
        points = rows_where(points, finite_rows(points))
        batch.append(moved_points(points, scan.pose).astype(np.float32))
        if len(batch) >= flush_every:
            merged = one_point_per_voxel(np.concatenate([merged, *batch]), voxel_m)
            batch = []
    merged = one_point_per_voxel(np.concatenate([merged, *batch]), voxel_m)
    if not len(merged):
        raise InvalidCloudError(f"{sequence.name}: no finite point to accumulate")
    return merged


class TiledCloud:
    """A cloud sorted by square tiles into a memory-mapped file: a view reads only the tiles
    it overlaps (near). The coordinates are stored as three columns (x, y, z), so a view's
    arithmetic runs on contiguous arrays. The file lives in folder (a temporary one by default)
    until close().

    Pickled, it is a handle to that file, not its points: a Dask worker opens the same file
    (the folder must be one every worker sees at the same path), and only the instance that
    made the file removes it."""

    def __init__(self, points: np.ndarray, tile_m: float, folder: str | Path | None = None
                 ) -> None:
        self.tile_m = tile_m
        self.origin = points[:, :2].min(axis=0)
        tiles = np.floor((points[:, :2] - self.origin) / tile_m).astype(np.int64)
        self.shape = tuple(int(v) for v in tiles.max(axis=0) + 1)
        keys = tiles[:, 0] * self.shape[1] + tiles[:, 1]
        order = np.argsort(keys, kind="stable")
        self._folder = tempfile.TemporaryDirectory(dir=folder, prefix="mf_lpr_tiles_")
        self._path = Path(self._folder.name) / "columns.f32"
        stored = np.memmap(self._path, dtype=np.float32, mode="w+", shape=(3, len(points)))
        stored[:] = points[order, :3].T
        stored.flush()
        del stored
        self.columns = np.memmap(self._path, dtype=np.float32, mode="r", shape=(3, len(points)))
        counts = np.bincount(keys, minlength=self.shape[0] * self.shape[1])
        self._starts = np.concatenate([[0], np.cumsum(counts)])

    def __getstate__(self) -> dict:
        return {"tile_m": self.tile_m, "origin": self.origin, "shape": self.shape,
                "path": str(self._path), "starts": self._starts,
                "count": int(self.columns.shape[1])}

    def __setstate__(self, state: dict) -> None:
        self.tile_m, self.origin, self.shape = state["tile_m"], state["origin"], state["shape"]
        self._starts = state["starts"]
        self._folder = None
        self._path = Path(state["path"])
        expected = 3 * state["count"] * np.dtype(np.float32).itemsize
        try:
            size = self._path.stat().st_size
        except OSError:
            raise InvalidCloudError(
                f"{self._path}: the tiled global cloud is not on this machine; a cluster on "
                "other machines needs the tiles in a folder every worker sees at the same path "
                "(build-map --tiles-dir)") from None
        if size != expected:
            raise InvalidCloudError(f"{self._path}: the tiled global cloud holds {size} bytes, "
                                    f"{expected} expected (another build replaced it?)")
        self.columns = np.memmap(self._path, dtype=np.float32, mode="r",
                                 shape=(3, state["count"]))

    def near(self, x: float, y: float, half: float) -> np.ndarray:
        """(3, n) x, y, z columns (a copy) of every point in the tiles that the square
        |px - x| < half, |py - y| < half overlaps: a superset of the window, in tile order."""
        low = np.floor((np.array([x, y]) - half - self.origin) / self.tile_m).astype(int)
        high = np.floor((np.array([x, y]) + half - self.origin) / self.tile_m).astype(int)
        low = np.maximum(low, 0)
        high = np.minimum(high, np.array(self.shape) - 1)
        # One contiguous run of tiles per tile row: slices, never an index array (20x slower).
        rows = [self.columns[:, self._starts[tx * self.shape[1] + low[1]]:
                             self._starts[tx * self.shape[1] + high[1] + 1]]
                for tx in range(low[0], high[0] + 1)]
        if not rows:
            return np.zeros((3, 0), dtype=np.float32)
        return np.concatenate(rows, axis=1)

    def close(self) -> None:
        del self.columns
        if self._folder is not None:
            self._folder.cleanup()
