"""ICP refinement (open3d) of a matched-filter alignment against a stored reference cloud."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from mf_lpr_ros.core.pose import alignment_from_poses, planar, query_pose_from_alignment
from mf_lpr_ros.optional import require

if TYPE_CHECKING:
    from mf_lpr_ros.core.map_store import ReferenceMap
    from mf_lpr_ros.core.search import MatchResult

MIN_FITNESS = 0.3
MAX_CORRECTION_M = 2.0
MAX_CORRECTION_RAD = np.radians(5.0)
# ICP cost grows faster than linearly with the query's size (300 ms at 7k points, 40 ms at 3k
# on BALM scans); an even subsample keeps the fitness fraction and the alignment.
MAX_QUERY_POINTS = 3000


@dataclass
class IcpRefinement:
    shift_m: np.ndarray
    rotation_rad: float
    fitness: float
    accepted: bool


def refine_with_icp(query_points: np.ndarray, reference_points: np.ndarray, shift_m: np.ndarray,
                    rotation_rad: float, max_correspondence_m: float,
                    max_iterations: int = 30) -> IcpRefinement:
    """Point-to-point ICP from the matched-filter alignment (query points -> reference frame).

    The refinement is kept only when enough points correspond (fitness) and it moves the
    estimate by less than a matched-filter error could (2 m, 5 deg); otherwise the input returns.
    """
    o3d = require("open3d")
    initial = np.eye(4)
    c, s = np.cos(rotation_rad), np.sin(rotation_rad)
    initial[:2, :2] = [[c, -s], [s, c]]
    initial[:2, 3] = shift_m
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(query_points[:, :3],
                                                                           dtype=np.float64)))
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(reference_points[:, :3],
                                                                           dtype=np.float64)))
    result = o3d.pipelines.registration.registration_icp(
        source, target, max_correspondence_m, initial,
        o3d.pipelines.registration.TransformationEstimationPointToPoint(),
        o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=max_iterations))
    transform = np.asarray(result.transformation)
    refined_shift = transform[:2, 3].copy()
    refined_rotation = float(np.arctan2(transform[1, 0], transform[0, 0]))
    change = np.linalg.norm(refined_shift - shift_m)
    turn = abs((refined_rotation - rotation_rad + np.pi) % (2 * np.pi) - np.pi)
    accepted = (result.fitness >= MIN_FITNESS and change <= MAX_CORRECTION_M
                and turn <= MAX_CORRECTION_RAD)
    if not accepted:
        return IcpRefinement(np.asarray(shift_m, dtype=float), rotation_rad, float(result.fitness),
                             False)
    return IcpRefinement(refined_shift, refined_rotation, float(result.fitness), True)


def refine_match(match: "MatchResult", points: np.ndarray, reference_map: "ReferenceMap"
                 ) -> IcpRefinement:
    """ICP of a match against the stored cloud of the reference its alignment was scored on
    (MatchResult.scored_reference: what verification tests is the evidence, not the nearer
    reference a re-ranking reports); updates the match's pose, and its alignment to the
    reported reference, in place when the refinement is kept, and records its time in
    match.timings_ms."""
    started = time.perf_counter()
    points = points[::max(1, -(-len(points) // MAX_QUERY_POINTS))]
    scored = match.reference_index if match.scored_reference is None else match.scored_reference
    scored_pose = planar(reference_map.poses[scored])
    reported_is_scored = scored == match.reference_index
    shift_m, rotation_rad = ((match.shift_m, match.rotation_rad) if reported_is_scored
                             else alignment_from_poses(scored_pose, match.pose))
    refined = refine_with_icp(points, reference_map.cloud(scored), shift_m, rotation_rad,
                              max_correspondence_m=2 * reference_map.params.voxel_size)
    if refined.accepted:
        match.pose = query_pose_from_alignment(scored_pose, refined.shift_m, refined.rotation_rad)
        match.shift_m, match.rotation_rad = (
            (refined.shift_m, refined.rotation_rad) if reported_is_scored
            else alignment_from_poses(planar(reference_map.poses[match.reference_index]),
                                      match.pose))
    match.timings_ms["icp"] = (time.perf_counter() - started) * 1e3
    return refined
