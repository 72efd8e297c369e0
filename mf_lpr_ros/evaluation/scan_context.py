"""Scan Context (Kim and Kim, IROS 2018), the baseline we compare against, from the paper.

A scan becomes a rings x sectors polar grid around the sensor holding the highest point in each
bin (0 where empty). Retrieval: the ring key (fraction of non-empty sectors per ring, rotation
invariant) picks candidates by nearest neighbours; each candidate's distance is the smallest,
over column shifts, mean cosine distance between corresponding non-empty sector columns. The
best shift gives the relative yaw; Scan Context gives no translation, so the pose it implies is
the reference's position with the corrected heading.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mf_lpr_ros.core.descriptor import finite_rows, rows_where
from mf_lpr_ros.core.pose import wrap_angle


@dataclass(frozen=True)
class ScanContextParams:
    """The paper's values: 20 rings, 60 sectors, 80 m, 10 ring-key candidates, accept < 0.2.

    height_offset lifts heights so the ground (sensor height below 0) stays positive.
    accept_distance: a match is a loop closure below this distance (the paper's 0.2).
    """

    n_rings: int = 20
    n_sectors: int = 60
    max_range: float = 80.0
    n_candidates: int = 10
    height_offset: float = 2.0
    accept_distance: float = 0.2


class ScanContextIndex:
    """Scan Context descriptors of a map's references, searched for each query."""

    def __init__(self, params: ScanContextParams = ScanContextParams()) -> None:
        self.params = params
        self._contexts = np.zeros((0, params.n_rings, params.n_sectors), dtype=np.float32)
        self._ring_keys = np.zeros((0, params.n_rings), dtype=np.float32)

    def __len__(self) -> int:
        return len(self._contexts)

    def describe(self, points: np.ndarray) -> np.ndarray:
        """The (rings, sectors) context of points (N, 3+) in the sensor frame."""
        p = self.params
        xyz = np.asarray(points)[:, :3].astype(np.float64)
        xyz = rows_where(xyz, finite_rows(xyz))
        radius = np.hypot(xyz[:, 0], xyz[:, 1])
        keep = (radius < p.max_range) & (radius > 0)
        xyz, radius = rows_where(xyz, keep), radius[keep]
        ring = np.minimum((radius / p.max_range * p.n_rings).astype(np.int64), p.n_rings - 1)
        angle = np.mod(np.arctan2(xyz[:, 1], xyz[:, 0]), 2 * np.pi)
        sector = np.minimum((angle / (2 * np.pi) * p.n_sectors).astype(np.int64),
                            p.n_sectors - 1)
        context = np.zeros(p.n_rings * p.n_sectors)
        np.maximum.at(context, ring * p.n_sectors + sector,
                      np.maximum(xyz[:, 2] + p.height_offset, 0.0))
        return context.reshape(p.n_rings, p.n_sectors).astype(np.float32)

    def append(self, points: np.ndarray) -> None:
        self.append_context(self.describe(points))

    def append_context(self, context: np.ndarray) -> None:
        self._contexts = np.concatenate([self._contexts, context[None]])
        self._ring_keys = np.concatenate([self._ring_keys, _ring_key(context)[None]])

    def query(self, points: np.ndarray, n_active: int | None = None
              ) -> tuple[int, float, float, np.ndarray]:
        """(reference index, yaw of the query in the reference's frame (rad), distance in
        [0, 1], candidates best first) over references [0, n_active)."""
        return self.query_context(self.describe(points), n_active)

    def query_context(self, context: np.ndarray, n_active: int | None = None
                      ) -> tuple[int, float, float, np.ndarray]:
        """query, for a context already described."""
        n_refs = len(self) if n_active is None else min(n_active, len(self))
        if n_refs == 0:
            raise ValueError("Scan Context: no reference to search")
        key_distance = np.linalg.norm(self._ring_keys[:n_refs] - _ring_key(context), axis=1)
        n_candidates = min(self.params.n_candidates, n_refs)
        candidates = np.argpartition(key_distance, n_candidates - 1)[:n_candidates]
        distances, shifts = _column_distances(context, self._contexts[candidates])
        order = np.argsort(distances, kind="stable")
        best = int(order[0])
        # Query column c + s lines up with reference column c: what the reference sees at
        # angle phi the query sees at phi - yaw, so the query is turned by -s sectors.
        yaw = float(wrap_angle(-2 * np.pi * shifts[best] / self.params.n_sectors))
        return int(candidates[best]), yaw, float(distances[best]), candidates[order]


def _ring_key(context: np.ndarray) -> np.ndarray:
    return (context > 0).mean(axis=1).astype(np.float32)


def _column_distances(query: np.ndarray, references: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Best (over the query's column shifts) mean cosine distance to each reference, and the
    shift reaching it."""
    n_sectors = query.shape[1]
    shifted = np.stack([np.roll(query, -s, axis=1) for s in range(n_sectors)])  # (S, R, C)
    dots = np.einsum("src,nrc->nsc", shifted, references)
    norms = (np.linalg.norm(shifted, axis=1)[None] * np.linalg.norm(references, axis=1)[:, None])
    valid = norms > 0
    cosine = np.where(valid, dots / np.where(valid, norms, 1.0), 0.0)
    counted = np.maximum(valid.sum(axis=2), 1)
    distance = 1.0 - cosine.sum(axis=2) / counted                                  # (n, S)
    shifts = distance.argmin(axis=1)
    return distance[np.arange(len(references)), shifts], shifts
