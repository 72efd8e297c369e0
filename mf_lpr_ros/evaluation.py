"""The evaluation protocol, the methods compared under it, and the metrics (METHOD.md section 5).

A protocol picks references (one per reference_spacing_m along the reference path, 0 keeps every
scan) and queries (one per query_spacing_m along the query path, or every query_every-th scan,
or the scans a dataset's own split names), optionally within fixed frame ranges
(reference_frames, query_frames: first and last index, inclusive, as BEVPlace splits a KITTI
sequence into database and queries), and for each query the references it may match (older than
exclude_recent_frames / exclude_recent_s in the single-sequence loop-closure protocol). A query is
positive when some reference it may match lies within tolerance_m of it.

Every method (MF-LPR, Scan Context, MapClosures) runs under the same protocol and yields one
record per query; summarise turns records into the metrics, computed the same way for all.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from .auto_params import map_metadata, resolve_for_sequence
from .progress import progress_bar
from .config import Config
from .datasets import Scan, Sequence
from .datasets.base import nearest_keys
from .descriptor import one_point_per_voxel
from .map_store import ReferenceMap
from .pipeline import describe_scan, prepared_points, record_sensor_offset, select_references
from .pose import planar, wrap_angle
from .scan_context import ScanContextIndex
from .refine import refine_match
from .search import MatchedFilterIndex
from .verification import MatchVerifier

RECALL_AT_N = 5
_STAMP_MATCH_S = 1e-4
_CURVE_POINTS = 200


@dataclass(frozen=True)
class Protocol:
    """How references and queries are chosen and when a match counts (see the module doc)."""

    tolerance_m: float
    reference_spacing_m: float | None = None
    query_spacing_m: float = 0.0
    query_every: int = 1
    exclude_recent_frames: int = 0
    exclude_recent_s: float = 0.0
    reference_frames: tuple[int, int] | None = None
    query_frames: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        if not self.tolerance_m > 0:
            raise ValueError(f"protocol tolerance_m must be > 0, got {self.tolerance_m}")
        if self.query_every < 1:
            raise ValueError(f"protocol query_every must be >= 1, got {self.query_every}")
        for name in ("reference_frames", "query_frames"):
            frames = getattr(self, name)
            if frames is not None and not 0 <= frames[0] <= frames[1]:
                raise ValueError(f"protocol {name} must be (first, last) with 0 <= first <= "
                                 f"last, got {frames}")


@dataclass
class Retrieval:
    """A method's answer for one query: the reference (position in the reference list, -1 for
    none), the query's estimated (x, y, yaw), a confidence, candidates best first, and whether
    the method would publish it as a loop closure at its defaults."""

    reference: int
    pose: np.ndarray
    confidence: float
    candidates: np.ndarray
    ms_global: float
    ms_local: float = 0.0
    published: bool = False


@dataclass
class Selection:
    """The protocol applied to a pair: reference and query scan indices, and for each query how
    many references (the oldest first) it may match."""

    references: np.ndarray
    queries: np.ndarray
    n_active: np.ndarray


def select(reference: Sequence, protocol: Protocol, spacing_m: float, *,
           query: Sequence | None = None, query_stamps: np.ndarray | None = None) -> Selection:
    """Which scans are references and queries under protocol (query None: the single-sequence
    loop-closure protocol on reference)."""
    same_sequence = query is None
    query_seq = reference if same_sequence else query
    ref_valid = _valid_poses(reference) & _in_frames(len(reference), protocol.reference_frames)
    spacing = protocol.reference_spacing_m if protocol.reference_spacing_m is not None else spacing_m
    references = select_references(reference.poses[:, :3, 3], spacing, ref_valid)
    if not len(references):
        raise ValueError(f"{reference.name}: no scan with a valid pose to use as a reference")
    query_valid = _valid_poses(query_seq) & _in_frames(len(query_seq), protocol.query_frames)
    if query_stamps is not None:
        query_valid &= _stamps_in(query_seq.stamps, np.asarray(query_stamps, dtype=np.float64))
    if protocol.query_spacing_m > 0:
        queries = select_references(query_seq.poses[:, :3, 3], protocol.query_spacing_m,
                                    query_valid)
    else:
        queries = np.flatnonzero(query_valid)
    queries = queries[::protocol.query_every]
    n_active = np.full(len(queries), len(references))
    if same_sequence or protocol.exclude_recent_frames > 0:
        n_active = np.minimum(n_active, np.searchsorted(
            references, queries - protocol.exclude_recent_frames, "left"))
    if protocol.exclude_recent_s > 0:
        n_active = np.minimum(n_active, np.searchsorted(
            reference.stamps[references], query_seq.stamps[queries] - protocol.exclude_recent_s,
            "right"))
    keep = n_active > 0
    return Selection(references, queries[keep], n_active[keep])


def _in_frames(count: int, frames: tuple[int, int] | None) -> np.ndarray:
    indices = np.arange(count)
    if frames is None:
        return np.ones(count, dtype=bool)
    return (indices >= frames[0]) & (indices <= frames[1])


def _valid_poses(sequence: Sequence) -> np.ndarray:
    if sequence.poses is None:
        raise ValueError(f"{sequence.name}: this source has no poses; evaluation needs them")
    return np.isfinite(sequence.poses).all(axis=(1, 2))


def _stamps_in(stamps: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    if not len(wanted):
        return np.zeros(len(stamps), dtype=bool)
    return nearest_keys(np.sort(wanted), stamps)[1] <= _STAMP_MATCH_S


@dataclass
class _DescribedScan:
    occupancy: np.ndarray
    points: np.ndarray | None
    sensor_offset_m: float = 0.0


class MatchedFilterMethod:
    """MF-LPR (ours): the two-stage matched-filter search and its pose; published closures are
    those verification.MatchVerifier accepts (ICP where the scans have points and the preset
    asks for it, odometry consistency on the sequence's poses)."""

    name = "MF-LPR (ours)"

    def __init__(self, config: Config) -> None:
        self.config = config
        self._index: MatchedFilterIndex | None = None
        self._verifier = MatchVerifier(config.search)

    def describe(self, scan: Scan, *, reference: bool) -> _DescribedScan:
        points = prepared_points(scan, self.config.descriptor) \
            if self.config.search.verify_fitness > 0 and scan.points is not None else None
        return _DescribedScan(describe_scan(scan, self.config.descriptor, reference=reference),
                              points, scan.sensor_offset_m)

    def build(self, descriptors: list, poses: np.ndarray, stamps: np.ndarray) -> None:
        reference_map = ReferenceMap(self.config.descriptor)
        for described, pose, stamp in zip(descriptors, poses, stamps):
            reference_map.append(described.occupancy, pose, float(stamp), len(reference_map),
                                 described.points)
        record_sensor_offset(reference_map, {scan.sensor_offset_m for scan in descriptors})
        self._index = MatchedFilterIndex(reference_map, self.config.search)

    def query(self, descriptor: _DescribedScan, n_active: int, odometry: np.ndarray
              ) -> Retrieval:
        match = self._index.query(descriptor.occupancy, n_active=n_active,
                                  sensor_offset_m=descriptor.sensor_offset_m)
        geometric = None
        if descriptor.points is not None and self._index.map.has_clouds:
            def geometric(found):
                return refine_match(found, descriptor.points, self._index.map).fitness
        verdict = self._verifier.verify(match, odometry, geometric)
        return Retrieval(match.reference_index, match.pose, match.confidence, match.candidates,
                         match.timings_ms["global"], match.timings_ms["local"], verdict.accepted)


class ScanContextMethod:
    """Scan Context (Kim and Kim, IROS 2018): the matched reference's position with the Scan
    Context yaw, so its corrected recall is its retrieval recall. Confidence: 1 - distance."""

    name = "Scan Context"

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
                         published=distance < self._index.params.accept_distance)


