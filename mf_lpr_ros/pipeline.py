"""Offline jobs that wire loaders, descriptors, the map and the search together."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Iterable

import numpy as np
from tqdm import tqdm

from .config import Config, DescriptorParams, SearchParams
from .datasets import Scan, Sequence
from .descriptor import describe_density_image, describe_points, stamp_seed_key
from .map_store import ReferenceMap
from .pose import level_points, planar, wrap_angle
from .refine import refine_match
from .scan_context import ScanContextIndex
from .search import MatchedFilterIndex, MatchResult


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
    """A ReferenceMap from a sequence's scans, one reference every config.spacing_m metres."""
    valid = _valid_poses(sequence)
    indices = select_references(sequence.poses[:, :3, 3], config.spacing_m, valid)
    reference_map = ReferenceMap(config.descriptor, sensor_frame_id=getattr(sequence, "frame_id", ""),
                                 metadata={"source": sequence.name, "spacing_m": config.spacing_m})
    for scan in tqdm(sequence.iter_scans(indices), total=len(indices), desc="build map",
                     disable=not progress, unit="scan"):
        occupancy = describe_scan(scan, config.descriptor, reference=True)
        cloud = prepared_points(scan, config.descriptor) if keep_clouds else None
        reference_map.append(occupancy, scan.pose, scan.stamp, scan.index, cloud)
    return reference_map


@dataclass
class QueryOutcome:
    """One query's match with its timings and, when ground truth exists, its errors."""

    index: int
    stamp: float
    match: MatchResult
    descriptor_ms: float
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
    """Match every (selected) scan of a sequence against a map; optionally refine by ICP
    against the reference clouds the map keeps."""
    if icp and not reference_map.has_clouds:
        raise ValueError("ICP refinement needs a map that keeps reference clouds "
                         "(build it with --keep-clouds)")
    index = MatchedFilterIndex(reference_map, search)
    outcomes = []
    selected = list(range(len(sequence))) if indices is None else list(indices)
    for scan in tqdm(sequence.iter_scans(selected), total=len(selected), desc="localise",
                     disable=not progress, unit="scan"):
        started = time.perf_counter()
        occupancy = describe_scan(scan, reference_map.params, reference=False)
        descriptor_ms = (time.perf_counter() - started) * 1e3
        match = index.query(occupancy)
        if icp:
            refine_match(match, prepared_points(scan, reference_map.params), reference_map)
        truth = planar(scan.pose) if scan.pose is not None and np.isfinite(scan.pose).all() else None
        outcomes.append(QueryOutcome(scan.index, scan.stamp, match, descriptor_ms, truth))
    return outcomes


def evaluate(reference: Sequence, config: Config, tolerance_m: float, *,
             query: Sequence | None = None, exclude_recent_frames: int = 0,
             query_every: int = 1, progress: bool = True) -> dict:
    """Recall, pose accuracy, F1max and timings (METHOD.md section 5).

    With no query sequence, the single-sequence loop-closure protocol: each scan (every
    query_every-th) queries the references more than exclude_recent_frames frames older. A
    query is positive when ground truth puts such a reference within tolerance_m. With a query
    sequence recorded frame by frame alongside the reference (e.g. KITTI 00 and 00_rot),
    exclude_recent_frames compares frame indices across the two the same way.
    """
    positions = reference.poses[:, :2, 3] if reference.poses is not None else None
    ref_indices, query_indices = _protocol(reference, config, query, exclude_recent_frames,
                                           query_every)
    same_sequence = query is None
    query_seq = reference if same_sequence else query

    reference_map = ReferenceMap(config.descriptor, metadata={"source": reference.name})
    query_occupancy: dict[int, tuple[np.ndarray, float]] = {}
    wanted_refs = set(ref_indices.tolist())
    wanted_queries = set(query_indices.tolist())
    to_describe = sorted(wanted_refs | (wanted_queries if same_sequence else set()))
    for scan in tqdm(reference.iter_scans(to_describe), desc="describe", disable=not progress,
                     unit="scan", total=len(to_describe)):
        if scan.index in wanted_refs:
            reference_map.append(describe_scan(scan, config.descriptor, reference=True), scan.pose,
                                 scan.stamp, scan.index)
        if same_sequence and scan.index in wanted_queries:
            query_occupancy[scan.index] = _timed_query_descriptor(scan, config.descriptor)
    if not same_sequence:
        for scan in tqdm(query_seq.iter_scans(query_indices), total=len(query_indices),
                         desc="describe queries", disable=not progress, unit="scan"):
            query_occupancy[scan.index] = _timed_query_descriptor(scan, config.descriptor)

    index = MatchedFilterIndex(reference_map, config.search)
    ref_positions = positions[ref_indices]
    records = []
    for query_index in tqdm(query_indices, desc="search", disable=not progress, unit="query"):
        n_active = _n_active(ref_indices, query_index, exclude_recent_frames, same_sequence)
        if n_active == 0:
            continue
        occupancy, descriptor_ms = query_occupancy[int(query_index)]
        match = index.query(occupancy, n_active=n_active)
        truth = planar(query_seq.poses[query_index])
        distances = np.linalg.norm(ref_positions[:n_active] - truth[:2], axis=1)
        records.append(_score_query(match, truth, distances, tolerance_m, descriptor_ms))
    return summarise(records, n_references=len(ref_indices))


