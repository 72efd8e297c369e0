"""Reference descriptors rendered from a global point-cloud map, anywhere the robot can be.

A SLAM map (PCD/PLY, world frame, z up) becomes a map of virtual references on a grid over the
traversable area:
- ground and traversability: a 2-D grid (ground_cell_m) holds the lowest point of each cell
  (the ground) and whether anything stands in the body band above it (an obstacle);
- the area: the free cells connected to the trajectory's cells when a trajectory is given (the
  streets the mapping run drove, and the lanes and side streets reachable from them), else
  every free cell; references on a spacing_m lattice over it;
- each reference: what a sensor sensor_height_m above the local ground would see there: the
  descriptor window around it, heights relative to it (so the presets' height bands apply),
  and only what a LiDAR there would return: the nearest point per beam direction
  (RenderParams' angular resolution and vertical field of view), described as a reference
  scan with yaw 0 (the search covers every rotation).
The cloud is sorted by square tiles into a memory-mapped file, so a window reads only the
tiles it overlaps and a map of a few km^2 builds on a workstation.
"""

from __future__ import annotations

import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

from mf_lpr_ros.config import Config
from mf_lpr_ros.params import DescriptorParams
from mf_lpr_ros.errors import DatasetError
from mf_lpr_ros.datasets.base import Sequence, read_kitti_poses, read_tum_poses
from mf_lpr_ros.io.pcd import read_pcd
from mf_lpr_ros.io.ply import read_ply
from mf_lpr_ros.errors import InvalidCloudError
from mf_lpr_ros.core.descriptor import describe_points, one_point_per_voxel
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.progress import progress_bar

GLOBAL_MAP_KIND = "global_map_grid"


@dataclass(frozen=True)
class RenderParams:
    """How references are rendered from a global cloud (see the module doc).

    spacing_m: lattice spacing of the references. sensor_height_m: the virtual sensor's height
    above the local ground (None: the trajectory's median height above its ground, else 1.8 m).
    ground_cell_m: cell of the ground/obstacle grid. body_band_m: heights above the ground
    where a point makes a cell an obstacle. azimuth_bins, elevation_bin_deg: the virtual
    sensor's angular resolution: one return, the nearest, per direction bin (what a LiDAR
    records: a facade as sparse rings, nothing behind it); match elevation_bin_deg to the
    sensor's beam spacing. elevation_deg: its vertical field of view (lowest, highest beam;
    None: unlimited). horizontal_fov_deg: below 360 (a forward-looking sensor, e.g. a Livox
    Avia's 70), each position gets references facing several headings (RenderParams.headings),
    each holding only that wedge: a 70-degree scan does not resemble a 360-degree view.
    tile_m: side of the tiles of the memory-mapped cloud.
    """

    spacing_m: float = 2.0
    sensor_height_m: float | None = None
    ground_cell_m: float = 1.0
    body_band_m: tuple[float, float] = (0.4, 2.0)
    azimuth_bins: int = 720
    elevation_bin_deg: float = 2.0
    elevation_deg: tuple[float, float] | None = None
    horizontal_fov_deg: float = 360.0
    tile_m: float = 32.0

    def headings(self) -> np.ndarray:
        """Yaws (rad) of the references rendered at each position: 0 alone for a 360-degree
        sensor; for a narrower one, every half field of view round the circle, so any heading
        is within a quarter field of view of a rendered one."""
        if self.horizontal_fov_deg >= 360:
            return np.zeros(1)
        count = math.ceil(360.0 / (self.horizontal_fov_deg / 2))
        return np.arange(count) * (2 * np.pi / count)

    def __post_init__(self) -> None:
        if not 0 < self.horizontal_fov_deg <= 360:
            raise ValueError(f"global map parameter horizontal_fov_deg must be in (0, 360], got "
                             f"{self.horizontal_fov_deg!r}")
        for name in ("spacing_m", "ground_cell_m", "elevation_bin_deg", "tile_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"global map parameter {name} must be > 0, got "
                                 f"{getattr(self, name)!r}")
        if self.sensor_height_m is not None and not self.sensor_height_m > 0:
            raise ValueError(f"global map parameter sensor_height_m must be > 0, got "
                             f"{self.sensor_height_m!r}")