class MapClosuresMethod:
    """MapClosures (Gupta et al., the map-closures package): ORB features of BEV density maps in
    an HBST tree, then RANSAC. Fed as its own pipeline feeds it: local maps, not single scans.
    Each scan's local map holds the scans of the last local_map_m metres of travel (those the
    protocol describes, up to and including it), put in that scan's frame with the sequence's
    poses (its pipeline uses kiss-icp odometry instead) and voxelised at its density-map
    resolution. Its pose is not used: the matched reference's position is reported.
    Confidence: RANSAC inliers. Every closure it returns passed its own RANSAC test, so each
    is published."""

    name = "MapClosures"
    candidates_asked = 50

    def __init__(self, config: Config, density_map_resolution: float | None = None,
                 local_map_m: float = 10.0) -> None:
        try:
            from map_closures.config import MapClosuresConfig
            from map_closures.map_closures import MapClosures
        except ImportError as error:
            raise ValueError(f"the MapClosures baseline needs the map-closures package "
                             f"(pip install map-closures): {error}") from error
        resolution = density_map_resolution or max(config.descriptor.voxel_size, 0.1)
        self.config = config
        self.resolution = resolution
        self.local_map_m = local_map_m
        self._closures = MapClosures(MapClosuresConfig(density_map_resolution=resolution))
        self._poses = np.zeros((0, 3))
        self._next_id = 0
        self._recent: dict[bool, deque] = {True: deque(), False: deque()}

    def describe(self, scan: Scan, *, reference: bool) -> np.ndarray:
        points = one_point_per_voxel(points_for_baselines(scan, self.config).astype(np.float64),
                                     self.resolution)
        if scan.pose is None or not np.isfinite(scan.pose).all():
            return points
        recent = self._recent[reference]
        travelled = 0.0
        if recent:
            travelled = recent[-1][0] + float(np.linalg.norm(scan.pose[:3, 3] -
                                                             recent[-1][1][:3, 3]))
        recent.append((travelled, scan.pose, points))
        while travelled - recent[0][0] > self.local_map_m:
            recent.popleft()
        to_scan = np.linalg.inv(scan.pose)
        return one_point_per_voxel(np.concatenate([
            cloud @ (to_scan @ pose)[:3, :3].T + (to_scan @ pose)[:3, 3]
            for _, pose, cloud in recent]), self.resolution)

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


