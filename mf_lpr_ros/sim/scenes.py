"""Procedural scenes for the simulator: urban blocks and forest trails built from cylinders, boxes
turned about z and spheres on a ground plane at z = 0, seeded."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np


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
    return Scene("urban", np.asarray(cylinders), np.asarray(boxes), np.asarray(spheres).reshape(-1,
                                                                                                4),
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
