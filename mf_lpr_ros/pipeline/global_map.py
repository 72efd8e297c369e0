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
  scan with yaw 0 (the search covers every rotation);
- when the map keeps clouds (asked, or search.verify_fitness > 0: ICP verification), the
  global cloud thinned to the descriptor's voxel is stored once as the map's site cloud
  (core.site_cloud), and each reference's cloud is cut from it: everything a match's query
  may overlap (the descriptor window widened by max_shift_m), in the reference's frame, so
  that ICP verifies a match against the map itself, as it verifies against a keyframe's scan
  in a map of scans.
The cloud is sorted by square tiles into a memory-mapped file of x, y, z columns, so a view
reads only the tiles it overlaps and a map of a few km^2 builds on a workstation. A view costs
~5 ms: the nearest return per direction is one integer minimum per bin, not a sort. Views are
rendered by worker processes (every core by default; the tiles are shared, not copied) or, for
areas beyond one machine, by the workers of a Dask cluster, which open the tiles' file by its
path; the patch cap is applied in order in the parent, so the map does not depend on the number
of workers or where they run. Before rendering, a sample of views is timed and the expected
count, time and size are reported.
"""

from __future__ import annotations

import gc
import math
import multiprocessing
import os
import sys
import time
from collections import deque
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
from scipy import ndimage

from mf_lpr_ros.config import Config
from mf_lpr_ros.core.descriptor import cap_patches, describe_points, one_point_per_voxel, scan_seed
from mf_lpr_ros.core.map_store import GLOBAL_MAP_KIND, ReferenceMap
from mf_lpr_ros.core.references import keeps_clouds
from mf_lpr_ros.core.site_cloud import SiteCloud
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
    reach_m: a position is rendered only when structure (an obstacle cell) lies within this
    distance: the middle of an open field sees only ground, and a km^2 of it would become
    thousands of references that match nothing. None: the descriptor window's half width
    (nothing in reach, nothing in the window); math.inf: no limit.
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
    reach_m: float | None = None
    tile_m: float = 8.0

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
        if self.reach_m is not None and not self.reach_m > 0:
            raise ValueError(f"global map parameter reach_m must be > 0, got {self.reach_m!r}")
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
                        trajectory_xy: np.ndarray | None = None,
                        reach_m: float = math.inf) -> np.ndarray:
    """(n, 2) positions on a spacing_m lattice over the free cells (ground, no obstacle)
    connected to the trajectory's cells, or over every free cell without a trajectory, with
    an obstacle cell within reach_m."""
    free = ~np.isnan(grid.ground) & ~grid.obstacle
    if math.isfinite(reach_m) and grid.obstacle.any():
        free &= ndimage.distance_transform_edt(~grid.obstacle) * grid.cell_m <= reach_m
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
    half = params.extent_m / 2
    x, y, z = cloud.near(float(position[0]), float(position[1]), half)
    x = x - np.float32(position[0])
    y = y - np.float32(position[1])
    z = z - np.float32(ground_z + sensor_height_m)
    ranges = np.hypot(x, y)
    # The descriptor drops what lies beyond its disc (or max_range), and a farther point never
    # hides a nearer one: dropping it now changes no return the descriptor keeps. (So the
    # disc needs no square window first.)
    reach = half * (1.0 if params.crop == "disc" else math.sqrt(2.0))
    if params.max_range is not None:
        reach = min(reach, params.max_range)
    keep = ranges <= reach + params.voxel_size
    if params.crop != "disc":
        keep &= (np.abs(x) < half) & (np.abs(y) < half)
    if params.z_max is not None:
        keep &= z <= params.z_max
    kept = np.flatnonzero(keep)
    x, y, z, ranges = x[kept], y[kept], z[kept], ranges[kept]
    elevation = np.degrees(np.arctan2(z, ranges))
    if render.elevation_deg is not None:
        in_view = np.flatnonzero((elevation >= render.elevation_deg[0])
                                 & (elevation <= render.elevation_deg[1]))
        x, y, z, ranges, elevation = (x[in_view], y[in_view], z[in_view], ranges[in_view],
                                      elevation[in_view])
    azimuth = ((np.arctan2(y, x) + np.pi) / (2 * np.pi)
               * render.azimuth_bins).astype(np.int64) % render.azimuth_bins
    n_elevations = int(180.0 / render.elevation_bin_deg) + 1
    elevation_bin = np.clip(((elevation + 90.0) / render.elevation_bin_deg).astype(np.int64),
                            0, n_elevations - 1)
    bins = azimuth * n_elevations + elevation_bin
    # One return per beam direction, the nearest (the first of equals): what a LiDAR with this
    # angular resolution records (fewer, sparser points on a facade than the map holds, and
    # nothing behind it). A non-negative float32's bits order as the float does, so one
    # integer minimum per bin over (range bits, point index) finds it without sorting.
    keys = (ranges.astype(np.float32).view(np.uint32).astype(np.uint64) << np.uint64(32)
            | np.arange(len(ranges), dtype=np.uint64))
    nearest = np.full(render.azimuth_bins * n_elevations, np.iinfo(np.uint64).max,
                      dtype=np.uint64)
    np.minimum.at(nearest, bins, keys)
    hit = np.sort(nearest[nearest != np.iinfo(np.uint64).max] & np.uint64(0xFFFFFFFF))
    hit = hit.astype(np.int64)
    return np.stack([x[hit], y[hit], z[hit]], axis=1)


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
                     points: np.ndarray | None = None, workers: int | None = None,
                     client: Any = None, tiles_folder: str | Path | None = None,
                     report: Callable[[str], None] | None = None,
                     keep_clouds: bool = False) -> ReferenceMap:
    """A ReferenceMap of references rendered from the global cloud at cloud_path (or points,
    already read) on a grid over the traversable area (see the module doc).

    trajectory: (n, 4, 4) world_T_sensor poses of the mapping run (seeds the area, and gives
    the sensor height when render.sensor_height_m is None). workers: rendering processes
    (None: every core this process may use; 1: in this process). client: a Dask
    distributed.Client whose workers render instead (workers is then ignored); tiles_folder:
    where the tiled cloud is written for the renderers (default: a temporary folder, which
    workers on other machines cannot see). report: where the estimate made before rendering
    goes (None: stderr when progress is on). keep_clouds: give every reference its cloud
    (see the module doc; also whenever config.search.verify_fitness > 0).
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
    params = config.descriptor
    reach = params.extent_m / 2 if render.reach_m is None else render.reach_m
    positions = reference_positions(grid, render.spacing_m, trajectory_xy, reach)
    if not len(positions):
        raise InvalidCloudError(f"{cloud_path}: no traversable ground found in the global map")
    grounds = grid.ground_at(positions)
    headings = render.headings()
    reference_map = ReferenceMap(params, metadata={
        "kind": GLOBAL_MAP_KIND, "source": str(cloud_path), "spacing_m": render.spacing_m,
        "sensor_height_m": height, "cloud_points": int(len(points)),
        "grid_area_km2": len(positions) * render.spacing_m ** 2 / 1e6})
    if report is None and progress:
        def report(line: str) -> None:
            print(line, file=sys.stderr, flush=True)
    if client is not None:
        workers = max(1, sum(client.nthreads().values()))
    else:
        workers = max(1, min(workers or len(os.sched_getaffinity(0)), len(positions)))
    site_bytes = 0
    if keeps_clouds(config.search, keep_clouds):
        site_cloud = SiteCloud.from_points(one_point_per_voxel(points, params.voxel_size),
                                           half_m=params.extent_m / 2 + config.search.max_shift_m)
        reference_map.set_site_cloud(site_cloud)
        site_bytes = site_cloud.nbytes
    # Half a voxel keeps every occupied voxel of a view occupied, at a fraction of the points.
    cloud = TiledCloud(one_point_per_voxel(points, params.voxel_size / 2), render.tile_m,
                       tiles_folder)
    global _RENDERER
    _RENDERER = _Renderer(cloud, positions, grounds, params, render, height, headings)
    try:
        if report is not None:
            report(_estimate(_RENDERER, workers, site_bytes))
        added = 0
        rendered = (_rendered_on_cluster(client, _RENDERER, workers) if client is not None
                    else _rendered(workers, len(positions)))
        for index, views in progress_bar(rendered, total=len(positions),
                                         desc="render references", enabled=progress,
                                         unit="position"):
            origin = np.array([positions[index, 0], positions[index, 1],
                               grounds[index] + height])
            for heading, packed in zip(headings, views):
                if packed is None:
                    continue
                occupied = np.unpackbits(packed, count=params.size ** 2).reshape(
                    params.size, params.size).astype(bool)
                pose = np.eye(4)
                pose[:2, :2] = [[np.cos(heading), -np.sin(heading)],
                                [np.sin(heading), np.cos(heading)]]
                pose[:3, 3] = origin
                # Capped here, in map order, with the seed a one-process build gives it.
                reference_map.append(cap_patches(occupied, params, scan_seed(params, added)),
                                     pose, 0.0, index)
                added += 1
    finally:
        _RENDERER = None
        cloud.close()
    if not len(reference_map):
        raise InvalidCloudError(f"{cloud_path}: no reference could be rendered (nothing within "
                                "the descriptor's window and height band)")
    return reference_map