def run_protocol(method, reference: Sequence, selection: Selection, *,
                 query: Sequence | None = None, truth_poses: np.ndarray | None = None,
                 progress: bool = True) -> list[dict[str, Any]]:
    """One record per query (see summarise) for method under a selection.

    The method sees the sequences' poses (the map's poses and each query's odometry);
    truth_poses, the query sequence's ground truth (and the references' in the single-sequence
    protocol), defaults to the same poses.
    """
    same_sequence = query is None
    query_seq = reference if same_sequence else query
    wanted_refs = {int(i): k for k, i in enumerate(selection.references)}
    wanted_queries = set(selection.queries.tolist())
    ref_descriptors: list = [None] * len(wanted_refs)
    query_descriptors: dict[int, tuple[Any, float]] = {}

    def describe_query(scan: Scan) -> None:
        started = time.perf_counter()
        descriptor = method.describe(scan, reference=False)
        query_descriptors[scan.index] = (descriptor, (time.perf_counter() - started) * 1e3)

    to_describe = sorted(set(wanted_refs) | (wanted_queries if same_sequence else set()))
    for scan in progress_bar(reference.iter_scans(to_describe), total=len(to_describe),
                             desc=f"{method.name}: describe", enabled=progress, unit="scan"):
        if scan.index in wanted_refs:
            ref_descriptors[wanted_refs[scan.index]] = method.describe(scan, reference=True)
        if same_sequence and scan.index in wanted_queries:
            describe_query(scan)
    if not same_sequence:
        for scan in progress_bar(query_seq.iter_scans(selection.queries),
                                 total=len(selection.queries),
                                 desc=f"{method.name}: describe queries", enabled=progress,
                                 unit="scan"):
            describe_query(scan)
    method.build(ref_descriptors, reference.poses[selection.references],
                 reference.stamps[selection.references])

    truth_poses = query_seq.poses if truth_poses is None else truth_poses
    ref_planar = planar((truth_poses if same_sequence else reference.poses)[selection.references])
    records = []
    for query_index, n_active in progress_bar(zip(selection.queries, selection.n_active),
                                              total=len(selection.queries),
                                              desc=f"{method.name}: search", enabled=progress,
                                              unit="query"):
        descriptor, descriptor_ms = query_descriptors[int(query_index)]
        retrieval = method.query(descriptor, int(n_active), planar(query_seq.poses[query_index]))
        truth = planar(truth_poses[query_index])
        distances = np.linalg.norm(ref_planar[:n_active, :2] - truth[:2], axis=1)
        found = retrieval.reference
        records.append({
            "query_index": int(query_index),
            "stamp": float(query_seq.stamps[query_index]),
            "truth": truth.tolist(),
            "estimate": np.asarray(retrieval.pose, dtype=float).tolist(),
            "reference_index": int(selection.references[found]) if found >= 0 else -1,
            "nearest_reference_m": float(distances.min()),
            "retrieved_distance_m": float(distances[found]) if found >= 0 else float("inf"),
            "candidate_distances_m": distances[retrieval.candidates[:RECALL_AT_N]].tolist(),
            "rte_m": float(np.hypot(*(retrieval.pose[:2] - truth[:2]))) if found >= 0
            else float("inf"),
            "rre_deg": float(abs(np.degrees(wrap_angle(retrieval.pose[2] - truth[2]))))
            if found >= 0 else float("inf"),
            "confidence": float(retrieval.confidence),
            "published": bool(retrieval.published and found >= 0),
            "ms_descriptor": descriptor_ms,
            "ms_global": retrieval.ms_global,
            "ms_local": retrieval.ms_local,
        })
    return records


