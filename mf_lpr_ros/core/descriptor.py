"""BEV occupancy descriptors (docs/METHOD.md section 1).

Axis convention, used everywhere in the package: rows index y, columns index x, both
increasing with the coordinate; the point (x, y) falls in cell
(row, col) = (floor(y / v) + D/2, floor(x / v) + D/2), so the sensor sits at the corner shared
by cells (D/2 - 1 .. D/2) and cell (D/2, D/2) holds the first cell of positive x and y.
Rotations turn the image about that corner, counter-clockwise for positive angles.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from mf_lpr_ros.errors import InvalidCloudError
from mf_lpr_ros.params import DescriptorParams

MAX_DENSE_VOXEL_CELLS = 1 << 24


@lru_cache(maxsize=16)
def _footprint(size: int, disc: bool, field_of_view_deg: float, heading_deg: float
               ) -> np.ndarray:
    centres = np.arange(size) - size / 2 + 0.5
    x, y = np.meshgrid(centres, centres)
    inside = np.hypot(x, y) <= size / 2 if disc else np.ones((size, size), dtype=bool)
    if field_of_view_deg < 360:
        off_axis = (np.degrees(np.arctan2(y, x)) - heading_deg + 180.0) % 360.0 - 180.0
        inside &= np.abs(off_axis) <= field_of_view_deg / 2
    inside.setflags(write=False)
    return inside


def footprint(params: DescriptorParams) -> np.ndarray | None:
    """The cells a descriptor covers (D x D bool, read-only): None for the whole square window;
    the inscribed disc for crop "disc"; within the field of view when it is under 360 deg."""
    if params.crop == "square" and params.field_of_view_deg >= 360:
        return None
    return _footprint(params.size, params.crop == "disc", params.field_of_view_deg,
                      params.heading_deg)


# A sensor whose returns span less than this many degrees of azimuth is a narrow (forward-
# looking) one: views of a place from other headings share no ground.
FULL_CIRCLE_BELOW_DEG = 300.0
_DIRECTION_BINS = 180


def largest_empty_run(seen: np.ndarray) -> tuple[int, int]:
    """(length, last index) of the longest circular run of False in seen (azimuth bins)."""
    if seen.all():
        return 0, 0
    doubled = np.concatenate([~seen, ~seen]).astype(np.int64)
    # Run lengths: cumulative count since the last seen bin.
    resets = np.maximum.accumulate(np.where(doubled == 0, np.arange(len(doubled)), -1))
    runs = np.arange(len(doubled)) - resets
    end = int(np.argmax(runs))
    return min(int(runs[end]), len(seen)), end


@lru_cache(maxsize=4)
def _direction_bins(size: int) -> np.ndarray:
    """Each cell centre's 2-degree azimuth bin from the sensor at corner (size/2, size/2)."""
    centre = np.arange(size) - size / 2 + 0.5
    y, x = np.meshgrid(centre, centre, indexing="ij")
    return ((np.arctan2(y, x) + np.pi) / (2 * np.pi) * _DIRECTION_BINS).astype(int) \
        % _DIRECTION_BINS


def observed_cells(occupancy: np.ndarray, spread_bins: int = 2) -> np.ndarray:
    """The directions a narrow sensor's scan has seen: every cell of each 2-degree direction
    within spread_bins of one holding an occupied cell; a direction it did not see says nothing
    (not free space). A scan whose directions span FULL_CIRCLE_BELOW_DEG or more saw all round
    (a street with no obstacle in the window was seen free): all its cells count."""
    bins = _direction_bins(occupancy.shape[0])
    seen = np.zeros(_DIRECTION_BINS, dtype=bool)
    seen[np.unique(bins[occupancy])] = True
    gap, _ = largest_empty_run(seen)
    if (_DIRECTION_BINS - gap) * 360.0 / _DIRECTION_BINS >= FULL_CIRCLE_BELOW_DEG:
        return np.ones(occupancy.shape, dtype=bool)
    spread = seen.copy()
    for step in range(1, spread_bins + 1):
        spread |= np.roll(seen, step) | np.roll(seen, -step)
    return spread[bins]