@dataclass
class _Renderer:
    """What rendering a position needs; a module global so forked workers share it."""

    cloud: TiledCloud
    positions: np.ndarray
    grounds: np.ndarray
    params: DescriptorParams
    render: RenderParams
    height: float
    headings: np.ndarray

    def views(self, index: int) -> list[np.ndarray | None]:
        """The packed, uncapped occupancy of each heading's view at position index (None:
        nothing to describe)."""
        view = render_view(self.cloud, self.positions[index], float(self.grounds[index]),
                           self.params, self.render, self.height)
        packed: list[np.ndarray | None] = []
        for heading in self.headings:
            try:
                occupancy = describe_points(_facing(view, heading, self.render.horizontal_fov_deg),
                                            self.params)
            except InvalidCloudError:
                packed.append(None)
                continue
            packed.append(np.packbits(occupancy.ravel()))
        return packed


_RENDERER: _Renderer | None = None
_POSITIONS_PER_TASK = 64
_TASKS_IN_FLIGHT_PER_THREAD = 4
_ESTIMATE_SAMPLE = 24


def _render_positions(indices: range, renderer: _Renderer | None = None
                      ) -> list[list[np.ndarray | None]]:
    """The views of positions indices, by renderer (default: this process's _RENDERER)."""
    renderer = renderer or _RENDERER
    return [renderer.views(index) for index in indices]