def summarise(records: list[dict[str, Any]], tolerance_m: float, n_references: int) -> dict:
    """Metrics of METHOD.md section 5 from per-query records.

    recall_at_1: the retrieved reference lies within tolerance (retrieval recall).
    recall_at_1_corrected: the estimated pose lies within tolerance (the paper's recall).
    recall_at_n[k-1]: one of the best k candidates lies within tolerance.
    RTE/RRE mean and std over successes (RTE < 2 m and RRE < 5 deg among correct retrievals);
    success_rate = successes / correct retrievals (BVMatch). f1_max and pr_curve over the
    confidence: an accepted correct retrieval is a true positive, any other accepted match a
    false positive. recall_vs_threshold: recall as the distance threshold varies (positives
    fixed by tolerance). Timings are medians per query.

    Loop closures as published (each method's own acceptance, MF-LPR's verification):
    closures_published; closures_false, those whose estimated query position lies farther than
    tolerance from the truth (the constraint a pose graph would get is wrong);
    precision_published; recall_published, the positive queries with a correct published
    closure; recall_at_100_precision, the largest recall over confidence thresholds with no
    false match above the threshold (before verification).
    """
    def column(name: str) -> np.ndarray:
        return np.array([r[name] for r in records], dtype=float)

    positive = column("nearest_reference_m") <= tolerance_m
    n_positive = int(positive.sum())
    retrieved = column("retrieved_distance_m") <= tolerance_m
    rte, rre = column("rte_m"), column("rre_deg")
    correct = positive & retrieved
    success = correct & (rte < 2.0) & (rre < 5.0)
    candidate_hits = np.zeros((len(records), RECALL_AT_N), dtype=bool)
    for row, record in enumerate(records):
        hits = np.asarray(record["candidate_distances_m"], dtype=float) <= tolerance_m
        candidate_hits[row, :len(hits)] = hits
    recall_at_n = np.logical_or.accumulate(candidate_hits, axis=1)
    recall_at_n[:, 0] = retrieved

    def rate(mask: np.ndarray) -> float:
        return float(mask[positive].mean()) if n_positive else float("nan")

    def stat(values: np.ndarray, reducer) -> float:
        return float(reducer(values)) if len(values) else float("nan")

    confidence = column("confidence")
    thresholds = np.linspace(0.0, 2.0 * tolerance_m, 41)[1:]
    ms_total = column("ms_descriptor") + column("ms_global") + column("ms_local")
    f1, f1_confidence, curve = precision_recall(confidence, correct, n_positive)
    published = column("published").astype(bool)
    closure_correct = rte <= tolerance_m
    n_published = int(published.sum())
    return {
        "n_queries": n_positive,
        "n_evaluated": len(records),
        "n_references": n_references,
        "tolerance_m": tolerance_m,
        "recall_at_1": rate(retrieved),
        "recall_at_1_corrected": rate(rte <= tolerance_m),
        "recall_at_5": rate(recall_at_n[:, -1]),
        "recall_at_n": [rate(recall_at_n[:, k]) for k in range(RECALL_AT_N)],
        "rte_mean_m": stat(rte[success], np.mean),
        "rte_std_m": stat(rte[success], np.std),
        "rre_mean_deg": stat(rre[success], np.mean),
        "rre_std_deg": stat(rre[success], np.std),
        "success_rate": float(success.sum() / correct.sum()) if correct.any() else float("nan"),
        "f1_max": f1,
        "confidence_at_f1_max": f1_confidence,
        "pr_curve": curve,
        "closures_published": n_published,
        "closures_false": int((published & ~closure_correct).sum()),
        "precision_published": float((published & closure_correct).sum() / n_published)
        if n_published else float("nan"),
        "recall_published": rate(published & closure_correct),
        "recall_at_100_precision": recall_at_full_precision(confidence, closure_correct, positive),
        "recall_vs_threshold": {
            "threshold_m": thresholds.tolist(),
            "retrieval": [rate(column("retrieved_distance_m") <= t) for t in thresholds],
            "corrected": [rate(rte <= t) for t in thresholds]},
        "ms_per_query": stat(ms_total, np.median),
        "ms_descriptor": stat(column("ms_descriptor"), np.median),
        "ms_global": stat(column("ms_global"), np.median),
        "ms_local": stat(column("ms_local"), np.median),
    }


