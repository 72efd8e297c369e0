"""The evaluation protocol (docs/METHOD.md section 5): which scans are references and queries, and
running a method (evaluation.methods) over them into per-query records (evaluation.metrics).

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

import math
import time
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from mf_lpr_ros.config import Config
from mf_lpr_ros.core.auto_params import map_metadata, resolve_for_sequence
from mf_lpr_ros.core.pose import planar, planar_error
from mf_lpr_ros.core.references import select_references
from mf_lpr_ros.datasets import Scan, Sequence
from mf_lpr_ros.datasets.base import nearest_keys
from mf_lpr_ros.errors import InvalidCloudError
from mf_lpr_ros.evaluation.methods import make_method
from mf_lpr_ros.evaluation.metrics import RECALL_AT_N, QueryRecord, summarise
from mf_lpr_ros.pipeline.mapping import not_described
from mf_lpr_ros.pipeline.submaps import with_submaps
from mf_lpr_ros.progress import progress_bar

_STAMP_MATCH_S = 1e-4
# The world columns a thinned query loses whole (Protocol.query_thinning): about what a scene
# change takes away at once, a parked car or a bush.
THINNING_CELL_M = 2.0


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
    # False where each image is turned by its own unknown yaw while the poses are the
    # unturned scans' (BEVPlace's rotated copies): a retrieval can be scored there, an estimated
    # pose cannot (it carries the reference image's unknown turn), so the summary's pose-based
    # figures are NaN (metrics.POSE_FIGURES), and the search runs with map_headings "unknown".
    headings_known: bool = True
    # True where every query asks where one scan is on the map (BEVPlace's retrieval
    # protocol): each is searched as `mf-lpr localise` and the `~/relocalise` service search a
    # relocalisation request, a weak match searched again over the prefilter's wider list
    # (SearchParams.prefilter_retry). False: as a loop-closure stream searches its scans.
    requests: bool = False
    # Above 0, each query is described as if this fraction of the world's columns had gone
    # since the map was made (thinned_scan), the references whole: a query that sees less of
    # its place than the map did, as after a scene change.
    query_thinning: float = 0.0

    def __post_init__(self) -> None:
        if not self.tolerance_m > 0:
            raise ValueError(f"protocol tolerance_m must be > 0, got {self.tolerance_m}")
        if not 0.0 <= self.query_thinning < 1.0:
            raise ValueError(f"protocol query_thinning must be in [0, 1), got "
                             f"{self.query_thinning}")
        if self.query_every < 1:
            raise ValueError(f"protocol query_every must be >= 1, got {self.query_every}")
        for name in ("reference_frames", "query_frames"):
            frames = getattr(self, name)
            if frames is not None and not 0 <= frames[0] <= frames[1]:
                raise ValueError(f"protocol {name} must be (first, last) with 0 <= first <= "
                                 f"last, got {frames}")


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
    ref_valid = reference.valid_poses("evaluation") & _in_frames(len(reference),
                                                                 protocol.reference_frames)
    spacing = spacing_m if protocol.reference_spacing_m is None else protocol.reference_spacing_m
    references = select_references(reference.poses[:, :3, 3], spacing, ref_valid)
    if not len(references):
        raise ValueError(f"{reference.name}: no scan with a valid pose to use as a reference")
    query_valid = query_seq.valid_poses("evaluation") & _in_frames(len(query_seq),
                                                                   protocol.query_frames)
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


def thinned_scan(scan: Scan, fraction: float) -> Scan:
    """scan as if a fraction of the world's THINNING_CELL_M columns had gone since the map was
    made: each occupied pixel of a density image, or each point, whose world position (by the
    scan's pose) falls in a gone column is emptied. Which columns are gone is fixed in the
    world, so consecutive queries lose the same things, as after a scene change, not each its
    own, as a noisy sensor would."""
    if scan.pose is None:
        raise ValueError(f"scan {scan.index} has no pose: thinning a query needs one, the "
                         f"columns it loses being fixed in the world")
    rotation, origin = scan.pose[:2, :2], scan.pose[:2, 3]
    if scan.density is not None:
        rows, cols = scan.density.shape
        # A pixel's centre from the sensor, which sits sensor_offset_m from the corner before
        # pixel (rows // 2, cols // 2) (datasets.base.Scan).
        y = (np.arange(rows) - rows // 2 + 0.5) * scan.density_pixel_m - scan.sensor_offset_m
        x = (np.arange(cols) - cols // 2 + 0.5) * scan.density_pixel_m - scan.sensor_offset_m
        local = np.stack(np.broadcast_arrays(x[None, :], y[:, None]), axis=-1).reshape(-1, 2)
        gone = _gone_columns(local @ rotation.T + origin, fraction).reshape(rows, cols)
        density = scan.density.copy()
        density[gone] = 0
        return replace(scan, density=density)
    if scan.points is None or not len(scan.points):
        return scan
    world = np.nan_to_num(scan.points[:, :2]) @ rotation.T + origin
    return replace(scan, points=scan.points[~_gone_columns(world, fraction)])


def _gone_columns(world_xy: np.ndarray, fraction: float) -> np.ndarray:
    """(N,) bool: the world positions (N, 2) whose THINNING_CELL_M column is among the gone
    fraction, by a hash of the column (SplitMix64's finaliser): the same columns for every
    scan."""
    cells = np.floor(world_xy / THINNING_CELL_M).astype(np.int64)
    key = (cells[:, 0] * np.int64(1_000_003) + cells[:, 1]).astype(np.uint64)
    key = key + np.uint64(0x9E3779B97F4A7C15)
    key = (key ^ (key >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    key = (key ^ (key >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    key = key ^ (key >> np.uint64(31))
    return (key >> np.uint64(11)).astype(np.float64) / 2.0 ** 53 < fraction


def _in_frames(count: int, frames: tuple[int, int] | None) -> np.ndarray:
    indices = np.arange(count)
    if frames is None:
        return np.ones(count, dtype=bool)
    return (indices >= frames[0]) & (indices <= frames[1])


def _stamps_in(stamps: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    if not len(wanted):
        return np.zeros(len(stamps), dtype=bool)
    return nearest_keys(np.sort(wanted), stamps)[1] <= _STAMP_MATCH_S


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


@dataclass
class ProtocolRun:
    """What run_protocol gives: one record per query, and the scan indices of the references
    left out of the map (nothing to describe)."""

    records: list[QueryRecord]
    references_left_out: list[int]


def run_protocol(method, reference: Sequence, selection: Selection, *,
                 query: Sequence | None = None, truth_poses: np.ndarray | None = None,
                 query_thinning: float = 0.0, progress: bool = True) -> ProtocolRun:
    """One record per query (see summarise) for method under a selection, each query thinned
    first when query_thinning > 0 (Protocol.query_thinning; a scan that is also a reference is
    described whole as one).

    The method sees the sequences' poses (the map's poses, each query's odometry and the
    odometry its submaps are made with); truth_poses, the query sequence's ground truth (and the
    references' in the single-sequence protocol), defaults to the same poses.

    A scan with nothing to describe (InvalidCloudError) is passed over, as the live nodes and
    `localise` pass over it: a reference is left out of the map (its place is still in the
    protocol's ground truth, so a query there can only miss), a query is recorded as a miss
    whose reason says so (mapping.not_described), and the method is told (pass_over).
    """
    same_sequence = query is None
    reference = with_submaps(reference, method.submap_window)
    query_seq = reference if same_sequence else with_submaps(query, method.submap_window)
    wanted_refs = {int(i): k for k, i in enumerate(selection.references)}
    wanted_queries = set(selection.queries.tolist())
    ref_descriptors: list = [None] * len(wanted_refs)
    # Per query scan: its descriptor (None: not described), the time it took, the reason why
    # not.
    query_descriptors: dict[int, tuple[Any, float, str]] = {}

    def describe_query(scan: Scan) -> None:
        if query_thinning > 0:
            scan = thinned_scan(scan, query_thinning)
        started = time.perf_counter()
        try:
            descriptor, problem = method.describe(scan, reference=False), ""
        except InvalidCloudError as error:
            descriptor, problem = None, not_described(error)
        query_descriptors[scan.index] = (descriptor, (time.perf_counter() - started) * 1e3,
                                         problem)

    to_describe = sorted(set(wanted_refs) | (wanted_queries if same_sequence else set()))
    first_reference_problem = ""
    for scan in progress_bar(reference.iter_scans(to_describe), total=len(to_describe),
                             desc=f"{method.name}: describe", enabled=progress, unit="scan"):
        if scan.index in wanted_refs:
            try:
                ref_descriptors[wanted_refs[scan.index]] = method.describe(scan, reference=True)
            except InvalidCloudError as error:
                # Left out of the map (see the docstring).
                first_reference_problem = first_reference_problem or str(error)
        if same_sequence and scan.index in wanted_queries:
            describe_query(scan)
    if not same_sequence:
        for scan in progress_bar(query_seq.iter_scans(selection.queries),
                                 total=len(selection.queries),
                                 desc=f"{method.name}: describe queries", enabled=progress,
                                 unit="scan"):
            describe_query(scan)
    described = np.array([descriptor is not None for descriptor in ref_descriptors])
    if not described.any():
        raise InvalidCloudError(f"{reference.name}: none of the {len(described)} references "
                                f"could be described; the first: {first_reference_problem}")
    # Positions in the map of the described references, and how many precede each selection
    # position (a query may match the first n_active of the selection).
    in_map = np.flatnonzero(described)
    described_before = np.concatenate([[0], np.cumsum(described)])
    mapped = selection.references[in_map]
    method.build([ref_descriptors[k] for k in in_map], reference.poses[mapped],
                 reference.stamps[mapped])

    truth_poses = query_seq.poses if truth_poses is None else truth_poses
    ref_planar = planar((truth_poses if same_sequence else reference.poses)[selection.references])
    records = []
    # The record of each query the method searched, in its order (Retrieval.confirms).
    searched_records: list[int] = []
    for query_index, n_active in progress_bar(zip(selection.queries, selection.n_active),
                                              total=len(selection.queries),
                                              desc=f"{method.name}: search", enabled=progress,
                                              unit="query"):
        descriptor, descriptor_ms, problem = query_descriptors[int(query_index)]
        truth = planar(truth_poses[query_index])
        distances = np.linalg.norm(ref_planar[:n_active, :2] - truth[:2], axis=1)
        n_described = int(described_before[n_active])
        odometry = planar(query_seq.poses[query_index])
        if descriptor is None or not n_described:
            method.pass_over(odometry)
            records.append(_not_searched(
                int(query_index), float(query_seq.stamps[query_index]), truth, distances,
                descriptor_ms, problem if descriptor is None
                else "no reference it may match could be described"))
            continue
        searched_records.append(len(records))
        retrieval = method.query(descriptor, n_described, odometry)
        found = int(in_map[retrieval.reference]) if retrieval.reference >= 0 else -1
        rte, rre = planar_error(retrieval.pose, truth) if found >= 0 else (math.inf, math.inf)
        records.append(QueryRecord(
            query_index=int(query_index),
            stamp=float(query_seq.stamps[query_index]),
            truth=truth.tolist(),
            estimate=np.asarray(retrieval.pose, dtype=float).tolist(),
            reference_index=int(selection.references[found]) if found >= 0 else -1,
            nearest_reference_m=float(distances.min()),
            retrieved_distance_m=float(distances[found]) if found >= 0 else math.inf,
            candidate_distances_m=distances[
                in_map[retrieval.candidates[:RECALL_AT_N]]].tolist(),
            rte_m=rte,
            rre_deg=rre,
            confidence=float(retrieval.confidence),
            published=bool(retrieval.published and found >= 0),
            ms_descriptor=descriptor_ms,
            ms_global=retrieval.ms_global,
            ms_local=retrieval.ms_local,
            distinctiveness=float(retrieval.distinctiveness),
            local_distinctiveness=float(retrieval.local_distinctiveness),
            reason=retrieval.reason,
            searched_nearest_m=_nearest_of(
                distances, None if retrieval.searched is None else in_map[retrieval.searched]),
            place_similarity=float(retrieval.place_similarity),
            position_covariance=_flat_covariance(retrieval.position_covariance)))
        for earlier, (reason, pose, covariance) in retrieval.confirms.items():
            confirmed = records[searched_records[earlier]]
            confirmed.published = True
            confirmed.reason = reason
            confirmed.estimate = np.asarray(pose, dtype=float).tolist()
            confirmed.rte_m, confirmed.rre_deg = planar_error(pose, confirmed.truth)
            confirmed.position_covariance = _flat_covariance(covariance)
    return ProtocolRun(records, selection.references[~described].tolist())


def _flat_covariance(covariance: np.ndarray | None) -> list[float]:
    """QueryRecord.position_covariance of a 2x2 covariance (None: NaN)."""
    if covariance is None:
        return [math.nan] * 3
    return [float(covariance[0, 0]), float(covariance[0, 1]), float(covariance[1, 1])]


def _not_searched(query_index: int, stamp: float, truth: np.ndarray, distances: np.ndarray,
                  descriptor_ms: float, reason: str) -> QueryRecord:
    """The record of a query that could not be searched: a miss, for the reason given."""
    return QueryRecord(
        query_index=query_index, stamp=stamp, truth=truth.tolist(),
        estimate=[math.nan] * 3, reference_index=-1,
        nearest_reference_m=float(distances.min()), retrieved_distance_m=math.inf,
        candidate_distances_m=[], rte_m=math.inf, rre_deg=math.inf, confidence=0.0,
        published=False, ms_descriptor=descriptor_ms, ms_global=math.nan, ms_local=math.nan,
        reason=reason, searched_nearest_m=math.inf)


def _nearest_of(distances: np.ndarray, references: np.ndarray | None) -> float:
    """The smallest of distances at references (inf for none; NaN when references is None)."""
    if references is None:
        return math.nan
    references = np.asarray(references, dtype=np.int64)
    return float(distances[references].min()) if len(references) else math.inf


@dataclass
class PairResult:
    """One method on one reference/query pair: the metrics and the per-query records."""

    method: str
    summary: dict
    records: list[QueryRecord] = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, saved: dict) -> "PairResult":
        return cls(saved["method"], saved["summary"],
                   [QueryRecord(**record) for record in saved["records"]])


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
    # Either side may know that the map's yaws are not its views': the protocol (a dataset's
    # turned copy) tells the search, a configuration saying so leaves the poses unscored.
    headings_known = protocol.headings_known and config.search.map_headings == "known"
    if not headings_known:
        config = replace(config, search=replace(config.search, map_headings="unknown"))
    if protocol.requests:
        config = replace(config, search=replace(config.search, prefilter_retry="every_query"))
    runner = make_method(method, config)
    run = run_protocol(runner, reference, selection, query=query,
                       query_thinning=protocol.query_thinning, progress=progress)
    summary = summarise(run.records, protocol.tolerance_m, len(selection.references),
                        poses_scored=headings_known)
    summary["references_not_described"] = len(run.references_left_out)
    if profile is not None:
        summary["auto"] = map_metadata(profile, config.descriptor)
    return PairResult(runner.name, summary, run.records)
