"""Submaps: a scan together with the scans of the last few metres of travel, moved into its
sensor frame by odometry (docs/METHOD.md section 1, "Submaps").

A sparse or narrow sensor (a Livox Mid-360's few thousand points, an Avia's 70-degree cone)
sees too little of a place in one scan for its occupancy image to be distinctive; STD, BTC and
MapClosures all match accumulated local maps for that reason. Submap keeps a ring buffer of
recent scans, each voxel-thinned and stored in the odometry (world) frame, and returns, for any
kept scan, the union of that scan and the earlier ones within the window, in that scan's sensor
frame. The window is bounded by travel (window_m), by a count and by an age, so memory and time
stay flat on long runs and a robot standing still does not pile up copies of one view.

Every path that describes a scan uses this one class: the live nodes (live.localiser,
live.map_builder) feed it every scan they are given, and the offline tools read a sequence
through pipeline.submaps.SubmapSequence, which feeds it the same way.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from dataclasses import dataclass

import numpy as np

from mf_lpr_ros.core.descriptor import finite_rows, one_point_per_voxel, rows_where
from mf_lpr_ros.core.pose import moved_points
from mf_lpr_ros.params import DescriptorParams

# Stored scans are thinned to a fraction of the descriptor's voxel: the occupancy that the
# descriptor computes at its own voxel is kept, the memory of a dense scan is not. Thinning at
# the descriptor's voxel itself changed no match on the tuning suite but cost held-out recall
# (docs/RESULTS.md, session 24).
THINNING_FRACTION = 0.5


@dataclass(frozen=True)
class SubmapWindow:
    """Which earlier scans join a scan's submap: those within window_m of travel, at most
    max_scans of them and none older than max_age_s; stored thinned to voxel_m and cropped to
    reach_m (horizontal) around their own sensor. window_m 0 = single scans."""

    window_m: float
    max_scans: int
    max_age_s: float
    voxel_m: float
    reach_m: float

    @classmethod
    def for_descriptor(cls, params: DescriptorParams) -> "SubmapWindow":
        # A stored point farther than this from its own sensor can never reach the window of a
        # scan at most window_m away.
        reach = params.extent_m / 2.0 * math.sqrt(2.0) + params.submap_m
        return cls(params.submap_m, params.submap_max_scans, params.submap_max_age_s,
                   params.voxel_size * THINNING_FRACTION, reach)

    @property
    def active(self) -> bool:
        return self.window_m > 0


@dataclass
class SubmapPoints:
    """A submap in the sensor frame of the scan it was made for: the points, how many scans it
    joins, the travel it spans (metres from the oldest scan used to this one) and whether it is
    complete: the window, not the start of the buffer, left the earlier scans out (what a
    relocalisation request waits for)."""

    points: np.ndarray
    scans: int
    span_m: float
    complete: bool

    def describe(self) -> str:
        state = "complete" if self.complete else "partial"
        return f"{state} submap of {self.scans} scans over {self.span_m:.1f} m"


@dataclass
class _Kept:
    stamp: float
    travelled_m: float
    pose: np.ndarray
    world_points: np.ndarray


class Submap:
    """The ring buffer of recent scans (see the module doc). Thread-safe: a node adds every
    scan from its executor thread while its search thread asks for submaps."""

    def __init__(self, window: SubmapWindow) -> None:
        self.window = window
        self._kept: deque[_Kept] = deque()
        self._dropped_any = False
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._kept)

    @property
    def nbytes(self) -> int:
        """The memory the kept scans' points take."""
        with self._lock:
            return sum(kept.world_points.nbytes for kept in self._kept)

    def reset(self) -> None:
        with self._lock:
            self._clear()

    def _clear(self) -> None:
        self._kept.clear()
        self._dropped_any = False

    def add(self, stamp: float, points: np.ndarray, pose: np.ndarray | None) -> None:
        """Keep a scan (points (N, 3+) in its sensor frame, pose world_T_sensor from odometry).
        A scan without a finite pose, or older than the newest kept and not kept itself, starts
        the buffer afresh (odometry lost, or a bag played again); a scan already kept is not
        kept again."""
        if pose is None or not np.isfinite(pose).all():
            self.reset()
            return
        if self.holds(stamp):
            return
        pose = np.asarray(pose, dtype=np.float64)
        thinned = self._thinned(points)
        world = moved_points(thinned, pose)
        with self._lock:
            if self._kept and stamp <= self._kept[-1].stamp:
                self._clear()
            travelled = 0.0
            if self._kept:
                last = self._kept[-1]
                travelled = last.travelled_m + float(np.linalg.norm(pose[:3, 3] - last.pose[:3, 3]))
            self._kept.append(_Kept(float(stamp), travelled, pose, world))
            newest = self._kept[-1]
            while self._kept and not self._within(self._kept[0], newest, len(self._kept)):
                self._kept.popleft()
                self._dropped_any = True

    def holds(self, stamp: float) -> bool:
        """Whether a scan with this stamp is kept."""
        with self._lock:
            return any(kept.stamp == stamp for kept in reversed(self._kept))

    def points_at(self, stamp: float) -> SubmapPoints:
        """The submap of the kept scan with this stamp, in its sensor frame: it and the earlier
        kept scans within the window. KeyError when no kept scan has this stamp."""
        with self._lock:
            kept, dropped_any = list(self._kept), self._dropped_any
        position = next((k for k in range(len(kept) - 1, -1, -1) if kept[k].stamp == stamp), None)
        if position is None:
            raise KeyError(f"no kept scan at stamp {stamp:.6f}")
        current = kept[position]
        used = [current]
        complete = dropped_any
        for earlier in reversed(kept[:position]):
            if not self._within(earlier, current, len(used) + 1):
                complete = True
                break
            used.append(earlier)
        points = moved_points(np.concatenate([scan.world_points for scan in used]),
                              np.linalg.inv(current.pose))
        return SubmapPoints(points, len(used), current.travelled_m - used[-1].travelled_m,
                            complete)

    def _within(self, earlier: _Kept, current: _Kept, count: int) -> bool:
        window = self.window
        return (current.travelled_m - earlier.travelled_m <= window.window_m
                and count <= window.max_scans
                and current.stamp - earlier.stamp <= window.max_age_s)

    def _thinned(self, points: np.ndarray) -> np.ndarray:
        xyz = np.asarray(points, dtype=np.float64)[:, :3]
        xyz = rows_where(xyz, finite_rows(xyz))
        xyz = rows_where(xyz, np.hypot(xyz[:, 0], xyz[:, 1]) <= self.window.reach_m)
        return one_point_per_voxel(xyz, self.window.voxel_m)