def turns_with_sensor(params: DescriptorParams) -> bool:
    """Whether the footprint changes when the sensor turns (a limited field of view)."""
    return params.field_of_view_deg < 360


def rows_where(points: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """points[keep] for a boolean keep over the rows of points (N, C): numpy indexes a 2-D
    array by a boolean mask row by row, np.compress in one pass (a submap's 34k points: 0.40
    -> 0.08 ms, the same array)."""
    if len(keep) != len(points):
        # np.compress would cut the rows short where boolean indexing refuses.
        raise ValueError(f"a mask of {len(keep)} entries for {len(points)} rows")
    return np.compress(keep, points, axis=0)


def finite_rows(points: np.ndarray) -> np.ndarray:
    """Whether each row of points (N, 3+) has a finite x, y and z: tested per coordinate, not
    reduced over rows of three, which numpy does slowly (the same mask)."""
    return np.isfinite(points[:, 0]) & np.isfinite(points[:, 1]) & np.isfinite(points[:, 2])


def filter_points(points: np.ndarray, params: DescriptorParams) -> np.ndarray:
    """Finite points inside the height band, range and window (square or disc), as (N, 3)
    float64: the transposed view of one row per axis, so the tests here and the binning of
    each axis run along contiguous rows instead of across rows of three."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise InvalidCloudError(f"points must have shape (N, 3+), got {points.shape}")
    xyz = np.array(points[:, :3].T, dtype=np.float64, order="C")
    x, y, z = xyz
    half = params.extent_m / 2
    # A NaN or infinite x or y fails the window test itself; only z needs its own.
    keep = (np.abs(x) < half) & (np.abs(y) < half) & np.isfinite(z)
    if params.z_min is not None:
        keep &= z >= params.z_min
    if params.z_max is not None:
        keep &= z <= params.z_max
    if params.max_range is not None or params.crop == "disc":
        # Squared ranges: a submap's hundred thousand points pay for no square root.
        squared_range = x * x + y * y
        if params.max_range is not None:
            keep &= squared_range <= params.max_range ** 2
        if params.crop == "disc":
            keep &= squared_range < half * half
    return np.compress(keep, xyz, axis=1).T


def height_density(points: np.ndarray, params: DescriptorParams) -> np.ndarray:
    """Height density map (D, D): occupied voxels (or raw points) per column."""
    size, voxel = params.size, params.voxel_size
    x, y, z = filter_points(points, params).T
    if len(x) == 0:
        raise InvalidCloudError("no finite point lies inside the descriptor window and height band")
    cols = np.floor(x / voxel).astype(np.int64) + size // 2
    rows = np.floor(y / voxel).astype(np.int64) + size // 2
    np.clip(cols, 0, size - 1, out=cols)
    np.clip(rows, 0, size - 1, out=rows)
    column = rows * size + cols
    if params.density_mode == "points":
        counts = np.bincount(column, minlength=size * size)
        return counts.reshape(size, size).astype(np.float32)
    levels = np.floor(z / voxel).astype(np.int64)
    levels -= levels.min()
    n_levels = int(levels.max()) + 1
    voxels = column * n_levels + levels
    if size * size * n_levels <= MAX_DENSE_VOXEL_CELLS:
        # The occupied voxels, in order, marked on a dense grid: cheaper than sorting them.
        occupied = np.zeros(size * size * n_levels, dtype=bool)
        occupied[voxels] = True
        voxels = np.flatnonzero(occupied)
    else:
        voxels = np.unique(voxels)
    # Counted by the columns of the occupied voxels (a submap's 60 levels: 4x faster than
    # summing every voxel of every column).
    counts = np.bincount(voxels // n_levels, minlength=size * size)
    return counts.reshape(size, size).astype(np.float32)


def occupancy_from_density(density: np.ndarray, params: DescriptorParams) -> np.ndarray:
    """Occupied cells (bool, D x D): density strictly above the threshold d, inside the
    footprint."""
    occupied = np.asarray(density) > params.density_threshold
    covered = footprint(params)
    return occupied if covered is None else occupied & covered


def cap_patches(occupancy: np.ndarray, params: DescriptorParams, seed: int) -> np.ndarray:
    """Keep at most patch_cap occupied cells per patch, chosen at random (seeded per scan)."""
    size, patch, cap = params.size, params.patch_size, params.patch_cap
    n_patches = size // patch
    priority = np.random.default_rng(seed).random((size, size))
    priority[~occupancy] = np.inf
    per_patch = priority.reshape(n_patches, patch, n_patches, patch).transpose(0, 2, 1, 3)
    per_patch = per_patch.reshape(n_patches, n_patches, patch * patch)
    rank = np.argsort(np.argsort(per_patch, axis=-1, kind="stable"), axis=-1, kind="stable")
    keep = (rank < cap).reshape(n_patches, n_patches, patch, patch).transpose(0, 2, 1, 3)
    return occupancy & keep.reshape(size, size)


def scan_seed(params: DescriptorParams, seed_key: int) -> int:
    """Seed of the patch cap of one scan, so a map rebuilt from the same scans is identical."""
    return (params.seed * 1_000_003 + seed_key) % (1 << 63)


def stamp_seed_key(stamp: float) -> int:
    """A scan's seed key from its stamp (microseconds): the same scan gets the same patch cap
    whether it is read from a folder, a bag or a live topic, and whatever was dropped before it."""
    return int(round(stamp * 1e6))


def describe_points(points: np.ndarray, params: DescriptorParams, *, reference: bool = False,
                    seed_key: int = 0) -> np.ndarray:
    """The high-resolution occupancy (bool, D x D) of one scan's points (sensor frame)."""
    occupancy = occupancy_from_density(height_density(points, params), params)
    return _finish(occupancy, params, reference, seed_key)


def describe_density_image(density: np.ndarray, pixel_size: float, params: DescriptorParams, *,
                           reference: bool = False, seed_key: int = 0) -> np.ndarray:
    """The occupancy of a ready height-density image already in the package's axis convention.

    density: (H, W) occupied-voxel counts per column, rows = y, columns = x, the sensor at the
    corner before pixel (H // 2, W // 2); resampled (nearest) when pixel_size differs from v.
    """
    density = np.asarray(density, dtype=np.float32)
    if density.ndim != 2:
        raise InvalidCloudError(f"a density image must be 2-D, got shape {density.shape}")
    if not np.isfinite(density).all():
        raise InvalidCloudError("the density image holds non-finite values")
    size = params.size
    centres = (np.arange(size) - size // 2 + 0.5) * params.voxel_size
    src_rows = np.floor(centres / pixel_size).astype(np.int64) + density.shape[0] // 2
    src_cols = np.floor(centres / pixel_size).astype(np.int64) + density.shape[1] // 2
    inside_rows = (src_rows >= 0) & (src_rows < density.shape[0])
    inside_cols = (src_cols >= 0) & (src_cols < density.shape[1])
    resampled = np.zeros((size, size), dtype=np.float32)
    resampled[np.ix_(inside_rows, inside_cols)] = density[np.ix_(src_rows[inside_rows],
                                                                 src_cols[inside_cols])]
    occupancy = occupancy_from_density(resampled, params)
    if not occupancy.any():
        raise InvalidCloudError("the density image has no occupied cell")
    return _finish(occupancy, params, reference, seed_key)


def _finish(occupancy: np.ndarray, params: DescriptorParams, reference: bool,
            seed_key: int) -> np.ndarray:
    if reference:
        occupancy = cap_patches(occupancy, params, scan_seed(params, seed_key))
    return occupancy


def weighted(occupancy: np.ndarray, unoccupied_weight: float,
             covered: np.ndarray | None = None) -> np.ndarray:
    """Occupancy as matched-filter weights (float32): 1 occupied, w unoccupied, and 0 outside
    the covered cells (a footprint; None covers all)."""
    # Two 0/1 images, one scaled by w and added: ~6x faster than np.where, and exact for any
    # w (each cell adds w or 1 to a zero), where w + (1 - w) * occupancy is not.
    if covered is None:
        occupied, empty = occupancy, ~occupancy
    else:
        occupied, empty = occupancy & covered, covered & ~occupancy
    weights = occupied.astype(np.float32)
    empty_weights = empty.astype(np.float32)
    empty_weights *= np.float32(unoccupied_weight)
    weights += empty_weights
    return weights


def pool(images: np.ndarray, factor: int) -> np.ndarray:
    """Average pooling by factor over the last two axes."""
    if factor == 1:
        return images.astype(np.float32, copy=False)
    # A sum of factor^2 strided views: a mean over two axes of the blocks reduces ~10x slower.
    total = np.zeros(images.shape[:-2] + (images.shape[-2] // factor, images.shape[-1] // factor),
                     dtype=np.float32)
    for i in range(factor):
        for j in range(factor):
            total += images[..., i::factor, j::factor]
    return total * np.float32(1.0 / factor ** 2)


def pooled_weights(occupancy: np.ndarray, unoccupied_weight: float, factor: int,
                   covered: np.ndarray | None = None) -> np.ndarray:
    """pool(weighted(occupancy, w, covered), factor), from occupied counts per block: ~10x
    faster."""
    if factor == 1:
        return weighted(occupancy, unoccupied_weight, covered)
    if covered is not None:
        occupancy = occupancy & covered
    return _pooled_from_counts(_block_counts(occupancy, factor), unoccupied_weight, factor,
                               covered)


def _pooled_from_counts(counts: np.ndarray, unoccupied_weight: float, factor: int,
                        covered: np.ndarray | None) -> np.ndarray:
    """Pooled weights from the occupied (and covered) cells counted per block."""
    scale = np.float32((1.0 - unoccupied_weight) / factor ** 2)
    if covered is None:
        return counts.astype(np.float32) * scale + np.float32(unoccupied_weight)
    empty = _block_counts(covered, factor).astype(np.float32) * np.float32(
        unoccupied_weight / factor ** 2)
    return counts.astype(np.float32) * scale + empty


class TurnedPooling:
    """pooled_weights(rotate_occupancy(occupancy, angles_deg), w, factor, covered) for one set
    of angles and a footprint that does not turn with the query, from the occupied cells alone.

    Under nearest-neighbour rotation each cell is the source of about one output cell per
    angle. The table lists, by source cell, the low-resolution blocks (over every angle) that
    its copies land in, so a query's counts per block are one bincount over the entries of its
    ~10 % occupied cells instead of a gather of every cell at every angle: the same numbers,
    ~2.5x faster at 72 angles.
    """

    def __init__(self, size: int, angles_deg: np.ndarray, factor: int,
                 unoccupied_weight: float, covered: np.ndarray | None) -> None:
        self.n_angles, self.low = len(angles_deg), size // factor
        self.factor, self.unoccupied_weight, self.covered = factor, unoccupied_weight, covered
        sources = _rotation_sources(size, rotation_key(angles_deg))
        rows, cols = np.divmod(np.arange(size * size), size)
        block = (rows // factor) * self.low + cols // factor
        landed = sources < size * size
        if covered is not None:
            landed &= covered.ravel()[None, :]
        angle, cell = np.nonzero(landed)
        source = sources[angle, cell]
        by_source = np.argsort(source, kind="stable")
        self._blocks = (angle * self.low ** 2 + block[cell])[by_source].astype(np.int32)
        self._starts = np.searchsorted(source[by_source], np.arange(size * size + 1))

    def __call__(self, occupancy: np.ndarray) -> np.ndarray:
        """(A, low, low) float32 pooled weights of occupancy (D x D bool) at every angle."""
        occupied = np.flatnonzero(occupancy)
        first = self._starts[occupied]
        lengths = self._starts[occupied + 1] - first
        # Every entry of every occupied cell: its run [first, first + length) laid end to end.
        entries = np.repeat(first - np.cumsum(lengths) + lengths, lengths) + np.arange(
            int(lengths.sum()))
        counts = np.bincount(self._blocks[entries], minlength=self.n_angles * self.low ** 2)
        return _pooled_from_counts(counts.reshape(self.n_angles, self.low, self.low),
                                   self.unoccupied_weight, self.factor, self.covered)


def _block_counts(cells: np.ndarray, factor: int) -> np.ndarray:
    """True cells per factor x factor block over the last two axes (uint16)."""
    *lead, rows, cols = cells.shape
    blocks = np.ascontiguousarray(cells).view(np.uint8).reshape(
        *lead, rows // factor, factor, cols // factor, factor)
    counts = np.zeros((*lead, rows // factor, cols // factor), dtype=np.uint16)
    for i in range(factor):
        for j in range(factor):
            counts += blocks[..., i, :, j]
    return counts


# A search prepares one set per global angle and the global set (73 at a 5-degree step); a
# cache smaller than that would evict and recompute tables on every query.
@lru_cache(maxsize=256)
def _rotation_sources(size: int, angles_deg: tuple[float, ...]) -> np.ndarray:
    """For each angle, the flat source cell of every output cell (A, size^2) int32; size^2, one
    past the last cell, for a source outside the window."""
    centres = np.arange(size) - size / 2 + 0.5
    # x along columns, y along rows, broadcast rather than laid out, and each full-size step
    # in place (a set made for one call, a place's similarity, is on the query's path).
    x, y = centres[None, None, :], centres[None, :, None]
    theta = np.deg2rad(np.asarray(angles_deg))[:, None, None]
    cos, sin = np.cos(theta), np.sin(theta)
    shape = (len(angles_deg), size, size)

    def source_cells(along_x: np.ndarray, along_y: np.ndarray) -> np.ndarray:
        total = np.add(along_x * x, along_y * y, out=np.empty(shape))
        total += size / 2
        return np.floor(total, out=total).astype(np.int32)

    # Inverse mapping: the output cell at p takes the input at R(-theta) p.
    cols, rows = source_cells(cos, sin), source_cells(-sin, cos)
    # Read as unsigned, a cell below 0 is past size: one comparison a bound.
    inside = cols.view(np.uint32) < size
    inside &= rows.view(np.uint32) < size
    rows *= size
    rows += cols
    rows[~inside] = size * size
    return rows.reshape(len(angles_deg), -1)


def quarter_turn_roots(size: int, angles_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each angle of the set, an angle of the set (its root, by index) and a number of
    quarter turns k: rotating by the angle is np.rot90(rotated by the root, -k), cell for cell.
    An angle that is no such turn of an earlier root is its own root (k = 0). So a search that
    turns a query to a whole circle of headings turns it to a quarter of them and lays the
    rest out by rot90. The rotation tables themselves are compared, not the angles: in
    floating point some cells of 45-degree multiples land across a cell edge from where the
    quarter turn of the root puts them."""
    angles = np.atleast_1d(np.asarray(angles_deg, dtype=np.float64))
    sources = _rotation_sources(size, rotation_key(angles)).reshape(-1, size, size)
    index = {round(float(angle) % 360.0, 9): i for i, angle in enumerate(angles)}
    roots, turns = np.arange(len(angles)), np.zeros(len(angles), dtype=np.int64)
    for heading, angle in enumerate(angles):
        for quarter_turns in (1, 2, 3):
            root = index.get(round(float(angle - 90.0 * quarter_turns) % 360.0, 9))
            if (root is not None and root < heading and turns[root] == 0
                    and np.array_equal(sources[heading],
                                       np.rot90(sources[root], -quarter_turns))):
                roots[heading], turns[heading] = root, quarter_turns
                break
    return roots, turns


def rotation_key(angles_deg: np.ndarray) -> tuple[float, ...]:
    """The key of a set of angles in the cache of rotation tables."""
    return tuple(float(a) for a in np.atleast_1d(angles_deg))


def prepare_rotations(size: int, angle_sets: list[np.ndarray]) -> frozenset[tuple[float, ...]]:
    """Compute the rotation tables of these angle sets now (they are cached, at most 256 sets):
    a long-running search then allocates nothing new for rotations. Returns the sets' keys
    (rotation_key)."""
    keys = frozenset(rotation_key(angles) for angles in angle_sets)
    for key in keys:
        _rotation_sources(size, key)
    return keys


def rotate_occupancy(occupancy: np.ndarray, angles_deg: np.ndarray,
                     only: np.ndarray | None = None, *, cached: bool = True) -> np.ndarray:
    """Occupancy rotated counter-clockwise about the sensor by each angle: (A, D, D) bool; with
    only (indices into angles_deg), by those angles alone (the set's tables are reused).
    cached False: the set's table is made for this call alone (a set used once would take a
    place in the cache, ~0.4 MB, and push out the search's own).

    Nearest-neighbour; cells whose source falls outside the window become unoccupied.
    """
    size = occupancy.shape[0]
    # One unoccupied cell past the last: where every source outside the window reads.
    cells = np.zeros(size * size + 1, dtype=bool)
    cells[:-1] = occupancy.ravel()
    if cached:
        sources = _rotation_sources(size, rotation_key(angles_deg))
        sources = sources if only is None else sources[only]
    else:
        # Made for this call alone: only the angles it turns to (~0.4 ms an angle).
        wanted = np.atleast_1d(angles_deg) if only is None else np.atleast_1d(angles_deg)[only]
        sources = _rotation_sources.__wrapped__(size, rotation_key(wanted))
    return np.take(cells, sources).reshape(-1, size, size)


def auto_voxel_size(point_clouds: list[np.ndarray]) -> float:
    """The paper's rule of thumb on these scans: voxel_size_for_density of their mean occupied
    1 m voxels."""
    if not point_clouds:
        raise InvalidCloudError("auto voxel size needs at least one scan")
    return voxel_size_for_density(float(np.mean([occupied_unit_voxels(c)
                                                 for c in point_clouds])))


def one_point_per_voxel(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """The first point of each occupied voxel_m voxel, in the points' order."""
    if not len(points):
        return points
    # One row per axis: the bounds are then reductions along rows, not over rows of three.
    keys = np.floor(np.ascontiguousarray(np.asarray(points)[:, :3].T) / voxel_m).astype(np.int64)
    keys -= keys.min(axis=1, keepdims=True)
    span = keys.max(axis=1) + 1
    flat = (keys[0] * span[1] + keys[1]) * span[2] + keys[2]
    _, first = np.unique(flat, return_index=True)
    return points[np.sort(first)]


def occupied_unit_voxels(cloud: np.ndarray) -> int:
    """Occupied 1 m voxels of one scan (finite points only)."""
    xyz = np.asarray(cloud)[:, :3]
    xyz = rows_where(xyz, finite_rows(xyz))
    return len(np.unique(np.floor(xyz).astype(np.int64), axis=0))


def voxel_size_for_density(mean_occupied: float) -> float:
    """The paper's rule of thumb: voxel size falling linearly with the occupied 1 m voxels per
    scan, through its three points (1360 -> 0.3, 876 -> 0.75, 275 -> 1.3 m); held at the end
    values outside them (a line continued past 1360 would give dense scans no voxel at all;
    KITTI's 64-beam scans occupy ~4500)."""
    return float(np.interp(float(mean_occupied), _PAPER_OCCUPIED_VOXELS, _PAPER_VOXEL_SIZES_M))


_PAPER_OCCUPIED_VOXELS = np.array([275.0, 876.0, 1360.0])
_PAPER_VOXEL_SIZES_M = np.array([1.3, 0.75, 0.3])