def recall_at_full_precision(confidence: np.ndarray, true_match: np.ndarray,
                             positive: np.ndarray) -> float:
    """The largest recall (true matches among positives) over accept thresholds on confidence
    that accept no false match."""
    if not positive.any():
        return float("nan")
    order = np.argsort(-confidence, kind="stable")
    false_before = np.cumsum(~true_match[order])
    clean = int(np.searchsorted(false_before, 1))
    return float((true_match & positive)[order[:clean]].sum() / positive.sum())


def precision_recall(confidence: np.ndarray, true_match: np.ndarray, n_positive: int
                     ) -> tuple[float, float, dict[str, list[float]]]:
    """(F1max, the confidence threshold reaching it, the precision-recall curve) over accept
    thresholds on confidence."""
    empty = {"precision": [], "recall": [], "confidence": []}
    if n_positive == 0 or len(confidence) == 0:
        return float("nan"), float("nan"), empty
    order = np.argsort(-confidence, kind="stable")
    true_positives = np.cumsum(true_match[order])
    precision = true_positives / np.arange(1, len(order) + 1)
    recall = true_positives / n_positive
    with np.errstate(invalid="ignore", divide="ignore"):
        f1 = np.where(precision + recall > 0, 2 * precision * recall / (precision + recall), 0.0)
    best = int(np.argmax(f1))
    keep = np.unique(np.linspace(0, len(order) - 1, min(len(order), _CURVE_POINTS)).astype(int))
    curve = {"precision": precision[keep].tolist(), "recall": recall[keep].tolist(),
             "confidence": confidence[order][keep].tolist()}
    return float(f1[best]), float(confidence[order][best]), curve


@dataclass
class PairResult:
    """One method on one reference/query pair: the metrics and the per-query records."""

    method: str
    summary: dict
    records: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)


def evaluate(reference: Sequence, config: Config, tolerance_m: float, *,
             query: Sequence | None = None, exclude_recent_frames: int = 0,
             exclude_recent_s: float = 0.0, query_every: int = 1, query_spacing_m: float = 0.0,
             method: str = "mf-lpr", progress: bool = True) -> dict:
    """One method on one pair (or one sequence's loop closures): summarise's metrics."""
    protocol = Protocol(tolerance_m, query_spacing_m=query_spacing_m, query_every=query_every,
                        exclude_recent_frames=exclude_recent_frames,
                        exclude_recent_s=exclude_recent_s)
    return evaluate_pair(reference, config, protocol, query=query, method=method,
                         progress=progress).summary


def evaluate_pair(reference: Sequence, config: Config, protocol: Protocol, *,
                  query: Sequence | None = None, query_stamps: np.ndarray | None = None,
                  method: str = "mf-lpr", progress: bool = True) -> PairResult:
    """evaluate with a full Protocol, keeping the per-query records. Preset auto derives the
    descriptor from the reference sequence (summary["auto"] says what it chose)."""
    selection = select(reference, protocol, config.spacing_m, query=query,
                       query_stamps=query_stamps)
    config, profile = resolve_for_sequence(config, reference)
    runner = make_method(method, config)
    records = run_protocol(runner, reference, selection, query=query, progress=progress)
    summary = summarise(records, protocol.tolerance_m, len(selection.references))
    if profile is not None:
        summary["auto"] = map_metadata(profile, config.descriptor)
    return PairResult(runner.name, summary, records)
