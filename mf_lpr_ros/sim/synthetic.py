"""A small generated world (poles, building blocks, ground) and scans of it, seeded.

Scans keep the world's surface samples within the sensor's range, seen from the scan pose,
with range noise and random dropout. There is no occlusion: this is a scene for tests and the
quick demo, not a LiDAR simulator.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mf_lpr_ros.core.pose import pose_matrix, quaternion_from_yaw


@dataclass
class World:
    points: np.ndarray  # (N, 3) world frame


def make_world(seed: int, half_extent_m: float = 60.0, n_objects: int = 220) -> World:
    """Random poles and box-shaped blocks on a ground plane at z = -1.7 m."""
    rng = np.random.default_rng(seed)
    parts = []
    for _ in range(n_objects):
        centre = rng.uniform(-half_extent_m, half_extent_m, 2)
        if rng.random() < 0.5:
            radius, height, n = rng.uniform(0.1, 0.5), rng.uniform(2.0, 8.0), 150
            angle = rng.uniform(0, 2 * np.pi, n)
            parts.append(np.c_[centre[0] + radius * np.cos(angle),
                               centre[1] + radius * np.sin(angle),
                               rng.uniform(-1.7, height, n)])
        else:
            size = rng.uniform(1.5, 8.0, 2)
            height, n = rng.uniform(2.5, 10.0), 600
            side = rng.integers(0, 4, n)
            t = rng.uniform(-0.5, 0.5, n)
            x = np.where(side < 2, t * size[0], np.where(side == 2, -0.5, 0.5) * size[0])
            y = np.where(side < 2, np.where(side == 0, -0.5, 0.5) * size[1], t * size[1])
            yaw = rng.uniform(0, np.pi)
            c, s = np.cos(yaw), np.sin(yaw)
            parts.append(np.c_[centre[0] + c * x - s * y, centre[1] + s * x + c * y,
                               rng.uniform(-1.7, height, n)])
    ground = np.c_[rng.uniform(-half_extent_m, half_extent_m, (20000, 2)), np.full(20000, -1.7)]
    return World(np.concatenate(parts + [ground]).astype(np.float64))


def scan_world(world: World, x: float, y: float, yaw: float, rng: np.random.Generator,
               max_range_m: float = 40.0, noise_m: float = 0.02,
               dropout: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """(points (N, 3) float32 in the sensor frame, world_T_sensor 4x4) of a scan at (x, y, yaw)."""
    pose = pose_matrix(np.array([x, y, 0.0]), quaternion_from_yaw(yaw))
    local = (world.points - pose[:3, 3]) @ pose[:3, :3]
    keep = (np.hypot(local[:, 0], local[:, 1]) < max_range_m) & (rng.random(len(local)) > dropout)
    local = local[keep] + rng.normal(0, noise_m, (int(keep.sum()), 3))
    return local.astype(np.float32), pose


def route(n_scans: int, radius_m: float = 30.0, lateral_offset_m: float = 0.0,
          reverse: bool = False) -> np.ndarray:
    """(n, 3) x, y, yaw at equal steps around a rounded-square loop; optionally offset sideways
    (to the left of travel) and driven the other way."""
    t = np.linspace(0, 2 * np.pi, 20000, endpoint=False)
    x = radius_m * np.sign(np.cos(t)) * np.abs(np.cos(t)) ** 0.5
    y = radius_m * np.sign(np.sin(t)) * np.abs(np.sin(t)) ** 0.5
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
    samples = np.linspace(0, arc[-1], n_scans, endpoint=False)
    x, y = np.interp(samples, arc, x), np.interp(samples, arc, y)
    heading = np.arctan2(np.gradient(y), np.gradient(x))
    x = x - lateral_offset_m * np.sin(heading)
    y = y + lateral_offset_m * np.cos(heading)
    if reverse:
        x, y, heading = x[::-1], y[::-1], heading[::-1] + np.pi
    return np.stack([x, y, heading], axis=1)


def write_kitti_sequence(folder: Path, world: World, trajectory: np.ndarray, seed: int,
                         dropout: float = 0.1) -> None:
    """A KITTI odometry-style folder (velodyne/*.bin, poses.txt, times.txt) of scans, each
    return dropped with probability dropout."""
    rng = np.random.default_rng(seed)
    (folder / "velodyne").mkdir(parents=True, exist_ok=True)
    poses = []
    for index, (x, y, yaw) in enumerate(trajectory):
        points, pose = scan_world(world, x, y, yaw, rng, dropout=dropout)
        records = np.zeros((len(points), 4), dtype="<f4")
        records[:, :3] = points
        records.tofile(folder / "velodyne" / f"{index:06d}.bin")
        poses.append(pose[:3, :4].ravel())
    np.savetxt(folder / "poses.txt", np.asarray(poses), fmt="%.9e")
    np.savetxt(folder / "times.txt", np.arange(len(trajectory)) * 0.1, fmt="%.6f")
