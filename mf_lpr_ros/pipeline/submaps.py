"""Offline submaps: a sequence read through core.submap.Submap, as the live nodes feed it.

with_submaps(sequence, window) gives a sequence whose scans carry their submap (the scan and the
earlier scans within the window, in its sensor frame) instead of the single scan. The source's
poses serve as odometry. To make the submap of a scan, the scans of its window are read too,
in order, exactly as a live node would have seen them; scans without a pose, density images and
sources without poses stay single scans.
"""

from __future__ import annotations

import dataclasses
from typing import Iterator

import numpy as np

from mf_lpr_ros.core.submap import Submap, SubmapWindow
from mf_lpr_ros.datasets import Scan, Sequence


class SubmapSequence(Sequence):
    """base's scans, each replaced by its submap (see the module doc)."""

    def __init__(self, base: Sequence, window: SubmapWindow) -> None:
        self.base = base
        self.window = window
        self.name = base.name
        self.stamps = base.stamps
        self.poses = base.poses
        self.frame_id = getattr(base, "frame_id", "")
        self.window_starts = _window_starts(base.stamps, base.poses, window)

    def _read(self, indices: np.ndarray) -> Iterator[Scan]:
        wanted = set(indices.tolist())
        to_read = np.unique(np.concatenate([
            np.arange(self.window_starts[i], i + 1) for i in indices])) if len(indices) else indices
        submap = Submap(self.window)
        previous = None
        for scan in self.base.iter_scans(to_read):
            if previous is not None and scan.index != previous + 1:
                submap.reset()
            previous = scan.index
            if scan.points is None:
                if scan.index in wanted:
                    yield scan
                continue
            submap.add(scan.stamp, scan.points, scan.pose)
            if scan.index not in wanted:
                continue
            if not len(submap):
                yield scan
                continue
            yield dataclasses.replace(scan, points=submap.points_at(scan.stamp).points)


def with_submaps(sequence: Sequence, window: SubmapWindow | None) -> Sequence:
    """sequence read as submaps when the window is active and the sequence has poses; else the
    sequence itself."""
    if window is None or not window.active or sequence.poses is None:
        return sequence
    return SubmapSequence(sequence, window)


def _window_starts(stamps: np.ndarray, poses: np.ndarray, window: SubmapWindow) -> np.ndarray:
    """For each scan, the first scan of its window: the earliest j such that every scan from j
    to it has a pose and j lies within the window's travel, count and age."""
    count = len(stamps)
    posed = np.isfinite(poses).all(axis=(1, 2))
    steps = np.zeros(count)
    if count > 1:
        steps[1:] = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    steps[~np.isfinite(steps)] = 0.0
    travelled = np.cumsum(steps)
    # A scan without a pose breaks the chain: no window reaches back across it.
    run_start = np.maximum.accumulate(np.where(~posed, np.arange(count) + 1, 0))
    starts = np.empty(count, dtype=np.int64)
    for index in range(count):
        first = max(int(run_start[index]), index - window.max_scans + 1, 0)
        first = max(first, int(np.searchsorted(travelled, travelled[index] - window.window_m,
                                               "left")))
        first = max(first, int(np.searchsorted(stamps, stamps[index] - window.max_age_s, "left")))
        starts[index] = min(first, index)
    return starts
