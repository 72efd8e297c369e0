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
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

from mf_lpr_ros.config import Config
from mf_lpr_ros.core.descriptor import describe_points, one_point_per_voxel
from mf_lpr_ros.core.map_store import GLOBAL_MAP_KIND, ReferenceMap
from mf_lpr_ros.errors import InvalidCloudError
from mf_lpr_ros.params import DescriptorParams
from mf_lpr_ros.pipeline.global_cloud import TiledCloud, read_global_cloud
from mf_lpr_ros.progress import progress_bar


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