DEFAULT_SENSOR_HEIGHT_M = 1.8


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
    points = points[np.isfinite(points).all(axis=1)]
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
        if scan.points is None:
            raise InvalidCloudError(f"{sequence.name}: accumulating needs point clouds, not "
                                    "density images")
        points = np.asarray(scan.points)[:, :3]
        points = points[np.isfinite(points).all(axis=1)]
        batch.append((points @ scan.pose[:3, :3].T + scan.pose[:3, 3]).astype(np.float32))
        if len(batch) >= flush_every:
            merged = one_point_per_voxel(np.concatenate([merged, *batch]), voxel_m)
            batch = []
    merged = one_point_per_voxel(np.concatenate([merged, *batch]), voxel_m)
    if not len(merged):
        raise InvalidCloudError(f"{sequence.name}: no finite point to accumulate")
    return merged


class TiledCloud:
    """A cloud sorted by square tiles into a memory-mapped file: window() reads only the tiles
    a window overlaps. The file lives in folder (a temporary one by default) until close()."""

    def __init__(self, points: np.ndarray, tile_m: float, folder: str | Path | None = None
                 ) -> None:
        self.tile_m = tile_m
        self.origin = points[:, :2].min(axis=0)
        tiles = np.floor((points[:, :2] - self.origin) / tile_m).astype(np.int64)
        self.shape = tuple(int(v) for v in tiles.max(axis=0) + 1)
        keys = tiles[:, 0] * self.shape[1] + tiles[:, 1]
        order = np.argsort(keys, kind="stable")
        self._folder = tempfile.TemporaryDirectory(dir=folder, prefix="mf_lpr_tiles_")
        self._path = Path(self._folder.name) / "points.f32"
        stored = np.memmap(self._path, dtype=np.float32, mode="w+", shape=(len(points), 3))
        stored[:] = points[order]
        stored.flush()
        del stored
        self.points = np.memmap(self._path, dtype=np.float32, mode="r", shape=(len(points), 3))
        counts = np.bincount(keys, minlength=self.shape[0] * self.shape[1])
        self._starts = np.concatenate([[0], np.cumsum(counts)])

    def window(self, x: float, y: float, half: float) -> np.ndarray:
        """Points with |px - x| < half and |py - y| < half (a copy)."""
        low = np.floor((np.array([x, y]) - half - self.origin) / self.tile_m).astype(int)
        high = np.floor((np.array([x, y]) + half - self.origin) / self.tile_m).astype(int)
        low = np.maximum(low, 0)
        high = np.minimum(high, np.array(self.shape) - 1)
        parts = []
        for tx in range(low[0], high[0] + 1):
            first = tx * self.shape[1]
            start, stop = self._starts[first + low[1]], self._starts[first + high[1] + 1]
            if stop > start:
                parts.append(np.asarray(self.points[start:stop]))
        if not parts:
            return np.zeros((0, 3), dtype=np.float32)
        points = np.concatenate(parts)
        inside = (np.abs(points[:, 0] - x) < half) & (np.abs(points[:, 1] - y) < half)
        return points[inside]

    def close(self) -> None:
        del self.points
        self._folder.cleanup()


@dataclass
class GroundGrid:
    """The ground height (NaN: no point) and obstacles of each ground_cell_m cell."""

    origin: np.ndarray
    cell_m: float
    ground: np.ndarray
    obstacle: np.ndarray

    def cell_of(self, xy: np.ndarray) -> np.ndarray:
        return np.floor((np.atleast_2d(xy) - self.origin) / self.cell_m).astype(np.int64)

    def ground_at(self, xy: np.ndarray) -> np.ndarray:
        """The ground height under each position (the nearest cell with ground)."""
        cells = np.clip(self.cell_of(xy), 0, np.array(self.ground.shape) - 1)
        filled = self._filled_ground()
        return filled[cells[:, 0], cells[:, 1]]

    def _filled_ground(self) -> np.ndarray:
        missing = np.isnan(self.ground)
        if not missing.any():
            return self.ground
        nearest = ndimage.distance_transform_edt(missing, return_distances=False,
                                                 return_indices=True)
        return self.ground[tuple(nearest)]