def _protocol(reference: Sequence, config: Config, query: Sequence | None,
              exclude_recent_frames: int, query_every: int) -> tuple[np.ndarray, np.ndarray]:
    """Reference indices (one per spacing_m) and query indices (every query_every-th valid scan
    with at least one reference old enough) of evaluate's protocol."""
    valid = _valid_poses(reference)
    ref_indices = select_references(reference.poses[:, :3, 3], config.spacing_m, valid)
    query_indices = np.flatnonzero(_valid_poses(reference if query is None else query))[::query_every]
    if query is None or exclude_recent_frames > 0:
        query_indices = query_indices[query_indices > ref_indices[0] + exclude_recent_frames]
    return ref_indices, query_indices


def _n_active(ref_indices: np.ndarray, query_index: int, exclude_recent_frames: int,
              same_sequence: bool) -> int:
    if same_sequence or exclude_recent_frames > 0:
        return int(np.searchsorted(ref_indices, query_index - exclude_recent_frames, "left"))
    return len(ref_indices)


def evaluate_scan_context(reference: Sequence, config: Config, tolerance_m: float, *,
                          query: Sequence | None = None, exclude_recent_frames: int = 0,
                          query_every: int = 1, progress: bool = True) -> dict:
    """evaluate's protocol and metrics for the Scan Context baseline (scan_context.py).

    Its pose is the matched reference's position with the Scan Context yaw, so "corrected"
    recall is retrieval recall with the reference's own position error. Its confidence is
    1 - distance. BEV density images become one point per occupied pixel, the density as height.
    """
    ref_indices, query_indices = _protocol(reference, config, query, exclude_recent_frames,
                                           query_every)
    query_seq = reference if query is None else query
    index = ScanContextIndex()
    contexts: dict[int, tuple[np.ndarray, float]] = {}
    wanted_refs = set(ref_indices.tolist())
    wanted_queries = set(query_indices.tolist())
    reference_jobs = sorted(wanted_refs | (wanted_queries if query is None else set()))
    for scan in tqdm(reference.iter_scans(reference_jobs), total=len(reference_jobs),
                     desc="scan context", disable=not progress, unit="scan"):
        started = time.perf_counter()
        context = index.describe(_points_for_scan_context(scan, config.descriptor))
        elapsed_ms = (time.perf_counter() - started) * 1e3
        if scan.index in wanted_refs:
            index.append_context(context)
        if query is None and scan.index in wanted_queries:
            contexts[scan.index] = (context, elapsed_ms)
    if query is not None:
        for scan in tqdm(query.iter_scans(query_indices), total=len(query_indices),
                         desc="scan context queries", disable=not progress, unit="scan"):
            started = time.perf_counter()
            context = index.describe(_points_for_scan_context(scan, config.descriptor))
            contexts[scan.index] = (context, (time.perf_counter() - started) * 1e3)
    reference_poses = planar(reference.poses[ref_indices])
    records = []
    for query_index in query_indices:
        n_active = _n_active(ref_indices, query_index, exclude_recent_frames, query is None)
        if n_active == 0:
            continue
        context, descriptor_ms = contexts[int(query_index)]
        started = time.perf_counter()
        found, yaw, distance, candidates = index.query_context(context, n_active)
        search_ms = (time.perf_counter() - started) * 1e3
        truth = planar(query_seq.poses[query_index])
        distances = np.linalg.norm(reference_poses[:n_active, :2] - truth[:2], axis=1)
        pose = reference_poses[found] + np.array([0.0, 0.0, yaw])
        translation_error = float(distances[found])
        records.append({
            "positive": bool(distances.min() <= tolerance_m),
            "retrieved_correct": translation_error <= tolerance_m,
            "corrected_correct": translation_error <= tolerance_m,
            "top5_correct": bool((distances[candidates[:5]] <= tolerance_m).any()),
            "rte_m": translation_error,
            "rre_deg": float(abs(np.degrees(wrap_angle(pose[2] - truth[2])))),
            "confidence": 1.0 - distance,
            "ms_descriptor": descriptor_ms,
            "ms_global": search_ms,
            "ms_local": 0.0,
        })
    return summarise(records, n_references=len(ref_indices))