def _tasks(count: int) -> list[range]:
    return [range(first, min(first + _POSITIONS_PER_TASK, count))
            for first in range(0, count, _POSITIONS_PER_TASK)]


def _rendered_on_cluster(client: Any, renderer: _Renderer, threads: int
                         ) -> Iterator[tuple[int, list[np.ndarray | None]]]:
    """(position index, its views) in position order, rendered by a Dask cluster's workers.
    The renderer goes to every worker once; a few tasks per thread are in flight, so results
    never pile up faster than the map takes them."""
    shared = client.scatter(renderer, broadcast=True)
    tasks = iter(_tasks(len(renderer.positions)))
    pending: deque = deque()

    def submit(task: range) -> None:
        pending.append((task, client.submit(_render_positions, task, shared, pure=False)))

    for task in tasks:
        submit(task)
        if len(pending) >= _TASKS_IN_FLIGHT_PER_THREAD * threads:
            break
    while pending:
        task, future = pending.popleft()
        views = future.result()
        future.release()
        following = next(tasks, None)
        if following is not None:
            submit(following)
        yield from zip(task, views)


def _rendered(workers: int, count: int) -> Iterator[tuple[int, list[np.ndarray | None]]]:
    """(position index, its views) in position order, rendered by workers processes."""
    tasks = _tasks(count)
    if workers == 1:
        for task in tasks:
            yield from zip(task, _render_positions(task))
        return
    # fork: the workers share the tiled cloud's pages and the renderer without pickling them.
    # What the parent holds is collected here and frozen (gc.freeze) for the workers' lifetime:
    # a worker's garbage collector then never finalises an object of the parent's, such as one
    # bound to a thread or a library state that fork did not copy (a worker crashed so, in a
    # process that had run ROS and torch before), nor writes to its pages.
    gc.collect()
    gc.freeze()
    try:
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork")) as pool:
            for task, views in zip(tasks, pool.map(_render_positions, tasks)):
                yield from zip(task, views)
    finally:
        gc.unfreeze()


def _estimate(renderer: _Renderer, workers: int, site_bytes: int = 0) -> str:
    """A line saying how many references, how long and how large (site_bytes: the site cloud
    the map keeps), from a timed sample."""
    count = len(renderer.positions)
    sample = np.unique(np.linspace(0, count - 1, min(_ESTIMATE_SAMPLE, count)).astype(int))
    started = time.perf_counter()
    rendered = sum(view is not None for index in sample for view in renderer.views(int(index)))
    per_position = (time.perf_counter() - started) / len(sample)
    references = count * rendered / len(sample)
    seconds = count * per_position / workers
    megabytes = (references * (renderer.params.size ** 2 / 8 + 8 * 18) + site_bytes) / 1e6
    duration = f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.0f} min"
    return (f"rendering {count} positions x {len(renderer.headings)} headings: ~{references:.0f} "
            f"references, ~{megabytes:.0f} MB of map, ~{duration} on {workers} "
            f"worker{'s' if workers > 1 else ''} ({per_position * 1e3:.1f} ms a position)")
