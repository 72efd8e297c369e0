"""Relocalising off the mapping path: a keyframe map against a global-map grid, in the simulator.

The simulator's town (mf_lpr_ros/sim/simulator.py) is mapped twice from one drive around its
perimeter: as keyframes (a ray-cast scan every 2 m) and as a grid of references rendered from a
global cloud, the drive seeding the area. The global cloud is either the drive's scans
accumulated (what a SLAM run writes; source "drive") or the town's surfaces sampled whole
(simulator.scene_cloud; source "world"). Queries are
ray-cast scans from lanes 5-10 m beside that drive and from the middle street it never drove;
each is relocalised against both maps and counted when within 0.5 m and 2 degrees.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from mf_lpr_ros.config import preset
from mf_lpr_ros.core.descriptor import describe_points, one_point_per_voxel
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.pose import moved_points, planar_error, pose_matrix, quaternion_from_yaw
from mf_lpr_ros.core.search import MatchedFilterIndex
from mf_lpr_ros.pipeline.global_map import RenderParams, build_global_map
from mf_lpr_ros.progress import progress_bar
from mf_lpr_ros.sim.lidar import cast
from mf_lpr_ros.sim.scenes import scene_cloud
from mf_lpr_ros.sim.simulator import drive, urban_traversals

LANE_OFFSETS_M = (5.0, -6.0, 7.5, -9.0)
QUERY_STEP_M = 9.0
KEYFRAME_SPACING_M = 2.0
GLOBAL_SOURCES = ("drive", "world")


@dataclass
class DemoRow:
    queries: str
    count: int
    keyframe_ok: int
    global_ok: int


def _pose(x: float, y: float, yaw: float, height: float) -> np.ndarray:
    return pose_matrix(np.array([x, y, height]), quaternion_from_yaw(yaw))


def run(source: str = "drive", progress: bool = True) -> tuple[list[DemoRow], dict]:
    """The demo's rows and facts (map sizes, build time)."""
    if source not in GLOBAL_SOURCES:
        raise ValueError(f"global cloud source must be one of {GLOBAL_SOURCES}, got {source!r}")
    town = urban_traversals()
    sensor = town.sensor
    height = sensor.mount_height_m
    config = preset("kitti")
    rng = np.random.default_rng(0)
    drive_poses = town.first[::round(KEYFRAME_SPACING_M)]
    keyframes = ReferenceMap(config.descriptor)
    drive_clouds = []
    for index, (x, y, yaw) in enumerate(drive_poses):
        pose = _pose(x, y, yaw, height)
        scan = cast(town.scene, sensor, pose, rng)
        keyframes.append(describe_points(scan, config.descriptor, reference=True,
                                         seed_key=index), pose, 0.0, index)
        drive_clouds.append(moved_points(scan, pose))
    cloud = (one_point_per_voxel(np.concatenate(drive_clouds).astype(np.float32), 0.1)
             if source == "drive" else scene_cloud(town.scene))
    started = time.perf_counter()
    render = RenderParams(elevation_deg=(min(sensor.elevations_deg), max(sensor.elevations_deg)))
    grid = build_global_map(f"simulator town ({source})", config, points=cloud,
                            trajectory=np.stack([_pose(*p, height) for p in drive_poses]),
                            render=render, progress=progress)
    build_s = time.perf_counter() - started
    perimeter = np.array([[0, 0], [100, 0], [100, 100], [0, 100], [0, 0]], float)
    groups = {f"lane {offset:+.1f} m beside the drive": drive(perimeter, QUERY_STEP_M, offset)
              for offset in LANE_OFFSETS_M}
    groups["middle street (never driven)"] = drive(np.array([[50.0, 8.0], [50.0, 92.0]]),
                                                   QUERY_STEP_M / 2)
    indices = {name: MatchedFilterIndex(m, config.search)
               for name, m in (("keyframe", keyframes), ("global", grid))}
    rows = []
    for name, queries in groups.items():
        ok = {"keyframe": 0, "global": 0}
        for x, y, yaw in progress_bar(queries, total=len(queries), desc=name, enabled=progress,
                                      unit="query"):
            occupancy = describe_points(cast(town.scene, sensor, _pose(x, y, yaw, height), rng),
                                        config.descriptor)
            for kind, index in indices.items():
                match = index.query(occupancy)
                error_m, error_deg = planar_error(match.pose, np.array([x, y, yaw]))
                ok[kind] += error_m < 0.5 and error_deg < 2.0
        rows.append(DemoRow(name, len(queries), ok["keyframe"], ok["global"]))
    facts = {"source": source, "keyframes": len(keyframes), "grid_references": len(grid),
             "grid_area_km2": grid.metadata["grid_area_km2"], "build_s": build_s}
    return rows, facts


def format_table(rows: list[DemoRow], facts: dict) -> str:
    lines = ["| queries | n | keyframe map | global-map grid |", "|---|---|---|---|"]
    for row in rows:
        lines.append(f"| {row.queries} | {row.count} | {row.keyframe_ok / row.count:.0%} | "
                     f"{row.global_ok / row.count:.0%} |")
    total = sum(r.count for r in rows)
    lines.append(f"| all | {total} | {sum(r.keyframe_ok for r in rows) / total:.0%} | "
                 f"{sum(r.global_ok for r in rows) / total:.0%} |")
    lines.append(f"\nglobal cloud: {facts['source']}; within 0.5 m and 2 deg; keyframe map "
                 f"{facts['keyframes']} references, "
                 f"grid {facts['grid_references']} references over {facts['grid_area_km2']:.4f}"
                 f" km^2, rendered in {facts['build_s']:.0f} s")
    return "\n".join(lines)
