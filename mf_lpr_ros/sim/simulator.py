"""A small LiDAR simulator: procedural urban and forest scenes, ray-cast with a spinning
multi-beam sensor, two traversals of a route on different "days", written as ROS 2 bags.

Scenes are built from three primitives (vertical cylinders, boxes turned about z, spheres) on a
ground plane at z = 0. Everything is seeded: the same arguments give the same bags.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from mf_lpr_ros.progress import progress_bar
from mf_lpr_ros.core.pose import pose_matrix, quaternion_from_yaw


@dataclass(frozen=True)
class SensorModel:
    """A spinning LiDAR: beam elevations, azimuth step, range noise, dropout, max range."""

    name: str
    elevations_deg: tuple[float, ...]
    azimuth_step_deg: float = 0.4
    range_noise_m: float = 0.02
    dropout: float = 0.05
    max_range_m: float = 100.0
    mount_height_m: float = 1.8

    def directions(self) -> np.ndarray:
        """(R, 3) unit ray directions in the sensor frame."""
        azimuth = np.radians(np.arange(0.0, 360.0, self.azimuth_step_deg))
        elevation = np.radians(np.asarray(self.elevations_deg))
        az, el = np.meshgrid(azimuth, elevation)
        return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)],
                        -1).reshape(-1, 3)


VLP16 = SensorModel("VLP-16", tuple(np.arange(-15.0, 15.1, 2.0)))
HDL32 = SensorModel("HDL-32E", tuple(np.linspace(-30.67, 10.67, 32)), azimuth_step_deg=0.5,
                    max_range_m=80.0)


@dataclass
class Scene:
    """Cylinders (x, y, radius, height), boxes (x, y, half_x, half_y, yaw, height) and spheres
    (x, y, z, radius); movable marks boxes that may move between days (parked cars)."""

    kind: str
    cylinders: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    spheres: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    movable: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))

    def near(self, x: float, y: float, radius: float) -> "Scene":
        """The primitives whose centre lies within radius (plus their size) of (x, y)."""
        def keep(array: np.ndarray, extent: np.ndarray) -> np.ndarray:
            return np.hypot(array[:, 0] - x, array[:, 1] - y) <= radius + extent

        cylinders = keep(self.cylinders, self.cylinders[:, 2])
        boxes = keep(self.boxes, np.hypot(self.boxes[:, 2], self.boxes[:, 3]))
        spheres = keep(self.spheres, self.spheres[:, 3])
        return Scene(self.kind, self.cylinders[cylinders], self.boxes[boxes],
                     self.spheres[spheres], self.movable[boxes])


def urban_scene(seed: int, block_m: float = 50.0, n_blocks: int = 2,
                street_half_width_m: float = 8.0) -> Scene:
    """Streets on a grid every block_m metres (centre lines at 0, block_m, ...), building blocks
    between them, poles and parked cars along the kerbs."""
    rng = np.random.default_rng(seed)
    boxes, movable, cylinders, spheres = [], [], [], []
    extent = block_m * n_blocks
    for bx in range(-1, n_blocks + 1):
        for by in range(-1, n_blocks + 1):
            x0, y0 = bx * block_m + street_half_width_m, by * block_m + street_half_width_m
            size = block_m - 2 * street_half_width_m
            # A block: 2-4 buildings of varied depth and height along its edges.
            for _ in range(rng.integers(3, 6)):
                half = rng.uniform(4.0, size / 3, 2)
                cx = rng.uniform(x0 + half[0], x0 + size - half[0])
                cy = rng.uniform(y0 + half[1], y0 + size - half[1])
                if rng.random() < 0.7:      # push to the nearest street so facades line it
                    sides = [cx - x0 - half[0], x0 + size - cx - half[0],
                             cy - y0 - half[1], y0 + size - cy - half[1]]
                    side = int(np.argmin(sides))
                    cx, cy = [(x0 + half[0], cy), (x0 + size - half[0], cy),
                              (cx, y0 + half[1]), (cx, y0 + size - half[1])][side]
                boxes.append([cx, cy, half[0], half[1], rng.normal(0, 0.05),
                              rng.uniform(5.0, 25.0)])
                movable.append(False)
    for line in np.arange(0.0, extent + 1e-9, block_m):
        for along in np.arange(-block_m, extent + block_m, 1.0):
            for side in (-1, 1):
                kerb = line + side * (street_half_width_m - 1.0)
                u = rng.random()
                if u < 0.035:                   # poles / street lights / trees
                    cylinders.append([along, kerb, rng.uniform(0.1, 0.25), rng.uniform(3, 9)])
                    cylinders.append([kerb, along, rng.uniform(0.1, 0.25), rng.uniform(3, 9)])
                elif u < 0.06:                  # parked cars
                    for x, y, yaw in ((along, kerb + side * 0.6, 0.0),
                                      (kerb + side * 0.6, along, math.pi / 2)):
                        boxes.append([x, y, 2.2, 0.9, yaw + rng.normal(0, 0.03), 1.5])
                        movable.append(True)
                elif u < 0.07:
                    spheres.append([along, kerb, rng.uniform(3.5, 5.0), rng.uniform(1.5, 2.5)])
    return Scene("urban", np.asarray(cylinders), np.asarray(boxes), np.asarray(spheres).reshape(-1, 4),
                 np.asarray(movable, bool))


def forest_scene(seed: int, trail: np.ndarray, half_extent_m: float = 90.0,
                 trunks_per_100m2: float = 3.0, trail_clearance_m: float = 2.0) -> Scene:
    """Trunks with canopy crowns and undergrowth, cleared along a trail (polyline (N, 2))."""
    rng = np.random.default_rng(seed)
    count = int(trunks_per_100m2 * (2 * half_extent_m) ** 2 / 100)
    xy = rng.uniform(-half_extent_m, half_extent_m, (count, 2)) + trail.mean(0)
    clear = _distance_to_polyline(xy, trail) > trail_clearance_m
    xy = xy[clear]
    radius = rng.uniform(0.1, 0.45, len(xy))
    height = rng.uniform(8.0, 20.0, len(xy))
    cylinders = np.c_[xy, radius, height]
    crowns = np.c_[xy + rng.normal(0, 0.5, xy.shape), height - rng.uniform(1, 3, len(xy)),
                   rng.uniform(1.5, 3.5, len(xy))]
    n_shrubs = len(xy) * 2
    shrub_xy = rng.uniform(-half_extent_m, half_extent_m, (n_shrubs, 2)) + trail.mean(0)
    shrub_xy = shrub_xy[_distance_to_polyline(shrub_xy, trail) > trail_clearance_m - 0.5]
    shrubs = np.c_[shrub_xy, rng.uniform(0.2, 0.8, len(shrub_xy)),
                   rng.uniform(0.3, 0.9, len(shrub_xy))]
    return Scene("forest", cylinders, np.zeros((0, 6)), np.vstack([crowns, shrubs]),
                 np.zeros(0, bool))


def _distance_to_polyline(points: np.ndarray, polyline: np.ndarray) -> np.ndarray:
    a, b = polyline[:-1], polyline[1:]
    ab = b - a
    t = np.clip(np.einsum("pkd,kd->pk", points[:, None] - a[None], ab)
                / np.maximum((ab ** 2).sum(1), 1e-12), 0, 1)
    closest = a[None] + t[..., None] * ab[None]
    return np.linalg.norm(points[:, None] - closest, axis=-1).min(1)


def moved_objects(scene: Scene, seed: int, fraction: float = 0.4) -> Scene:
    """The scene on another day: a fraction of the movable objects gone, others shifted."""
    rng = np.random.default_rng(seed)
    boxes = scene.boxes.copy()
    movable = np.flatnonzero(scene.movable)
    changed = rng.random(len(movable)) < fraction
    gone = movable[changed & (rng.random(len(movable)) < 0.5)]
    shifted = movable[changed & ~np.isin(movable, gone)]
    boxes[shifted, :2] += rng.normal(0, 3.0, (len(shifted), 2)) * [[1, 0.1]]
    keep = np.ones(len(boxes), bool)
    keep[gone] = False
    return replace(scene, boxes=boxes[keep], movable=scene.movable[keep])


def cast(scene: Scene, sensor: SensorModel, pose: np.ndarray, rng: np.random.Generator
         ) -> np.ndarray:
    """One sweep from a levelled world_T_sensor pose: (N, 3) float32 hits in the sensor frame.

    Each primitive is only tested against the azimuth columns its bounding circle covers, so a
    sweep costs about (primitives x columns they span x beams), not (primitives x rays).
    """
    directions = sensor.directions().reshape(len(sensor.elevations_deg), -1, 3) @ pose[:3, :3].T
    n_columns = directions.shape[1]
    origin = pose[:3, 3]
    yaw = math.atan2(pose[1, 0], pose[0, 0])
    local = scene.near(origin[0], origin[1], sensor.max_range_m)
    with np.errstate(divide="ignore", invalid="ignore"):
        distance = np.where(directions[..., 2] < 0, -origin[2] / directions[..., 2], np.inf)
    distance = distance.ravel()
    for array, bound, hits in (
            (local.cylinders, local.cylinders[:, 2], _cylinder_hits),
            (local.boxes, np.hypot(local.boxes[:, 2], local.boxes[:, 3]), _box_hits),
            (local.spheres, local.spheres[:, 3], _sphere_hits)):
        if not len(array):
            continue
        primitive, column = _covered_columns(array[:, :2] - origin[:2], bound, yaw,
                                             sensor.azimuth_step_deg, n_columns)
        rays = directions[:, column].transpose(1, 0, 2)                 # (M, E, 3)
        t = hits(array[primitive], origin, rays)                        # (M, E)
        ray_index = np.arange(directions.shape[0])[None, :] * n_columns + column[:, None]
        np.minimum.at(distance, ray_index.ravel(), t.ravel())
    hit = (distance <= sensor.max_range_m) & (rng.random(len(distance)) >= sensor.dropout)
    ranges = distance[hit] + rng.normal(0, sensor.range_noise_m, int(hit.sum()))
    points_world = origin + directions.reshape(-1, 3)[hit] * ranges[:, None]
    return ((points_world - origin) @ pose[:3, :3]).astype(np.float32)


def _covered_columns(offset: np.ndarray, bound: np.ndarray, yaw: float, step_deg: float,
                     n_columns: int) -> tuple[np.ndarray, np.ndarray]:
    """(primitive, column) pairs: the azimuth columns within each bounding circle's span."""
    distance = np.hypot(offset[:, 0], offset[:, 1])
    centre = np.degrees(np.arctan2(offset[:, 1], offset[:, 0]) - yaw) / step_deg
    inside = distance <= bound
    half = np.where(inside, n_columns / 2,
                    np.degrees(np.arcsin(np.clip(bound / np.maximum(distance, 1e-9), 0, 1)))
                    / step_deg + 1)
    first = np.floor(centre - half).astype(np.int64)
    width = np.minimum(np.ceil(2 * half).astype(np.int64) + 1, n_columns)
    primitive = np.repeat(np.arange(len(offset)), width)
    start = np.repeat(np.cumsum(width) - width, width)
    column = (np.repeat(first, width) + np.arange(len(primitive)) - start) % n_columns
    return primitive, column