def ground_grid(points: np.ndarray, cell_m: float, body_band_m: tuple[float, float]
                ) -> GroundGrid:
    """Lowest point per cell as the ground; a cell is an obstacle when a point lies in the body
    band above its ground."""
    origin = points[:, :2].min(axis=0)
    cells = np.floor((points[:, :2] - origin) / cell_m).astype(np.int64)
    shape = tuple(int(v) for v in cells.max(axis=0) + 1)
    flat = cells[:, 0] * shape[1] + cells[:, 1]
    ground = np.full(shape[0] * shape[1], np.inf)
    np.minimum.at(ground, flat, points[:, 2])
    above = points[:, 2] - ground[flat]
    obstacle = np.zeros(shape[0] * shape[1], dtype=bool)
    obstacle[flat[(above >= body_band_m[0]) & (above <= body_band_m[1])]] = True
    ground[np.isinf(ground)] = np.nan
    return GroundGrid(origin, cell_m, ground.reshape(shape), obstacle.reshape(shape))


def reference_positions(grid: GroundGrid, spacing_m: float,
                        trajectory_xy: np.ndarray | None = None) -> np.ndarray:
    """(n, 2) positions on a spacing_m lattice over the free cells (ground, no obstacle)
    connected to the trajectory's cells, or over every free cell without a trajectory."""
    free = ~np.isnan(grid.ground) & ~grid.obstacle
    if trajectory_xy is not None and len(trajectory_xy):
        cells = np.clip(grid.cell_of(trajectory_xy), 0, np.array(free.shape) - 1)
        # The trajectory's own cells are driveable, whatever the grid says about them.
        free[cells[:, 0], cells[:, 1]] = True
        labels, _ = ndimage.label(free, structure=np.ones((3, 3)))
        seeds = np.unique(labels[cells[:, 0], cells[:, 1]])
        free = np.isin(labels, seeds[seeds > 0])
    lattice = np.arange(0.0, max(free.shape) * grid.cell_m + spacing_m, spacing_m)
    xs = grid.origin[0] + lattice[lattice < free.shape[0] * grid.cell_m]
    ys = grid.origin[1] + lattice[lattice < free.shape[1] * grid.cell_m]
    candidates = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)
    cells = grid.cell_of(candidates)
    return candidates[free[cells[:, 0], cells[:, 1]]]


def render_view(cloud: TiledCloud, position: np.ndarray, ground_z: float,
                params: DescriptorParams, render: RenderParams, sensor_height_m: float
                ) -> np.ndarray:
    """The points a sensor sensor_height_m above the ground at position would see, in its frame
    (yaw 0), within the descriptor's window and below its height band's top."""
    window = cloud.window(float(position[0]), float(position[1]), params.extent_m / 2)
    local = window - np.array([position[0], position[1], ground_z + sensor_height_m],
                              dtype=np.float32)
    if params.z_max is not None:
        local = local[local[:, 2] <= params.z_max]
    if not len(local):
        return local
    ranges = np.hypot(local[:, 0], local[:, 1])
    if render.elevation_deg is not None:
        elevation = np.degrees(np.arctan2(local[:, 2], ranges))
        in_view = (elevation >= render.elevation_deg[0]) & (elevation <= render.elevation_deg[1])
        local, ranges = local[in_view], ranges[in_view]
    azimuth = ((np.arctan2(local[:, 1], local[:, 0]) + np.pi) / (2 * np.pi)
               * render.azimuth_bins).astype(np.int64) % render.azimuth_bins
    n_elevations = int(180.0 / render.elevation_bin_deg) + 1
    elevation = np.clip(((np.degrees(np.arctan2(local[:, 2], ranges)) + 90.0)
                         / render.elevation_bin_deg).astype(np.int64), 0, n_elevations - 1)
    bins = azimuth * n_elevations + elevation
    # One return per beam direction, the nearest: what a LiDAR with this angular resolution
    # records (fewer, sparser points on a facade than the map holds, and nothing behind it).
    order = np.argsort(ranges, kind="stable")
    _, first = np.unique(bins[order], return_index=True)
    return local[order[first]]


