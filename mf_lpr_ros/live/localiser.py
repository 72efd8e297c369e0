"""The localiser's logic without ROS: search, verification and, in loop-closure mode, the map
growing from the robot's own scans."""

from __future__ import annotations

import math
import time
from collections import OrderedDict, deque
from dataclasses import dataclass, field

import numpy as np

from mf_lpr_ros.config import Config
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.pose import planar
from mf_lpr_ros.core.references import describe_observation, descriptor_points
from mf_lpr_ros.core.refine import refine_match
from mf_lpr_ros.core.search import MatchedFilterIndex, MatchResult
from mf_lpr_ros.core.submap import Submap, SubmapWindow
from mf_lpr_ros.core.verification import MAY_BE_CONFIRMED_KEPT, MatchVerifier
from mf_lpr_ros.errors import InvalidCloudError, InvalidPoseError
from mf_lpr_ros.live.map_builder import MapBuilder
from mf_lpr_ros.live.pose_buffer import PairedScan
from mf_lpr_ros.optional import require
from mf_lpr_ros.params import SearchParams

# Appended to LiveMatch.described_from for a scan a levelling map had no pose to level.
UNLEVELLED = ", not levelled (no pose)"


@dataclass
class LiveMatch:
    """One localisation attempt on a live scan. confirms: earlier attempts whose matches this
    one's agreement confirmed (now accepted; publish their closures late; a weak match a
    closure vouched for has been moved to where that closure puts it)."""

    stamp: float
    match: MatchResult | None
    accepted: bool
    reason: str
    descriptor_ms: float
    references_searched: int
    reference_stamp: float = math.nan
    fitness: float = math.nan
    support: int = -1
    timings_ms: dict[str, float] = field(default_factory=dict)
    described_from: str = "single scan"
    window_complete: bool = True
    confirms: list["LiveMatch"] = field(default_factory=list)


