"""The methods compared under the evaluation protocol: MF-LPR (ours), Scan Context, MapClosures.

Each describes scans (describe), takes the references' descriptors (build), answers a query
among the first n_active references (query) with a Retrieval, and is told of a query the
protocol could not search (pass_over, with its odometry). A method's submap_window says
which local map it describes (core.submap; None: single scans): the protocol reads the
sequences through it.
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from mf_lpr_ros.config import Config
from mf_lpr_ros.core.descriptor import one_point_per_voxel
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.pose import planar, wrap_angle
from mf_lpr_ros.core.references import DescribedScan, add_references
from mf_lpr_ros.core.refine import refine_match
from mf_lpr_ros.core.search import MatchedFilterIndex, MatchResult
from mf_lpr_ros.core.submap import SubmapWindow
from mf_lpr_ros.core.verification import MAY_BE_CONFIRMED_KEPT, MatchVerifier
from mf_lpr_ros.datasets import Scan
from mf_lpr_ros.evaluation.scan_context import ScanContextIndex
from mf_lpr_ros.optional import require
from mf_lpr_ros.pipeline.mapping import described_scan, prepared_points


@dataclass
class Retrieval:
    """A method's answer for one query: the reference (position in the reference list, -1 for
    none), the query's estimated (x, y, yaw), a confidence, candidates best first, and whether
    the method would publish it as a loop closure at its defaults; confirms: earlier queries
    (their order among this method's queries) it would now publish, confirmed late, each with
    the reason it is published for, the pose it is published at and that pose's (x, y)
    covariance (a weak match vouched for takes the pose of the closure that vouches, and its
    covariance, core/verification.py); distinctiveness, place_similarity and reason: see
    QueryRecord; searched: the references its candidate stage kept for the full comparison
    (None: the method does not say); position_covariance: the (x, y) covariance (2x2, map
    frame) the method publishes with pose (None: it gives none)."""

    reference: int
    pose: np.ndarray
    confidence: float
    candidates: np.ndarray
    ms_global: float
    ms_local: float = 0.0
    published: bool = False
    confirms: dict[int, tuple[str, np.ndarray, np.ndarray | None]] = field(default_factory=dict)
    distinctiveness: float = math.nan
    local_distinctiveness: float = math.nan
    reason: str = ""
    searched: np.ndarray | None = None
    place_similarity: float = math.nan
    position_covariance: np.ndarray | None = None


class MatchedFilterMethod:
    """MF-LPR (ours): the two-stage matched-filter search and its pose; published closures are
    those verification.MatchVerifier accepts (ICP where the scans have points and the preset
    asks for it, odometry consistency on the sequence's poses)."""

    name = "MF-LPR (ours)"

    def __init__(self, config: Config) -> None:
        self.config = config
        self.submap_window = SubmapWindow.for_descriptor(config.descriptor)
        self._index: MatchedFilterIndex | None = None
        # Made with the index: verification state (odometry consistency) belongs to one run.
        self._verifier: MatchVerifier | None = None
        self._queries = 0
        # The matches a later verdict may still confirm, by query order: a vouch moves a weak
        # one to the vouching closure's pose.
        self._may_be_confirmed: OrderedDict[int, MatchResult] = OrderedDict()

    def describe(self, scan: Scan, *, reference: bool) -> DescribedScan:
        keep_cloud = self.config.search.verify_fitness > 0 and scan.points is not None
        return described_scan(scan, self.config.descriptor, reference=reference,
                              keep_cloud=keep_cloud)

    def build(self, descriptors: list, poses: np.ndarray, stamps: np.ndarray) -> None:
        reference_map = ReferenceMap(self.config.descriptor)
        add_references(reference_map, descriptors)
        self._index = MatchedFilterIndex(reference_map, self.config.search)
        self._verifier = MatchVerifier(self.config.search,
                                       submap_m=self.config.descriptor.submap_m)
        self._queries = 0
        self._may_be_confirmed.clear()

    def pass_over(self, odometry: np.ndarray) -> None:
        """A query that could not be searched: the verifier still travels with its odometry,
        as `localise`'s does (odometry consistency counts travel step by step)."""
        self._verifier.verify(None, odometry)

    def query(self, descriptor: DescribedScan, n_active: int, odometry: np.ndarray
              ) -> Retrieval:
        match = self._index.query(descriptor.occupancy, n_active=n_active,
                                  sensor_offset_m=descriptor.sensor_offset_m,
                                  revisit_places=lambda weak: self._verifier.revisit_places(
                                      weak, odometry))
        geometric = None
        if descriptor.cloud is not None and self._index.map.has_clouds:
            def geometric(found):
                return refine_match(found, descriptor.cloud, self._index.map).fitness
        verdict = self._verifier.verify(match, odometry, geometric, key=self._queries)
        if verdict.may_be_confirmed:
            self._may_be_confirmed[self._queries] = match
            while len(self._may_be_confirmed) > MAY_BE_CONFIRMED_KEPT:
                self._may_be_confirmed.popitem(last=False)
        self._queries += 1
        confirms = {}
        for earlier, reason in verdict.confirms.items():
            confirmed = self._may_be_confirmed.pop(earlier)
            confirms[earlier] = (reason, confirmed.pose, confirmed.covariance[:2, :2])
        return Retrieval(match.reference_index, match.pose, match.confidence, match.candidates,
                         match.timings_ms["global"], match.timings_ms["local"], verdict.accepted,
                         confirms, match.distinctiveness, match.local_distinctiveness,
                         verdict.reason,
                         np.arange(n_active) if match.searched is None else match.searched,
                         match.place_similarity, match.covariance[:2, :2])


class _IndependentQueries:
    """A baseline whose answer to a query depends on no earlier query."""

    def pass_over(self, odometry: np.ndarray) -> None:
        """Nothing carries over to the next query."""


class ScanContextMethod(_IndependentQueries):
    """Scan Context (Kim and Kim, IROS 2018): the matched reference's position with the Scan
    Context yaw, so its corrected recall is its retrieval recall. Confidence: 1 - distance."""

    name = "Scan Context"
    submap_window = None

    def __init__(self, config: Config) -> None:
        self.config = config
        self._index = ScanContextIndex()
        self._poses = np.zeros((0, 3))

    def describe(self, scan: Scan, *, reference: bool) -> np.ndarray:
        return self._index.describe(points_for_baselines(scan, self.config))

    def build(self, descriptors: list, poses: np.ndarray, stamps: np.ndarray) -> None:
        for context in descriptors:
            self._index.append_context(context)
        self._poses = planar(poses)

    def query(self, descriptor: np.ndarray, n_active: int, odometry: np.ndarray) -> Retrieval:
        started = time.perf_counter()
        found, yaw, distance, candidates = self._index.query_context(descriptor, n_active)
        elapsed = (time.perf_counter() - started) * 1e3
        pose = self._poses[found] + np.array([0.0, 0.0, yaw])
        pose[2] = wrap_angle(pose[2])
        return Retrieval(found, pose, 1.0 - distance, candidates, elapsed,
                         published=distance < self._index.params.accept_distance,
                         searched=candidates)


class MapClosuresMethod(_IndependentQueries):
    """MapClosures (Gupta et al., the map-closures package): ORB features of BEV density maps in
    an HBST tree, then RANSAC. Fed as its own pipeline feeds it: local maps, not single scans.
    Each scan's local map holds the scans of the last local_map_m metres of travel, put in that
    scan's frame with the sequence's poses (its pipeline uses kiss-icp odometry instead; the
    protocol makes them with core.submap, as ours) and voxelised at its density-map
    resolution. Its pose is not used: the matched reference's position is reported.
    Confidence: RANSAC inliers. Every closure it returns passed its own RANSAC test, so each
    is published."""

    name = "MapClosures"
    candidates_asked = 50

    def __init__(self, config: Config, density_map_resolution: float | None = None,
                 local_map_m: float = 10.0) -> None:
        MapClosuresConfig = require("map_closures.config").MapClosuresConfig
        MapClosures = require("map_closures.map_closures").MapClosures
        resolution = density_map_resolution or max(config.descriptor.voxel_size, 0.1)
        self.config = config
        self.resolution = resolution
        self.submap_window = SubmapWindow(local_map_m, max_scans=10 ** 6, max_age_s=math.inf,
                                          voxel_m=resolution, reach_m=math.inf)
        self._closures = MapClosures(MapClosuresConfig(density_map_resolution=resolution))
        self._poses = np.zeros((0, 3))
        self._next_id = 0

    def describe(self, scan: Scan, *, reference: bool) -> np.ndarray:
        return one_point_per_voxel(points_for_baselines(scan, self.config).astype(np.float64),
                                   self.resolution)

    def build(self, descriptors: list, poses: np.ndarray, stamps: np.ndarray) -> None:
        for points in descriptors:
            self._closures.get_closures(self._next_id, points)
            self._next_id += 1
        self._poses = planar(poses)

    def query(self, descriptor: np.ndarray, n_active: int, odometry: np.ndarray) -> Retrieval:
        started = time.perf_counter()
        query_id = self._next_id
        self._next_id += 1
        closures = self._closures.get_top_k_closures(query_id, descriptor, self.candidates_asked)
        elapsed = (time.perf_counter() - started) * 1e3
        found = [(c.number_of_inliers, min(c.source_id, c.target_id)) for c in closures
                 if max(c.source_id, c.target_id) == query_id
                 and min(c.source_id, c.target_id) < n_active]
        if not found:
            return Retrieval(-1, np.full(3, np.nan), 0.0, np.zeros(0, dtype=np.int64), elapsed)
        found.sort(key=lambda item: -item[0])
        candidates = np.array([reference for _, reference in found], dtype=np.int64)
        return Retrieval(int(candidates[0]), self._poses[candidates[0]].copy(),
                         float(found[0][0]), candidates, elapsed, published=True)


METHODS = {"mf-lpr": MatchedFilterMethod, "scan-context": ScanContextMethod,
           "map-closures": MapClosuresMethod}


def make_method(name: str, config: Config):
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}; choose from {sorted(METHODS)}")
    return METHODS[name](config)


def points_for_baselines(scan: Scan, config: Config) -> np.ndarray:
    """A scan's points as the baselines take them; a BEV density image becomes one point per
    occupied pixel with the density as height."""
    if scan.points is not None:
        return prepared_points(scan, config.descriptor)
    density = np.asarray(scan.density, dtype=np.float64)
    rows, cols = np.nonzero(density > 0)
    pixel = scan.density_pixel_m
    return np.stack([(cols - density.shape[1] // 2 + 0.5) * pixel,
                     (rows - density.shape[0] // 2 + 0.5) * pixel,
                     density[rows, cols] * pixel], axis=1)