def _points_for_scan_context(scan: Scan, params: DescriptorParams) -> np.ndarray:
    if scan.points is not None:
        return prepared_points(scan, params)
    density = np.asarray(scan.density, dtype=np.float64)
    rows, cols = np.nonzero(density > 0)
    pixel = scan.density_pixel_m
    return np.stack([(cols - density.shape[1] // 2 + 0.5) * pixel,
                     (rows - density.shape[0] // 2 + 0.5) * pixel,
                     density[rows, cols] * pixel], axis=1)


def _timed_query_descriptor(scan: Scan, params: DescriptorParams) -> tuple[np.ndarray, float]:
    started = time.perf_counter()
    occupancy = describe_scan(scan, params, reference=False)
    return occupancy, (time.perf_counter() - started) * 1e3


def _score_query(match: MatchResult, truth: np.ndarray, distances: np.ndarray, tolerance_m: float,
                 descriptor_ms: float) -> dict:
    translation_error = float(np.hypot(*(match.pose[:2] - truth[:2])))
    yaw_error = float(abs(np.degrees(wrap_angle(match.pose[2] - truth[2]))))
    return {
        "positive": bool(distances.min() <= tolerance_m),
        "retrieved_correct": bool(distances[match.reference_index] <= tolerance_m),
        "corrected_correct": translation_error <= tolerance_m,
        "top5_correct": bool((distances[match.candidates] <= tolerance_m).any()),
        "rte_m": translation_error,
        "rre_deg": yaw_error,
        "confidence": match.confidence,
        "ms_descriptor": descriptor_ms,
        "ms_global": match.timings_ms["global"],
        "ms_local": match.timings_ms["local"],
    }


def summarise(records: list[dict], n_references: int) -> dict:
    """The evaluation JSON from per-query records (see evaluate)."""
    def column(name: str) -> np.ndarray:
        return np.array([r[name] for r in records], dtype=float)

    positive = column("positive").astype(bool)
    retrieved = column("retrieved_correct").astype(bool)
    n_positive = int(positive.sum())
    rte, rre = column("rte_m"), column("rre_deg")
    correct = positive & retrieved
    success = correct & (rte < 2.0) & (rre < 5.0)
    ms_total = column("ms_descriptor") + column("ms_global") + column("ms_local")

    def rate(mask: np.ndarray) -> float:
        return float(mask[positive].mean()) if n_positive else float("nan")

    def median(values: np.ndarray) -> float:
        return float(np.median(values)) if len(values) else float("nan")

    return {
        "n_queries": n_positive,
        "n_evaluated": len(records),
        "n_references": n_references,
        "recall_at_1": rate(retrieved),
        "recall_at_1_corrected": rate(column("corrected_correct").astype(bool)),
        "recall_at_5": rate(column("top5_correct").astype(bool)),
        "rte_mean_m": float(rte[success].mean()) if success.any() else float("nan"),
        "rte_std_m": float(rte[success].std()) if success.any() else float("nan"),
        "rre_mean_deg": float(rre[success].mean()) if success.any() else float("nan"),
        "rre_std_deg": float(rre[success].std()) if success.any() else float("nan"),
        "success_rate": float(success.sum() / correct.sum()) if correct.any() else float("nan"),
        "f1_max": f1_max(column("confidence"), positive & retrieved, n_positive),
        "confidence_at_f1_max": confidence_at_f1_max(column("confidence"), positive & retrieved,
                                                     n_positive),
        "ms_per_query": median(ms_total),
        "ms_descriptor": median(column("ms_descriptor")),
        "ms_global": median(column("ms_global")),
        "ms_local": median(column("ms_local")),
    }


def f1_max(confidence: np.ndarray, true_match: np.ndarray, n_positive: int) -> float:
    """Best F1 over confidence thresholds: accepted correct matches are true positives, accepted
    wrong ones (including any match for a query with no true reference) false positives."""
    return _f1_curve(confidence, true_match, n_positive)[0]


def confidence_at_f1_max(confidence: np.ndarray, true_match: np.ndarray, n_positive: int) -> float:
    """The accept threshold (min_confidence) that reaches f1_max."""
    return _f1_curve(confidence, true_match, n_positive)[1]


def _f1_curve(confidence: np.ndarray, true_match: np.ndarray, n_positive: int
              ) -> tuple[float, float]:
    if n_positive == 0 or len(confidence) == 0:
        return float("nan"), float("nan")
    order = np.argsort(-confidence, kind="stable")
    true_positives = np.cumsum(true_match[order])
    accepted = np.arange(1, len(order) + 1)
    precision = true_positives / accepted
    recall = true_positives / n_positive
    with np.errstate(invalid="ignore", divide="ignore"):
        f1 = np.where(precision + recall > 0, 2 * precision * recall / (precision + recall), 0.0)
    best = int(np.argmax(f1))
    return float(f1[best]), float(confidence[order][best])