class Localiser:
    """Matches live scans against a map; in loop-closure mode the map grows from the scans.

    relocalise: the map is fixed (built earlier). loop_closure: each paired scan that moved
    spacing_m becomes a reference, and a query only searches references older than
    exclude_recent_s (so it cannot match the scans it was just taken with).
    A match is accepted when it passes verification.MatchVerifier: confidence, min_score,
    distinctiveness, ICP fitness (search.verify_fitness > 0) and, when odometry_known (the
    scans come with odometry poses), odometry consistency.
    When the map's descriptor has a submap window (descriptor.submap_m), each scan is described
    with the scans of its window (core.submap): give observe every scan the robot takes, with
    its odometry pose, searched or not; scans without a pose are described alone. Likewise a
    map that levels its scans (descriptor.level) levels each scan by its pose's roll and
    pitch, and describes a scan without a pose as the sensor held it (LiveMatch.described_from
    says so): a tilted sensor then matches less well, a level one as well.
    """

    MODES = ("relocalise", "loop_closure")

    def __init__(self, reference_map: ReferenceMap, config: Config, *, mode: str = "relocalise",
                 exclude_recent_s: float = 30.0, min_score: float = 0.0,
                 odometry_known: bool | None = None) -> None:
        if mode not in self.MODES:
            raise ValueError(f"mode must be one of {self.MODES}, got {mode!r}")
        reference_map.check_params(config.descriptor)
        self.config = config
        self.mode = mode
        self.exclude_recent_s = exclude_recent_s
        self.min_score = min_score
        self.map = reference_map
        self.index = MatchedFilterIndex(reference_map, config.search)
        self.reference_count = len(reference_map)
        self._incoming: deque[PairedScan] = deque()
        self.rejected_references = 0
        self.last_reference_error = ""
        odometry_known = mode == "loop_closure" if odometry_known is None else odometry_known
        self.verifier = MatchVerifier(config.search, min_score=min_score,
                                      odometry_known=odometry_known,
                                      submap_m=config.descriptor.submap_m)
        # Candidates that may still be confirmed by later ones, by stamp (bounded: far more
        # than odometry consistency's window holds).
        self._unconfirmed: OrderedDict[float, LiveMatch] = OrderedDict()
        self.verify = config.search.verify_fitness > 0
        if self.verify:
            # Imported now (about a second) rather than at the first match, failing at start-up.
            require("open3d")
        if self.verify and mode == "relocalise" and not reference_map.has_clouds:
            raise ValueError("search.verify_fitness needs a map that keeps reference clouds "
                             "(build it with keep_clouds / --keep-clouds), or set it to 0")
        window = SubmapWindow.for_descriptor(config.descriptor)
        self.submap = Submap(window) if window.active else None
        self._builder = MapBuilder(config, None, reference_map=reference_map,
                                   keep_clouds=self.verify, submap=self.submap) \
            if mode == "loop_closure" else None

    @property
    def search(self) -> SearchParams:
        return self.config.search

    def add_reference(self, scan: PairedScan) -> None:
        """Loop-closure mode: queue the robot's own scan for the map (safe from any thread; the
        searching thread adds queued scans, spacing permitting, before its next search)."""
        if self._builder is None:
            raise RuntimeError("references are only added in loop_closure mode")
        self._incoming.append(scan)

    def observe(self, stamp: float, points: np.ndarray, pose: np.ndarray | None) -> None:
        """Let a scan join the submap window (safe from any thread; nothing when the map has
        no window). Every scan taken should, including those never searched."""
        if self.submap is not None:
            self.submap.add(stamp, points, pose)

    def _integrate_references(self) -> None:
        added = False
        while self._incoming:
            scan = self._incoming.popleft()
            try:
                added |= self._builder.offer(scan) is not None
            except (InvalidCloudError, InvalidPoseError, ValueError) as error:
                self.rejected_references += 1
                self.last_reference_error = f"scan at {scan.stamp:.3f} not added: {error}"
        if added:
            self.index.sync()
            self.reference_count = len(self.map)

    def localise(self, stamp: float, points: np.ndarray, pose: np.ndarray | None = None,
                 *, request: bool = False) -> LiveMatch:
        """Search the map for one scan and verify the match (pose: world_T_sensor from odometry,
        used for levelling and odometry consistency). request: the scan answers a
        relocalisation request, so a weak match is searched again over a wider candidate
        list (SearchParams.prefilter_retry). Call it from one thread: it also adds the
        references queued by add_reference."""
        if self._builder is not None:
            self._integrate_references()
        params = self.config.descriptor
        started = time.perf_counter()
        described_from, complete = "single scan", True
        if self.submap is not None and pose is not None:
            self.observe(stamp, points, pose)
            if self.submap.holds(stamp):
                submap = self.submap.points_at(stamp)
                points, described_from, complete = submap.points, submap.describe(), \
                    submap.complete
        if pose is None and params.level:
            described_from += UNLEVELLED
        else:
            points = descriptor_points(points, pose, params)
        occupancy = describe_observation(params, reference=False, stamp=stamp, points=points)
        descriptor_ms = (time.perf_counter() - started) * 1e3
        n_active = len(self.map)
        if self.mode == "loop_closure":
            n_active = int(np.searchsorted(self.map.stamps, stamp - self.exclude_recent_s,
                                           side="right"))
        odometry = planar(pose) if pose is not None and self.verifier.consistency_active \
            else None
        match = self.index.query(
            occupancy, n_active, request=request,
            revisit_places=lambda weak: self.verifier.revisit_places(weak, odometry)
        ) if n_active else None
        verdict = self.verifier.verify(
            match, odometry, lambda found: refine_match(found, points, self.map).fitness,
            key=stamp)
        if match is None:
            return LiveMatch(stamp, None, False, verdict.reason, descriptor_ms, n_active,
                             described_from=described_from, window_complete=complete)
        timings = {"descriptor": descriptor_ms, **match.timings_ms}
        result = LiveMatch(stamp, match, verdict.accepted, verdict.reason, descriptor_ms,
                           n_active, float(self.map.stamps[match.reference_index]),
                           verdict.fitness, verdict.support, timings, described_from, complete)
        result.confirms = self._confirmed(verdict.confirms)
        if verdict.may_be_confirmed:
            self._unconfirmed[stamp] = result
            while len(self._unconfirmed) > MAY_BE_CONFIRMED_KEPT:
                self._unconfirmed.popitem(last=False)
        return result

    def _confirmed(self, reasons: dict[float, str]) -> list[LiveMatch]:
        """The earlier candidates these stamps name, now accepted for the reason given."""
        confirmed = []
        for stamp, reason in reasons.items():
            earlier = self._unconfirmed.pop(stamp, None)
            if earlier is not None:
                earlier.accepted, earlier.reason = True, reason
                confirmed.append(earlier)
        return confirmed

    def reference_pose(self, index: int) -> np.ndarray:
        return np.array(self.map.poses[index])


def relocalised_pose(match: MatchResult, reference_pose: np.ndarray,
                     extrinsic: np.ndarray | None = None) -> np.ndarray:
    """world_T_base (4x4) from a match: planar x, y, yaw of the estimate, z of the reference,
    no roll or pitch; the sensor-to-base extrinsic (base_T_sensor) removed."""
    x, y, yaw = match.pose
    sensor = np.eye(4)
    sensor[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    sensor[:3, 3] = [x, y, reference_pose[2, 3]]
    if extrinsic is None:
        return sensor
    return sensor @ np.linalg.inv(extrinsic)


def relative_transform(match: MatchResult) -> np.ndarray:
    """reference_T_query (4x4, planar) of a match: the loop-closure constraint."""
    transform = np.eye(4)
    c, s = math.cos(match.rotation_rad), math.sin(match.rotation_rad)
    transform[:2, :2] = [[c, -s], [s, c]]
    transform[:2, 3] = match.shift_m
    return transform