def _facing(view: np.ndarray, heading: float, fov_deg: float) -> np.ndarray:
    """The part of a yaw-0 view a sensor facing heading (rad) with this horizontal field of
    view sees, in that sensor's frame."""
    if fov_deg >= 360:
        return view
    c, s = np.cos(heading), np.sin(heading)
    turned = view.copy()
    turned[:, 0] = c * view[:, 0] + s * view[:, 1]
    turned[:, 1] = -s * view[:, 0] + c * view[:, 1]
    off_axis = np.degrees(np.abs(np.arctan2(turned[:, 1], turned[:, 0])))
    return turned[off_axis <= fov_deg / 2]


def build_global_map(cloud_path: str | Path, config: Config, *,
                     trajectory: np.ndarray | None = None,
                     render: RenderParams = RenderParams(), progress: bool = True,
                     points: np.ndarray | None = None) -> ReferenceMap:
    """A ReferenceMap of references rendered from the global cloud at cloud_path (or points,
    already read) on a grid over the traversable area (see the module doc).

    trajectory: (n, 4, 4) world_T_sensor poses of the mapping run (seeds the area, and gives
    the sensor height when render.sensor_height_m is None).
    """
    if config.auto:
        raise ValueError("preset auto measures scans; a global map has none: name a preset")
    points = read_global_cloud(cloud_path) if points is None else points
    grid = ground_grid(points, render.ground_cell_m, render.body_band_m)
    trajectory_xy = None
    height = render.sensor_height_m
    if trajectory is not None:
        trajectory = trajectory[np.isfinite(trajectory).all(axis=(1, 2))]
        trajectory_xy = trajectory[:, :2, 3]
        if height is None and len(trajectory):
            height = float(np.median(trajectory[:, 2, 3] - grid.ground_at(trajectory_xy)))
    height = DEFAULT_SENSOR_HEIGHT_M if height is None or not height > 0 else height
    positions = reference_positions(grid, render.spacing_m, trajectory_xy)
    if not len(positions):
        raise InvalidCloudError(f"{cloud_path}: no traversable ground found in the global map")
    grounds = grid.ground_at(positions)
    params = config.descriptor
    # Half a voxel keeps every occupied voxel of a view occupied, at a fraction of the points.
    cloud = TiledCloud(one_point_per_voxel(points, params.voxel_size / 2), render.tile_m)
    headings = render.headings()
    reference_map = ReferenceMap(params, metadata={
        "kind": GLOBAL_MAP_KIND, "source": str(cloud_path), "spacing_m": render.spacing_m,
        "sensor_height_m": height, "cloud_points": int(len(points)),
        "grid_area_km2": len(positions) * render.spacing_m ** 2 / 1e6})
    try:
        for index in progress_bar(range(len(positions)), total=len(positions),
                                  desc="render references", enabled=progress, unit="ref"):
            view = render_view(cloud, positions[index], float(grounds[index]), params,
                               render, height)
            for heading in headings:
                seen = _facing(view, heading, render.horizontal_fov_deg)
                try:
                    occupancy = describe_points(seen, params, reference=True,
                                                seed_key=len(reference_map))
                except InvalidCloudError:
                    continue
                pose = np.eye(4)
                pose[:2, :2] = [[np.cos(heading), -np.sin(heading)],
                                [np.sin(heading), np.cos(heading)]]
                pose[:3, 3] = [positions[index, 0], positions[index, 1],
                               grounds[index] + height]
                reference_map.append(occupancy, pose, 0.0, index)
    finally:
        cloud.close()
    if not len(reference_map):
        raise InvalidCloudError(f"{cloud_path}: no reference could be rendered (nothing within "
                                "the descriptor's window and height band)")
    return reference_map
