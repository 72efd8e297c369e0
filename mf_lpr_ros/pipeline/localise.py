"""Localising a whole sequence against a map offline, verified as the live localiser verifies."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Iterable

import numpy as np

from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.pose import planar, planar_error
from mf_lpr_ros.core.refine import refine_match
from mf_lpr_ros.core.search import MatchedFilterIndex, MatchResult
from mf_lpr_ros.core.submap import SubmapWindow
from mf_lpr_ros.core.verification import MatchVerifier, Verdict, published_late
from mf_lpr_ros.datasets import Sequence
from mf_lpr_ros.errors import InvalidCloudError
from mf_lpr_ros.params import SearchParams
from mf_lpr_ros.pipeline.mapping import describe_scan, not_described, prepared_points
from mf_lpr_ros.pipeline.submaps import with_submaps
from mf_lpr_ros.progress import progress_bar


@dataclass
class QueryOutcome:
    """One query's match with its timings and, when ground truth exists, its errors. match is
    None for a scan that could not be described (the verdict says why)."""

    index: int
    stamp: float
    match: MatchResult | None
    descriptor_ms: float
    verdict: Verdict
    truth: np.ndarray | None = None

    @property
    def translation_error_m(self) -> float:
        return self._errors()[0]

    @property
    def yaw_error_deg(self) -> float:
        return self._errors()[1]

    def _errors(self) -> tuple[float, float]:
        if self.truth is None or self.match is None:
            return float("nan"), float("nan")
        return planar_error(self.match.pose, self.truth)


def localise_sequence(reference_map: ReferenceMap, sequence: Sequence, search: SearchParams, *,
                      indices: Iterable[int] | None = None, icp: bool = False,
                      progress: bool = True) -> list[QueryOutcome]:
    """Match every (selected) scan of a sequence against a map and verify each match as the
    localiser does (verification.MatchVerifier; the sequence's poses, when every scan has one,
    serve as odometry, and make each scan's submap when the map's descriptor has a window).
    Each scan is a relocalisation request: a weak match is searched again over the
    prefilter's wider list (SearchParams.prefilter_retry). A scan with nothing to describe
    (no point inside the descriptor's window and height band) is passed over, as the live
    localiser passes it over, its outcome saying why.
    icp: refine every pose by ICP against the map's reference clouds."""
    if icp and not reference_map.has_clouds:
        raise ValueError("ICP refinement needs a map that keeps reference clouds "
                         "(build it with --keep-clouds)")
    index = MatchedFilterIndex(reference_map, search)
    odometry_known = sequence.fully_posed
    verifier = MatchVerifier(search, odometry_known=odometry_known,
                             submap_m=reference_map.params.submap_m)
    outcomes = []
    selected = list(range(len(sequence))) if indices is None else list(indices)
    sequence = with_submaps(sequence, SubmapWindow.for_descriptor(reference_map.params))
    for scan in progress_bar(sequence.iter_scans(selected), total=len(selected), desc="localise",
                             enabled=progress, unit="scan"):
        posed = scan.pose is not None and np.isfinite(scan.pose).all()
        truth = planar(scan.pose) if posed else None
        odometry = truth if odometry_known else None
        started = time.perf_counter()
        try:
            occupancy = describe_scan(scan, reference_map.params, reference=False)
        except InvalidCloudError as error:
            # The verifier still travels with the scan's odometry.
            verifier.verify(None, odometry)
            outcomes.append(QueryOutcome(scan.index, scan.stamp, None, math.nan,
                                         Verdict(False, not_described(error)), truth))
            continue
        descriptor_ms = (time.perf_counter() - started) * 1e3
        match = index.query(occupancy, sensor_offset_m=scan.sensor_offset_m, request=True)
        geometric = None
        if reference_map.has_clouds and scan.points is not None:
            points = prepared_points(scan, reference_map.params)

            def geometric(found):
                return refine_match(found, points, reference_map).fitness
        verdict = verifier.verify(match, odometry, geometric, key=len(outcomes))
        for earlier, reason in verdict.confirms.items():
            outcomes[earlier].verdict = published_late(outcomes[earlier].verdict, reason)
        if icp and np.isnan(verdict.fitness) and geometric is not None:
            geometric(match)
        outcomes.append(QueryOutcome(scan.index, scan.stamp, match, descriptor_ms, verdict, truth))
    return outcomes