def _cylinder_hits(cylinders: np.ndarray, origin: np.ndarray, d: np.ndarray) -> np.ndarray:
    offset = (origin[:2] - cylinders[:, :2])[:, None, :]                # (M, 1, 2)
    a = (d[..., :2] ** 2).sum(-1)
    b = 2 * (d[..., :2] * offset).sum(-1)
    c = (offset ** 2).sum(-1) - cylinders[:, 2:3] ** 2
    disc = b * b - 4 * a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-b - np.sqrt(disc)) / (2 * a)
    z = origin[2] + t * d[..., 2]
    valid = (disc >= 0) & (t > 0) & (z >= 0) & (z <= cylinders[:, 3:4])
    return np.where(valid, t, np.inf)


def _box_hits(boxes: np.ndarray, origin: np.ndarray, d: np.ndarray) -> np.ndarray:
    c, s = np.cos(boxes[:, 4:5]), np.sin(boxes[:, 4:5])                 # (M, 1)
    rel = origin[:2] - boxes[:, :2]
    ox = c[:, 0] * rel[:, 0] + s[:, 0] * rel[:, 1]
    oy = -s[:, 0] * rel[:, 0] + c[:, 0] * rel[:, 1]
    dx = d[..., 0] * c + d[..., 1] * s                                  # (M, E)
    dy = -d[..., 0] * s + d[..., 1] * c
    near, far = np.full(dx.shape, -np.inf), np.full(dx.shape, np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        for o, direction, low, high in ((ox, dx, -boxes[:, 2], boxes[:, 2]),
                                        (oy, dy, -boxes[:, 3], boxes[:, 3]),
                                        (np.full(len(boxes), origin[2]), d[..., 2],
                                         np.zeros(len(boxes)), boxes[:, 5])):
            t1 = (low[:, None] - o[:, None]) / direction
            t2 = (high[:, None] - o[:, None]) / direction
            near = np.maximum(near, np.nan_to_num(np.minimum(t1, t2), nan=-np.inf))
            far = np.minimum(far, np.nan_to_num(np.maximum(t1, t2), nan=np.inf))
    return np.where((near <= far) & (near > 0), near, np.inf)


def _sphere_hits(spheres: np.ndarray, origin: np.ndarray, d: np.ndarray) -> np.ndarray:
    offset = (origin - spheres[:, :3])[:, None, :]
    b = (d * offset).sum(-1)
    c = (offset ** 2).sum(-1) - spheres[:, 3:4] ** 2
    disc = b * b - c
    with np.errstate(invalid="ignore"):
        t = -b - np.sqrt(disc)
    return np.where((disc >= 0) & (t > 0), t, np.inf)


def scene_cloud(scene: Scene, spacing_m: float = 0.25, margin_m: float = 30.0) -> np.ndarray:
    """The scene as a global point cloud (N, 3) float32, world frame: its surfaces sampled every
    spacing_m (ground, cylinder sides, box walls and roofs, spheres), as a SLAM map of the
    whole world would hold them."""
    parts = [_cylinder_surface(c, spacing_m) for c in scene.cylinders]
    parts += [_box_surface(b, spacing_m) for b in scene.boxes]
    parts += [_sphere_surface(sp, spacing_m) for sp in scene.spheres]
    objects = np.concatenate(parts) if parts else np.zeros((0, 3))
    low = objects[:, :2].min(axis=0) - margin_m
    high = objects[:, :2].max(axis=0) + margin_m
    xs, ys = np.arange(low[0], high[0], spacing_m), np.arange(low[1], high[1], spacing_m)
    ground = np.stack(np.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)
    return np.concatenate([np.c_[ground, np.zeros(len(ground))], objects]).astype(np.float32)


def _cylinder_surface(cylinder: np.ndarray, spacing: float) -> np.ndarray:
    x, y, radius, height = cylinder
    angle = np.arange(0.0, 2 * np.pi, max(spacing / radius, 0.05))
    z = np.arange(0.0, height, spacing)
    a, zz = np.meshgrid(angle, z)
    return np.c_[x + radius * np.cos(a.ravel()), y + radius * np.sin(a.ravel()), zz.ravel()]


def _box_surface(box: np.ndarray, spacing: float) -> np.ndarray:
    x, y, half_x, half_y, yaw, height = box
    u, v = np.arange(-half_x, half_x, spacing), np.arange(-half_y, half_y, spacing)
    z = np.arange(0.0, height, spacing)
    walls = [np.c_[np.repeat(u, len(z)), np.full(len(u) * len(z), side * half_y),
                   np.tile(z, len(u))] for side in (-1, 1)]
    walls += [np.c_[np.full(len(v) * len(z), side * half_x), np.repeat(v, len(z)),
                    np.tile(z, len(v))] for side in (-1, 1)]
    uu, vv = np.meshgrid(u, v)
    walls.append(np.c_[uu.ravel(), vv.ravel(), np.full(uu.size, height)])
    local = np.concatenate(walls)
    c, s = math.cos(yaw), math.sin(yaw)
    return np.c_[x + c * local[:, 0] - s * local[:, 1], y + s * local[:, 0] + c * local[:, 1],
                 local[:, 2]]


def _sphere_surface(sphere: np.ndarray, spacing: float) -> np.ndarray:
    x, y, z, radius = sphere
    count = max(int(4 * np.pi * radius ** 2 / spacing ** 2), 8)
    k = np.arange(count) + 0.5
    polar = np.arccos(1 - 2 * k / count)
    azimuth = np.pi * (1 + 5 ** 0.5) * k
    return np.c_[x + radius * np.sin(polar) * np.cos(azimuth),
                 y + radius * np.sin(polar) * np.sin(azimuth), z + radius * np.cos(polar)]


def drive(waypoints: np.ndarray, step_m: float, lateral_offset_m: float = 0.0) -> np.ndarray:
    """(n, 3) x, y, yaw every step_m metres along a polyline, offset to the left of travel."""
    segment = np.hypot(*np.diff(waypoints, axis=0).T)
    arc = np.concatenate([[0.0], np.cumsum(segment)])
    samples = np.arange(0.0, arc[-1], step_m)
    x, y = np.interp(samples, arc, waypoints[:, 0]), np.interp(samples, arc, waypoints[:, 1])
    index = np.clip(np.searchsorted(arc, samples, side="right") - 1, 0, len(segment) - 1)
    direction = np.diff(waypoints, axis=0)[index]
    heading = np.arctan2(direction[:, 1], direction[:, 0])
    return np.c_[x - lateral_offset_m * np.sin(heading), y + lateral_offset_m * np.cos(heading),
                 heading]


@dataclass
class Traversals:
    """A scene, the sensor and two days' routes: (n, 3) x, y, yaw at 10 Hz."""

    scene: Scene
    second_day: Scene
    sensor: SensorModel
    first: np.ndarray
    second: np.ndarray


def urban_traversals(seed: int = 7, step_m: float = 1.0) -> Traversals:
    """Day 1 drives the perimeter of a 2 x 2 block grid. Day 2, in the other lane, drives half
    of it backwards, cuts through the middle street (never seen on day 1) and drives on."""
    block = 50.0
    scene = urban_scene(seed, block_m=block)
    perimeter = np.array([[0, 0], [2 * block, 0], [2 * block, 2 * block], [0, 2 * block], [0, 0]],
                         float)
    backwards = np.array([[2 * block, 2 * block], [2 * block, 0], [block, 0]], float)
    unseen = np.array([[block, 0], [block, 2 * block]], float)
    onwards = np.array([[block, 2 * block], [0, 2 * block], [0, block]], float)
    second = np.vstack([drive(part, step_m, lateral_offset_m=-3.0)
                        for part in (backwards, unseen, onwards)])
    return Traversals(scene, moved_objects(scene, seed + 1), VLP16, drive(perimeter, step_m),
                      second)


def forest_traversals(seed: int = 11, step_m: float = 0.5) -> Traversals:
    """Day 1 walks a trail loop; day 2 walks part of it backwards, 1 m to the side, then takes a
    side trail day 1 never saw."""
    angle = np.linspace(0, 2 * np.pi, 40)
    loop = np.c_[30 * np.cos(angle) + 6 * np.cos(3 * angle), 22 * np.sin(angle)]
    side_trail = np.array([loop[10], loop[10] + [0, 35], loop[10] + [25, 60]])
    scene = forest_scene(seed, np.vstack([loop, side_trail]))
    backwards = loop[25:9:-1]
    second = np.vstack([drive(backwards, step_m, lateral_offset_m=1.0),
                        drive(side_trail, step_m)])
    return Traversals(scene, scene, HDL32, drive(loop, step_m), second)


WORLDS = {"urban": urban_traversals, "forest": forest_traversals}


def write_bag(path: Path, scene: Scene, sensor: SensorModel, trajectory: np.ndarray, seed: int,
              *, start_s: float = 1_700_000_000.0, rate_hz: float = 10.0,
              cloud_topic: str = "/points", odom_topic: str = "/odom",
              progress: bool = True) -> None:
    """A ROS 2 bag (mcap) with PointCloud2 scans in frame 'lidar' and their Odometry
    ('map' -> 'lidar'), one pair per trajectory row at rate_hz."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types = store.types
    rng = np.random.default_rng(seed)
    cloud_type, odom_type = "sensor_msgs/msg/PointCloud2", "nav_msgs/msg/Odometry"
    fields = [types["sensor_msgs/msg/PointField"](name=n, offset=4 * i, datatype=7, count=1)
              for i, n in enumerate("xyz")]
    zero36 = np.zeros(36)
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        clouds = writer.add_connection(cloud_topic, cloud_type, typestore=store)
        odometry = writer.add_connection(odom_topic, odom_type, typestore=store)
        for index, (x, y, yaw) in enumerate(progress_bar(trajectory, desc=f"simulate {path.name}",
                                                         unit="scan", enabled=progress)):
            pose = pose_matrix(np.array([x, y, sensor.mount_height_m]), quaternion_from_yaw(yaw))
            points = cast(scene, sensor, pose, rng)
            stamp_ns = int(round((start_s + index / rate_hz) * 1e9))
            stamp = types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9,
                                                         nanosec=stamp_ns % 10**9)
            header = types["std_msgs/msg/Header"](stamp=stamp, frame_id="lidar")
            cloud = types[cloud_type](
                header=header, height=1, width=len(points), fields=fields, is_bigendian=False,
                point_step=12, row_step=12 * len(points),
                data=np.frombuffer(points.astype("<f4").tobytes(), np.uint8), is_dense=True)
            q = quaternion_from_yaw(yaw)
            odom = types[odom_type](
                header=types["std_msgs/msg/Header"](stamp=stamp, frame_id="map"),
                child_frame_id="lidar",
                pose=types["geometry_msgs/msg/PoseWithCovariance"](
                    pose=types["geometry_msgs/msg/Pose"](
                        position=types["geometry_msgs/msg/Point"](x=x, y=y,
                                                                  z=sensor.mount_height_m),
                        orientation=types["geometry_msgs/msg/Quaternion"](
                            x=q[0], y=q[1], z=q[2], w=q[3])),
                    covariance=zero36),
                twist=types["geometry_msgs/msg/TwistWithCovariance"](
                    twist=types["geometry_msgs/msg/Twist"](
                        linear=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                        angular=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
                    covariance=zero36))
            writer.write(odometry, stamp_ns, store.serialize_cdr(odom, odom_type))
            writer.write(clouds, stamp_ns, store.serialize_cdr(cloud, cloud_type))
