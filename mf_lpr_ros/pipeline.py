"""Offline jobs that wire loaders, descriptors, the map and the search together."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Iterable

import numpy as np

from .auto_params import map_metadata, resolve_for_sequence
from .progress import progress_bar
from .config import Config, DescriptorParams, SearchParams
from .datasets import Scan, Sequence
from .descriptor import describe_density_image, describe_points, stamp_seed_key
from .map_store import ReferenceMap
from .pose import level_points, planar, wrap_angle
from .refine import refine_match
from .search import MatchedFilterIndex, MatchResult
from .verification import MatchVerifier, Verdict


def describe_scan(scan: Scan, params: DescriptorParams, *, reference: bool) -> np.ndarray:
    """Occupancy of a scan, from its points or its ready density image."""
    if scan.density is not None:
        return describe_density_image(scan.density, scan.density_pixel_m, params,
                                      reference=reference, seed_key=stamp_seed_key(scan.stamp))
    if scan.points is None:
        raise ValueError(f"scan {scan.index} has neither points nor a density image")
    return describe_points(prepared_points(scan, params), params, reference=reference,
                           seed_key=stamp_seed_key(scan.stamp))


def prepared_points(scan: Scan, params: DescriptorParams) -> np.ndarray:
    """The scan's points in the descriptor's frame (levelled when params.level)."""
    if scan.points is None:
        raise ValueError(f"scan {scan.index} has no points")
    if not params.level:
        return scan.points
    if scan.pose is None or not np.isfinite(scan.pose).all():
        raise ValueError(f"scan {scan.index}: levelling needs its orientation, and it has no pose")
    return level_points(scan.points, scan.pose[:3, :3])


def select_references(positions: np.ndarray, spacing_m: float,
                      valid: np.ndarray | None = None) -> np.ndarray:
    """Indices of scans kept as references: the first, then each one >= spacing_m from the last kept."""
    valid = np.ones(len(positions), dtype=bool) if valid is None else valid
    kept: list[int] = []
    last = None
    for index in np.flatnonzero(valid):
        if last is None or np.linalg.norm(positions[index] - last) >= spacing_m:
            kept.append(int(index))
            last = positions[index]
    return np.asarray(kept, dtype=np.int64)


def revisits(stamps: np.ndarray, positions: np.ndarray, spacing_m: float,
             exclude_recent_s: float, radius_m: float) -> set[int]:
    """Indices of scans that revisit a place: a reference (one per spacing_m of travel) at
    least exclude_recent_s older lies within radius_m of them (the loop-closure ground truth)."""
    references = select_references(positions, spacing_m)
    found = set()
    for index, stamp in enumerate(stamps):
        old = references[stamps[references] <= stamp - exclude_recent_s]
        if len(old) and np.linalg.norm(positions[old, :2] - positions[index, :2],
                                       axis=1).min() <= radius_m:
            found.add(index)
    return found


def _valid_poses(sequence: Sequence) -> np.ndarray:
    if sequence.poses is None:
        raise ValueError(f"{sequence.name}: this source has no poses; a map needs them")
    return np.isfinite(sequence.poses).all(axis=(1, 2))


def build_map(sequence: Sequence, config: Config, *, keep_clouds: bool = False,
              progress: bool = True) -> ReferenceMap:
    """A ReferenceMap from a sequence's scans, one reference every config.spacing_m metres
    (preset auto: the descriptor derived from the sequence first, and the choice recorded in
    the map's metadata)."""
    valid = _valid_poses(sequence)
    indices = select_references(sequence.poses[:, :3, 3], config.spacing_m, valid)
    config, profile = resolve_for_sequence(config, sequence)
    metadata = {"source": sequence.name, "spacing_m": config.spacing_m}
    if profile is not None:
        metadata["auto"] = map_metadata(profile, config.descriptor)
    reference_map = ReferenceMap(config.descriptor, sensor_frame_id=getattr(sequence, "frame_id", ""),
                                 metadata=metadata)
    offsets = set()
    for scan in progress_bar(sequence.iter_scans(indices), total=len(indices), desc="build map",
                             enabled=progress, unit="scan"):
        occupancy = describe_scan(scan, config.descriptor, reference=True)
        cloud = prepared_points(scan, config.descriptor) if keep_clouds else None
        reference_map.append(occupancy, scan.pose, scan.stamp, scan.index, cloud)
        offsets.add(scan.sensor_offset_m)
    record_sensor_offset(reference_map, offsets)
    return reference_map


def record_sensor_offset(reference_map: ReferenceMap, offsets: set[float]) -> None:
    """Store the references' common Scan.sensor_offset_m in the map (the search reads it)."""
    if len(offsets) > 1:
        raise ValueError(f"the references mix sensor offsets {sorted(offsets)} (density images "
                         f"of different layouts); build one map per layout")
    offset = offsets.pop() if offsets else 0.0
    if offset:
        reference_map.metadata["sensor_offset_m"] = offset


@dataclass
class QueryOutcome:
    """One query's match with its timings and, when ground truth exists, its errors."""

    index: int
    stamp: float
    match: MatchResult
    descriptor_ms: float
    verdict: Verdict
    truth: np.ndarray | None = None

    @property
    def translation_error_m(self) -> float:
        return float(np.hypot(*(self.match.pose[:2] - self.truth[:2]))) if self.truth is not None \
            else float("nan")

    @property
    def yaw_error_deg(self) -> float:
        if self.truth is None:
            return float("nan")
        return float(abs(np.degrees(wrap_angle(self.match.pose[2] - self.truth[2]))))


def localise_sequence(reference_map: ReferenceMap, sequence: Sequence, search: SearchParams, *,
                      indices: Iterable[int] | None = None, icp: bool = False,
                      progress: bool = True) -> list[QueryOutcome]:
    """Match every (selected) scan of a sequence against a map and verify each match as the
    localiser does (verification.MatchVerifier; the sequence's poses, when every scan has one,
    serve as odometry). icp: refine every pose by ICP against the map's reference clouds."""
    if icp and not reference_map.has_clouds:
        raise ValueError("ICP refinement needs a map that keeps reference clouds "
                         "(build it with --keep-clouds)")
    index = MatchedFilterIndex(reference_map, search)
    posed = sequence.poses is not None and bool(np.isfinite(sequence.poses).all())
    verifier = MatchVerifier(search, odometry_known=posed)
    outcomes = []
    selected = list(range(len(sequence))) if indices is None else list(indices)
    for scan in progress_bar(sequence.iter_scans(selected), total=len(selected), desc="localise",
                             enabled=progress, unit="scan"):
        started = time.perf_counter()
        occupancy = describe_scan(scan, reference_map.params, reference=False)
        descriptor_ms = (time.perf_counter() - started) * 1e3
        match = index.query(occupancy, sensor_offset_m=scan.sensor_offset_m)
        geometric = None
        if reference_map.has_clouds and scan.points is not None:
            points = prepared_points(scan, reference_map.params)

            def geometric(found):
                return refine_match(found, points, reference_map).fitness
        verdict = verifier.verify(match, planar(scan.pose) if posed else None, geometric)
        if icp and np.isnan(verdict.fitness) and geometric is not None:
            geometric(match)
        truth = planar(scan.pose) if scan.pose is not None and np.isfinite(scan.pose).all() else None
        outcomes.append(QueryOutcome(scan.index, scan.stamp, match, descriptor_ms, verdict, truth))
    return outcomes
