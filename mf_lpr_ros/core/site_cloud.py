"""One cloud for a whole site, shared by every reference that lies in it.

A grid rendered from a global cloud puts references 2 m apart, and ICP needs the cloud a
match's query may overlap: the descriptor window widened by max_shift_m, ~72 m across. Kept per
reference, each point would be stored once for every reference that sees it, ~1,300 times at
2 m (89 references of the Avia site: 34 MB; a square kilometre: ~200 GB). Kept once, the map
holds the site's cloud thinned to the descriptor voxel, sorted by square tiles, and a
reference's cloud is cut from it when a match is verified: a few tiles, ~6 ms for the 57k
points of a reference in a simulated town.

Points are in the map frame, sorted by tile (column by column, row by row within a column:
one column's tiles are one run of points), with each non-empty tile's key and the offset of
its first point; half_m is the half-width of the square cut around a reference.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mf_lpr_ros.core.descriptor import finite_rows, rows_where

# Keys are (column + _KEY_OFFSET) * _KEY_SPAN + (row + _KEY_OFFSET): tile indices within
# +-2^20 (16,000 km at 16 m tiles) stay distinct and sort column by column.
_KEY_OFFSET = 1 << 20
_KEY_SPAN = 1 << 21
DEFAULT_TILE_M = 16.0


@dataclass(frozen=True)
class SiteCloud:
    """A site's points sorted by tile (see the module doc).

    points: (P, 3) float32, map frame. tile_keys: (T,) int64, increasing. tile_offsets:
    (T + 1,) int64, tile k's points are points[tile_offsets[k]:tile_offsets[k + 1]].
    tile_m: tile side. half_m: half-width of the square cut around a reference.
    """

    points: np.ndarray
    tile_keys: np.ndarray
    tile_offsets: np.ndarray
    tile_m: float
    half_m: float

    @classmethod
    def from_points(cls, points: np.ndarray, half_m: float,
                    tile_m: float = DEFAULT_TILE_M) -> "SiteCloud":
        """The site cloud of (P, >=3) map-frame points (only x, y, z are kept)."""
        if not (tile_m > 0 and half_m > 0):
            raise ValueError(f"tile_m and half_m must be > 0, got {tile_m} and {half_m}")
        points = np.asarray(points, dtype=np.float32)[:, :3]
        points = rows_where(points, finite_rows(points))
        keys = _tile_keys(points, tile_m)
        order = np.argsort(keys, kind="stable")
        keys = keys[order]
        tile_keys, starts = np.unique(keys, return_index=True)
        offsets = np.append(starts, len(keys)).astype(np.int64)
        return cls(np.ascontiguousarray(points[order]), tile_keys.astype(np.int64), offsets,
                   float(tile_m), float(half_m))

    def check(self) -> str | None:
        """What is inconsistent in the arrays (None: nothing), as a map file's loader asks."""
        if self.points.ndim != 2 or self.points.shape[1] != 3:
            return "site_points must be (P, 3)"
        if len(self.tile_offsets) != len(self.tile_keys) + 1:
            return "site_tile_offsets must hold one entry more than site_tile_keys"
        if len(self.tile_offsets) and (self.tile_offsets[0] != 0
                                       or self.tile_offsets[-1] != len(self.points)
                                       or bool((np.diff(self.tile_offsets) <= 0).any())):
            return ("site_tile_offsets must run from 0 to the number of site points, "
                    "increasing")
        if bool((np.diff(self.tile_keys) <= 0).any()):
            return "site_tile_keys must increase"
        if not (self.tile_m > 0 and self.half_m > 0):
            return "the site cloud's tile_m and half_m must be > 0"
        return None

    def around(self, pose: np.ndarray) -> np.ndarray:
        """The points within half_m of the pose's position in x and y, in the pose's frame."""
        origin = np.asarray(pose[:3, 3], dtype=np.float64)
        low = np.floor((origin[:2] - self.half_m) / self.tile_m).astype(np.int64)
        high = np.floor((origin[:2] + self.half_m) / self.tile_m).astype(np.int64)
        # One column of tiles is one run of keys, so one slice of points.
        columns = (np.arange(low[0], high[0] + 1) + _KEY_OFFSET) * _KEY_SPAN
        first = np.searchsorted(self.tile_keys, columns + low[1] + _KEY_OFFSET, side="left")
        last = np.searchsorted(self.tile_keys, columns + high[1] + _KEY_OFFSET, side="right")
        pieces = [self.points[self.tile_offsets[start]:self.tile_offsets[stop]]
                  for start, stop in zip(first, last) if stop > start]
        if not pieces:
            return np.zeros((0, 3), np.float32)
        near = np.concatenate(pieces).astype(np.float64) - origin
        near = near[(np.abs(near[:, 0]) < self.half_m) & (np.abs(near[:, 1]) < self.half_m)]
        return (near @ np.asarray(pose[:3, :3], dtype=np.float64)).astype(np.float32)

    @property
    def nbytes(self) -> int:
        return self.points.nbytes + self.tile_keys.nbytes + self.tile_offsets.nbytes


def _tile_keys(points: np.ndarray, tile_m: float) -> np.ndarray:
    tiles = np.floor(points[:, :2].astype(np.float64) / tile_m).astype(np.int64)
    if len(tiles) and int(np.abs(tiles).max()) >= _KEY_OFFSET:
        raise ValueError(f"the site cloud reaches {math.ldexp(tile_m, 20) / 1e3:.0f} km from "
                         "the map origin, beyond what its tile keys hold")
    return (tiles[:, 0] + _KEY_OFFSET) * _KEY_SPAN + tiles[:, 1] + _KEY_OFFSET
