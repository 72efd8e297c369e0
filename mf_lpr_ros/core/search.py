"""Two-stage matched-filter search and pose estimation (docs/METHOD.md sections 2 and 3)."""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from mf_lpr_ros.core.backends import make_backend
from mf_lpr_ros.core.descriptor import (
    TurnedPooling,
    footprint,
    observed_cells,
    pool,
    pooled_weights,
    prepare_rotations,
    quarter_turn_roots,
    rotate_occupancy,
    rotation_key,
    turns_with_sensor,
    weighted,
)
from mf_lpr_ros.core.map_store import GLOBAL_MAP_KIND, ReferenceMap
from mf_lpr_ros.core.matched_filter import PreparedQueries, SpectralBank
from mf_lpr_ros.core.peak import inverse_2x2, smallest_eigenvalue, subcell_peak, subsample_peak
from mf_lpr_ros.core.pose import (
    alignment_from_poses,
    planar,
    planar_error,
    query_pose_from_alignment,
    reference_distance,
    rotate_covariance,
    wrap_angle,
)
from mf_lpr_ros.core.prefilter_cache import cache_path, load_features, save_features
from mf_lpr_ros.params import SearchParams
from mf_lpr_ros.progress import progress_bar

# Scale from normalised peak curvature to variance: a peak whose score halves one cell away
# gets a standard deviation of ~0.3 cell before inflation by low confidence.
_CURVATURE_TO_VARIANCE = 0.1
_MIN_CONFIDENCE_FOR_COVARIANCE = 0.05
_REPORTED_CANDIDATES = 5
# How far down the global ranking another_place_finalist looks for another place: with
# references 2 m apart one place's views fill the first ~8 (KITTI 00).
_RANKED_FOR_ANOTHER_PLACE = 12
_EXPANDED_LEADERS = 16
# Map neighbours the candidate stage left out that a nearer view is looked for among, where
# the map's headings are unknown (_nearer_neighbours): along a route, one on each side.
_UNSEARCHED_NEIGHBOURS = 2
# Map neighbours that estimate a reference's heading (_estimate_headings): the farthest ones
# in reach, where a shift's error turns the direction between the two views least.
_HEADING_NEIGHBOURS = 4
_HEADING_BASELINE_M = 2.0
# search.reference_spectra "auto": spectra in memory up to this many references (~0.9 GB).
ON_DEMAND_ABOVE = 50_000
_INDEX_BLOCKS_WITHOUT_PROGRESS = 16
_HEADINGS_WITHOUT_PROGRESS = 500


def _overlap(image: np.ndarray, di: int, dj: int) -> tuple[slice, slice, np.ndarray]:
    """(rows, cols, the part of image they meet once it is moved by (di, dj)): a query's cells
    q[rows, cols] face that part of a reference (correlation index: q(x) with r(x + d))."""
    height, width = image.shape
    rows = slice(max(0, -di), min(height, height - di))
    cols = slice(max(0, -dj), min(width, width - dj))
    return rows, cols, image[rows.start + di:rows.stop + di, cols.start + dj:cols.stop + dj]


def _norm_under(image: np.ndarray, mask: np.ndarray, di: int, dj: int) -> float:
    """Norm of image over the cells mask covers once moved by (di, dj): the part of a reference
    a query's footprint overlaps at that alignment."""
    rows, cols, shifted = _overlap(image, di, dj)
    return float(np.sqrt(np.sum(np.square(shifted, dtype=np.float64)[mask[rows, cols]])))


def _correlation_at(query: np.ndarray, reference: np.ndarray, di: int, dj: int) -> float:
    """The plain correlation of query with reference moved by (di, dj)."""
    rows, cols, shifted = _overlap(reference, di, dj)
    return float(np.sum(query[rows, cols] * shifted, dtype=np.float64))


@dataclass
class Hypothesis:
    """One finalist of the local stage: its reference, the query pose it implies (x, y, yaw in
    the map frame), its local score and confidence."""

    reference_index: int
    pose: np.ndarray
    score: float
    confidence: float


@dataclass
class MatchResult:
    """The best reference for a query and the pose it implies.

    shift_m, rotation_rad: the query sensor's position and heading in the reference's sensor
    frame (the loop-closure constraint). pose: (x, y, yaw) of the query in the map frame.
    covariance / relative_covariance: 3x3 over (x, y, yaw) in the map / reference frame.
    score: local peak score, normalised as SearchParams.score_normalisation says.
    confidence: cosine similarity of query and reference at the best alignment, in [0, 1].
    distinctiveness: 1 - (best global score of another place) / (the match's global score),
        in [0, 1]; near 0 when another place scores as well (a look-alike), and 0 when no
        other place was searched (nothing to tell the match apart from). Another place: a
        reference farther than SearchParams.distinct_radius_m from the match's, except, for a
        match that passes min_confidence and would fail min_distinctiveness, the best of
        those (up to distinct_aligned_rivals) whose own alignment puts the query where the
        match does (same_place): the same answer seen from farther away.
    local_distinctiveness: the same comparison at the local stage's resolution: 1 - (local
        score of the best other place: the best-scoring one of the global stage, aligned as
        a finalist is, or another place aligned already that scored higher) / (the match's
        local score). Computed only where verification asks for it (min_local_distinctiveness
        > 0, confidence passes and distinctiveness does not); NaN otherwise.
    candidates: reference indices by rank (the match first, then the global ranking).
    hypotheses: the local stage's finalists (SearchParams.top_n, and the nearest place when
        re-ranking aligned it), the match first, the others by local score, each with the
        pose it implies; a reported nearer reference stands for the finalist it confirmed
        (one answer, listed once).
    scored_reference: when the nearest-place re-ranking reports a nearer reference that
        confirmed the match, the reference whose alignment gave the pose, score and confidence
        (geometric verification tests that one); None: reference_index itself.
    searched: the references the candidate stage handed to the exact global stage (the
        prefilter's list and its map neighbours); None: every active reference was searched.
        A true place missing from it can be reported only as the place nearest the match
        (the re-ranking): what the candidate stage loses.
    revisit_predicted: the revisit check (SearchParams.revisit_check) reported this reference
        in place of a look-alike the images could not tell apart from it: where the stream's
        revisit, carried along the odometry, put the scan.
    place_similarity: how alike the map's own views of the matched place are
        (MatchedFilterIndex.place_similarity of the scored reference), the yardstick of
        SearchParams.min_relative_confidence. Measured only for a match under min_confidence
        (the relative test is needed nowhere else); NaN otherwise, and where the place has no
        other view within distinct_radius_m.
    """

    reference_index: int
    score: float
    confidence: float
    shift_m: np.ndarray
    rotation_rad: float
    pose: np.ndarray
    covariance: np.ndarray
    relative_covariance: np.ndarray
    candidates: np.ndarray
    distinctiveness: float = 1.0
    local_distinctiveness: float = math.nan
    hypotheses: list[Hypothesis] = field(default_factory=list)
    timings_ms: dict[str, float] = field(default_factory=dict)
    scored_reference: int | None = None
    searched: np.ndarray | None = None
    place_similarity: float = math.nan
    revisit_predicted: bool = False


def passes_confidence(confidence: float, place_similarity: float, search: SearchParams) -> bool:
    """The confidence test: min_confidence, or else min_relative_confidence of the place's
    similarity (a NaN similarity fails the relative part)."""
    return confidence >= search.min_confidence or (
        search.min_relative_confidence > 0
        and confidence >= search.min_relative_confidence * place_similarity)


def distinct(match: MatchResult, search: SearchParams) -> bool:
    """The distinctiveness test: at the global stage's resolution, or else at the local
    stage's (SearchParams.min_local_distinctiveness; a NaN local figure fails)."""
    return (match.distinctiveness >= search.min_distinctiveness
            or (search.min_local_distinctiveness > 0
                and match.local_distinctiveness >= search.min_local_distinctiveness))


def same_place(implied: np.ndarray, other: np.ndarray, search: SearchParams
               ) -> "np.ndarray | bool":
    """Whether planar poses (..., 3) that alignments imply put the query at the same place
    and heading (broadcast): within rerank_agreement_m, and turned by at most
    local_rotation_range_deg (which the local stage would not search). A position alone is
    not the same answer: an alignment turned half round can land on the match's spot by
    chance, and where the map has drifted between two visits it does so more often
    (docs/RESULTS.md, session 55)."""
    apart, turned_deg = planar_error(implied, other)
    return (apart <= search.rerank_agreement_m) & (turned_deg <= search.local_rotation_range_deg)


def within_tolerance(predicted: np.ndarray, estimate: np.ndarray, search: SearchParams
                     ) -> "np.ndarray | bool":
    """Whether planar poses (..., 3) agree as odometry consistency asks: within
    consistency_tolerance_m and consistency_tolerance_deg of estimate."""
    position_gap, yaw_gap_deg = planar_error(predicted, estimate)
    return ((position_gap <= search.consistency_tolerance_m)
            & (yaw_gap_deg <= search.consistency_tolerance_deg))


def reads_spectra_on_demand(search: SearchParams, n_references: int) -> bool:
    """Whether a search of a map of n_references computes each query's candidates' spectra
    from the map instead of keeping every reference's (search.reference_spectra): then only
    the prefilter's features stay in memory, cached beside a map file (cache_prefilter)."""
    return search.reference_spectra == "on_demand" or (
        search.reference_spectra == "auto" and search.prefilter_top_k > 0
        and n_references > ON_DEMAND_ABOVE)


def cache_prefilter(map_path: Path, search: SearchParams, n_references: int | None = None
                    ) -> str | None:
    """The prefilter's features of the map saved at map_path, written beside it now as the
    first search of it would write them, so that a localiser's first start on a map built
    offline takes what a restart takes (a 1 km^2 grid: ~27 s to compute them, ~0.5 s to
    read them). What was done (MatchedFilterIndex.prefilter_cache_status), or None for a map
    whose search keeps its spectra in memory and caches nothing. n_references, where the
    caller knows it: such a map is not even opened."""
    if n_references is not None and not reads_spectra_on_demand(search, n_references):
        return None
    # Just written by the caller: its checksums (a whole read of the file) are checked by
    # every start that loads it, not here.
    reference_map = ReferenceMap.load(map_path, verify=False)
    if not reads_spectra_on_demand(search, len(reference_map)):
        return None
    return MatchedFilterIndex(reference_map, search).prefilter_cache_status


class MatchedFilterIndex:
    """Searches a ReferenceMap; reference spectra are computed once, when references arrive."""

    def __init__(self, reference_map: ReferenceMap, search: SearchParams) -> None:
        self.map = reference_map
        self.params = reference_map.params
        self.search = search
        self.covered = footprint(self.params)
        self.covered_window = footprint(dataclasses.replace(self.params, field_of_view_deg=360.0))
        if self.covered_window is None:
            self.covered_window = np.ones((self.params.size,) * 2, dtype=bool)
        self._map_offset = np.full(2, float(reference_map.metadata.get("sensor_offset_m", 0.0)))
        self._query_offset = np.zeros(2)
        # A rendered reference is a complete view; only a query's own view holds evidence.
        self.observed_queries = search.query_footprint == "observed" or (
            search.query_footprint == "auto"
            and reference_map.metadata.get("kind") == GLOBAL_MAP_KIND)
        low_cell = self.params.voxel_size * self.params.pool
        self.low_shift = min(math.ceil(search.max_shift_m / low_cell), self.params.low_size - 1)
        self.high_shift = min(math.ceil(search.max_shift_m / self.params.voxel_size),
                              self.params.size - 1)
        n_rotations = round(360 / search.rotation_step_deg)
        self.global_angles = np.arange(n_rotations) * search.rotation_step_deg
        if turns_with_sensor(self.params):
            # Two views of a limited field of view turned by more than its width share no
            # ground: those rotations can only produce false matches.
            turn = (self.global_angles + 180.0) % 360.0 - 180.0
            self.global_angles = self.global_angles[np.abs(turn) < self.params.field_of_view_deg]
        half = search.local_rotation_range_deg
        step = search.local_rotation_step_deg
        n_side = int(np.floor(half / step + 1e-9))
        self.local_offsets = np.arange(-n_side, n_side + 1) * step
        # Every rotation table a query can need (the global set and one local set per global
        # angle), now: memory is then fixed from the first query of a long run.
        self._prepared_angle_sets = prepare_rotations(
            self.params.size, [self.global_angles] + [angle + self.local_offsets
                                                      for angle in self.global_angles])
        size = self.params.low_size
        self.spectra_on_demand = reads_spectra_on_demand(search, len(reference_map))
        # On demand, the bank holds one query's candidates at a time.
        capacity = search.prefilter_top_k if self.spectra_on_demand else len(reference_map)
        backend = make_backend(search.backend, size, self.low_shift, max(capacity, 1),
                               prefilter=search.prefilter_top_k > 0,
                               local_size=self.params.size, local_shift=self.high_shift,
                               threads=search.threads, local_sharpening=search.local_sharpening)
        self.backend = backend.name
        self.bank, self.prefilter = backend.bank, backend.prefilter
        # The candidate stage's second opinion on the prefilter's list (_rescored): small
        # enough for the host on any backend.
        self.coarse_bank = SpectralBank(
            size // 2, size // 2,
            min(math.ceil(search.max_shift_m / (2 * low_cell)), size // 2 - 1),
            search.prefilter_rescore_k if self.spectra_on_demand else len(reference_map),
            backend.workers,
        ) if 0 < search.prefilter_top_k < search.prefilter_rescore_k else None
        self._local_correlation = backend.local
        # The global headings the query is turned to, and the quarter turns (np.rot90) of
        # those that give the rest exactly (quarter_turn_roots): where the footprint does not
        # turn and a quarter turn leaves it as it is, 52 of the 72 headings are laid out, not
        # turned, and their spectra likewise (SpectralBank.quarter_turned).
        self._heading_roots, self._heading_turns = (
            quarter_turn_roots(self.params.size, self.global_angles)
            if self._footprint_keeps_quarter_turns() else
            (np.arange(len(self.global_angles)), np.zeros(len(self.global_angles), dtype=int)))
        self._root_headings = np.flatnonzero(self._heading_turns == 0)
        # Every root heading at once from the occupied cells, where the footprint does not turn.
        self._turned_pooling = (
            TurnedPooling(self.params.size, self.global_angles[self._root_headings],
                          self.params.pool, self.params.unoccupied_weight, self.covered)
            if self.params.pool > 1 and (self.covered is None or not turns_with_sensor(
                self.params)) else None)
        self._workers = backend.workers
        # The query's footprint, and the query turned to each local-stage angle used so far:
        # finalists of one query mostly share their headings. New at every query.
        self._query_views = _Views(None)
        # The query's low-resolution weights at each global heading, made once per query
        # (those _pooled_made marks): the candidate stage and the global stage mostly need the
        # same headings.
        self._pooled_turns = np.empty((len(self.global_angles), size, size), dtype=np.float32)
        self._pooled_made = np.zeros(len(self.global_angles), dtype=bool)
        self.bank.reserve_operator(len(self.global_angles))
        self._query_lock = threading.Lock()
        self._indexed = 0
        self._positions: cKDTree | None = None
        # place_similarity by reference: (the view it was measured from, the figure).
        self._place_similarity: dict[int, tuple[int, float]] = {}
        # The references' estimated headings (radians), where the map's are unknown and could
        # be estimated (SearchParams.estimate_map_headings); None: the poses' own, or unknown.
        self._headings: np.ndarray | None = None
        self._headings_checked = 0
        # What became of the prefilter cache beside the map file (on demand only).
        self.prefilter_cache_status = "not used"
        self.sync()

    def __len__(self) -> int:
        return self._indexed

    @property
    def nbytes(self) -> int:
        return self.bank.nbytes + (self.prefilter.nbytes if self.prefilter is not None else 0)

    def sync(self, block: int = 1024) -> int:
        """Index references added to the map since the last call; returns how many."""
        start, stop = self._indexed, len(self.map)
        if start == stop:
            return 0
        restored = self._restore_prefilter() if start == 0 else 0
        if start == 0 and self.prefilter is not None:
            # The map's size is known once, at the first index; a growing map's references
            # come one sync at a time, and the bank doubles for them.
            self.prefilter.reserve(stop)
        first_blocks = range(start + restored, stop, block)
        for first in progress_bar(first_blocks, desc="index references", unit="block",
                                  enabled=len(first_blocks) > _INDEX_BLOCKS_WITHOUT_PROGRESS):
            last = min(first + block, stop)
            low = self._low_references(slice(first, last))
            if not self.spectra_on_demand:
                self.bank.append(low)
                if self.coarse_bank is not None:
                    self.coarse_bank.append(pool(low, 2))
            if self.prefilter is not None:
                self.prefilter.append(low)
        if start == 0 and not restored and self._caches_prefilter():
            saved = save_features(cache_path(self.map.source_path), self.map.content_key,
                                  self.prefilter.stored_features[:, : self.map.source_references])
            self.prefilter_cache_status = f"{self.prefilter_cache_status}; {saved}"
        self._indexed = stop
        return stop - start

    def _low_references(self, references: slice | np.ndarray) -> np.ndarray:
        return pooled_weights(self.map.occupancy(references), self.params.unoccupied_weight,
                              self.params.pool, self.covered)

    def _low_in_order(self, references: np.ndarray) -> np.ndarray:
        """_low_references of references, in their order, the map read in file order."""
        by_position = np.argsort(references)
        low = np.empty((len(references),) + (self.params.low_size,) * 2, dtype=np.float32)
        low[by_position] = self._low_references(references[by_position])
        return low

    def _caches_prefilter(self) -> bool:
        return (self.spectra_on_demand and self.prefilter is not None
                and self.map.source_path is not None and self.map.source_references > 0)

    def _restore_prefilter(self) -> int:
        """How many references' prefilter features came from the cache beside the map."""
        if not self._caches_prefilter():
            return 0
        shape = (self.prefilter.n_harmonics, self.map.source_references, self.prefilter.n_radii)
        features, self.prefilter_cache_status = load_features(
            cache_path(self.map.source_path), self.map.content_key, shape)
        if features is None:
            return 0
        self.prefilter.adopt(features)
        return self.map.source_references

    def query(self, occupancy: np.ndarray, n_active: int | None = None, *,
              sensor_offset_m: float = 0.0, request: bool = False,
              revisit_places: Callable[[MatchResult], np.ndarray] | None = None
              ) -> MatchResult | None:
        """Match one query occupancy (D x D bool, no patch cap) against references [0, n_active).

        sensor_offset_m: the query's Scan.sensor_offset_m; the map's is in its metadata. Both
        enter the pose: the alignment maps descriptor cells, and a sensor off the cell corner
        turns with the query.
        request: the query answers a relocalisation request (the scan is expected inside the
        map, and the answer may take longer): a weak match is searched again over the
        prefilter's wider list (SearchParams.prefilter_retry).
        revisit_places: under prefilter_retry "revisits", where a stream's revisit puts the
        scan when it contradicts a weak match ((k, 2) map positions, MatchVerifier.
        revisit_places): when the map holds a reference within max_shift_m of one, the scan
        retries as a request does.
        Returns None when there is no reference to search. One query at a time per index: the
        query operators' buffers are shared.
        """
        with self._query_lock:
            self._estimate_headings()
            self._query_offset = np.full(2, float(sensor_offset_m))
            self._query_views = _Views(self._seen(occupancy))
            self._pooled_made[:] = False
            with self._workers.own_cores():
                return self._query(occupancy, n_active, request, revisit_places)

    def _query(self, occupancy: np.ndarray, n_active: int | None, request: bool,
               revisit_places: Callable[[MatchResult], np.ndarray] | None = None
               ) -> MatchResult | None:
        n_refs = len(self) if n_active is None else min(n_active, len(self))
        if n_refs <= 0:
            return None
        top_k, retry_top_k = self.search.prefilter_top_k, self.search.prefilter_retry_top_k
        result = self._search(occupancy, n_refs, top_k)
        if (self.prefilter is not None and n_refs > top_k and retry_top_k > top_k
                and not passes_confidence(result.confidence, result.place_similarity,
                                          self.search)
                and self._retries(result, request, revisit_places, n_refs)):
            # Where the prefilter left the true place out, the match found instead is weak
            # (SearchParams.prefilter_retry_top_k): search its wider list.
            first_ms = result.timings_ms
            result = self._search(occupancy, n_refs, retry_top_k)
            result.timings_ms = {stage: ms + first_ms[stage]
                                 for stage, ms in result.timings_ms.items()}
        if (self.search.revisit_check and revisit_places is not None
                and not self._headings_unknown
                and not (passes_confidence(result.confidence, result.place_similarity,
                                           self.search) and distinct(result, self.search))):
            result = self._revisit_checked(occupancy, result, revisit_places(result), n_refs)
        return result

    def _revisit_checked(self, occupancy: np.ndarray, match: MatchResult, places: np.ndarray,
                         n_refs: int) -> MatchResult:
        """SearchParams.revisit_check: the reference nearest each place where the stream's
        revisit puts the scan ((k, 3) planar map poses; none where the match agrees with it),
        aligned by the local stage at the turn that place implies; the best of those whose
        alignment puts the query at that place (within consistency_tolerance_m and _deg) and
        scores within min_distinctiveness of the match is reported instead, as a match the
        images alone do not tell apart (distinctiveness 0): the verifier publishes it only
        where a confirmed closure vouches for it. Else the match as it was. Not where the
        map's headings are unknown: a place's turn there names no reference's view."""
        started = time.perf_counter()
        search = self.search
        floor = (1.0 - search.min_distinctiveness) * match.score
        checked: MatchResult | None = None
        for place in np.asarray(places, dtype=np.float64):
            nearest, distance = self._nearest_reference(place[:2], n_refs)
            if distance > search.max_shift_m:
                continue
            turn = math.degrees(place[2] - self._planar_poses(nearest)[2])
            peak = self._local(occupancy, nearest, self._snapped_global_angle(turn))
            if peak.score < floor or (checked is not None and peak.score <= checked.score):
                continue
            aligned = self._result(peak, match.candidates)
            if within_tolerance(aligned.pose, place, search):
                checked = aligned
        if checked is None:
            return match
        if (checked.confidence < search.min_confidence and search.min_relative_confidence > 0):
            checked.place_similarity = self._place_similarity_of(checked.reference_index,
                                                                 n_refs)
        checked.distinctiveness = 0.0
        checked.revisit_predicted = True
        # The place's reference may have been a finalist too: one answer, listed once.
        checked.hypotheses = [Hypothesis(checked.reference_index, checked.pose, checked.score,
                                         checked.confidence)] + [
            other for other in match.hypotheses
            if other.reference_index != checked.reference_index]
        checked.timings_ms = dict(match.timings_ms)
        checked.timings_ms["local"] += (time.perf_counter() - started) * 1e3
        checked.searched = match.searched
        return checked

    def _retries(self, weak: MatchResult, request: bool,
                 revisit_places: Callable[[MatchResult], np.ndarray] | None,
                 n_refs: int) -> bool:
        """Whether a weak match is searched again (SearchParams.prefilter_retry): under
        "revisits", where the revisit puts the scan at a place the map holds (a reference
        among the first n_refs within max_shift_m, where the search could align it); a
        revisit carried on past the mapped route puts it nowhere the map can answer."""
        mode = self.search.prefilter_retry
        if request or mode == "every_query":
            return True
        if mode != "revisits" or revisit_places is None:
            return False
        return any(self._nearest_reference(place[:2], n_refs)[1] <= self.search.max_shift_m
                   for place in revisit_places(weak))

    def _search(self, occupancy: np.ndarray, n_refs: int, top_k: int) -> MatchResult:
        """The two stages over the prefilter's top_k candidates (every reference when the
        prefilter is off or top_k covers them all)."""
        started = time.perf_counter()
        prefiltered = self.prefilter is not None and n_refs > top_k
        headings, allowed = np.arange(len(self.global_angles)), None
        if prefiltered:
            # global_angles[0] is 0: the unrotated query.
            upright = self._turned_and_pooled(occupancy, headings[:1])[0]
            searched = self._candidates(occupancy, upright, n_refs, top_k)
            allowed = self._allowed_headings(upright, searched)
            scored = None if allowed is None else allowed.any(axis=0)
            if scored is not None and not scored.all():
                # Only the headings some candidate is scored at are turned: along a route the
                # candidates face alike (KITTI 00: ~26 of 72).
                headings = np.flatnonzero(scored)
                allowed = allowed[:, headings]
        else:
            searched = np.arange(n_refs)
        prefilter_done = time.perf_counter()
        candidates = None
        if self.spectra_on_demand:
            # Column k is searched[k].
            self.bank.refill(self._low_in_order(searched))
            columns = np.arange(len(searched))
        else:
            columns = searched
        if allowed is not None:
            # The query turned to its headings, and their spectra, beside the candidates'
            # spectra: one thread each.
            prepared, candidates = self._workers.each(
                lambda: self.bank.prepare_queries(
                    self._turned_and_pooled(occupancy, headings), pairs=True,
                    turned_from=self._turned_from(headings)),
                lambda: self.bank.candidate_spectra(columns))
        else:
            prepared = self.bank.prepare_queries(self._turned_and_pooled(occupancy, headings))
        # Scores that fit one chunk come back with them (volume): the finalists are located in
        # them, not correlated a second time.
        scores, volume = self.bank.best_of_subset(prepared, columns, self.search.chunk_size,
                                                  allowed, candidates)
        scores = self._normalised(scores, self.bank.norms[columns])
        n_ranked = min(max(self.search.top_n, _REPORTED_CANDIDATES,
                           _RANKED_FOR_ANOTHER_PLACE if self.search.another_place_finalist
                           else 0), len(searched))
        order = np.argpartition(-scores, n_ranked - 1)[:n_ranked]
        order = order[np.argsort(-scores[order], kind="stable")]
        ranked = searched[order]
        global_done = time.perf_counter()

        def locate(positions: np.ndarray) -> np.ndarray:
            """The global stage's best alignment of searched[positions] (bank.locate rows)."""
            return (self.bank.peaks(volume, positions) if volume is not None
                    else self.bank.locate(prepared, columns[positions],
                                          None if allowed is None else allowed[positions]))

        def local_peaks(positions: np.ndarray, located: np.ndarray | None = None
                        ) -> list[_LocalPeak]:
            """The local stage on searched[positions], each at its global heading."""
            located = locate(positions) if located is None else located
            return self._local_peaks(occupancy, [
                (int(reference), float(self.global_angles[headings[int(row[0])]]))
                for reference, row in zip(searched[positions], located)])

        peaks = local_peaks(*self._finalists(order, scores, searched, headings, locate))
        peaks.sort(key=lambda peak: -peak.score)
        finalists = peaks
        result = self._result(peaks[0], ranked)
        nearer = self._nearest_place(occupancy, result, peaks, ranked, searched, columns,
                                     prepared, headings, volume, n_refs)
        match_pose = result.pose
        if nearer is not None:
            result = self._reported_at(result, nearer.reference, ranked)
            peaks = [nearer] + [other for other in peaks if other is not nearer]
        aligned = {peak.reference: peak for peak in peaks}

        def align(position: int) -> _LocalPeak:
            """searched[position] through the local stage, once per query."""
            reference = int(searched[position])
            if reference not in aligned:
                aligned[reference] = local_peaks(np.array([position]))[0]
            return aligned[reference]

        if (result.confidence < self.search.min_confidence
                and self.search.min_relative_confidence > 0):
            result.place_similarity = self._place_similarity_of(finalists[0].reference, n_refs)
        result.distinctiveness, result.local_distinctiveness = self._distinctiveness_tests(
            searched, scores, finalists[0], match_pose,
            passes_confidence(result.confidence, result.place_similarity, self.search), ranked,
            align, aligned)
        result.hypotheses = [Hypothesis(result.reference_index, result.pose, result.score,
                                        result.confidence)]
        for peak in peaks[1:]:
            if peak.reference == result.scored_reference:
                continue
            other = self._result(peak, ranked)
            result.hypotheses.append(Hypothesis(other.reference_index, other.pose, other.score,
                                                other.confidence))
        result.timings_ms = {"global": (global_done - started) * 1e3,
                             "prefilter": (prefilter_done - started) * 1e3,
                             "local": (time.perf_counter() - global_done) * 1e3}
        result.searched = searched if prefiltered else None
        return result

    def _finalists(self, order: np.ndarray, scores: np.ndarray, searched: np.ndarray,
                   headings: np.ndarray, locate: Callable[[np.ndarray], np.ndarray]
                   ) -> tuple[np.ndarray, np.ndarray | None]:
        """The positions (in searched) the local stage aligns, and their global alignments when
        located already: the top_n best-ranked; with another_place_finalist, the last of them
        is instead the best-ranked candidate after the first top_n - 1 whose alignment puts the
        query at another place than theirs, when one scores within min_distinctiveness of the
        best (a rival that would leave the match indistinct) among the first
        _RANKED_FOR_ANOTHER_PLACE. Not where the map's headings are unknown: an alignment puts
        the query nowhere in the map frame there, and the finalists are what a nearer view is
        reported from (_nearest_by_distances)."""
        top_n = self.search.top_n
        best = float(scores[order[0]]) if len(order) else 0.0
        rivals = int(np.count_nonzero(
            scores[order[top_n - 1:]] >= (1.0 - self.search.min_distinctiveness) * best))
        if (not self.search.another_place_finalist or self._headings_unknown
                or top_n < 2 or best <= 0 or rivals < 2):
            return order[:top_n], None
        eligible = order[: top_n - 1 + rivals]
        # Located top_n at a time: where the whole volume is not at hand (a map searched whole
        # in more than one chunk), each costs a correlation at every heading.
        located = locate(eligible[:top_n])
        while True:
            elsewhere = np.flatnonzero(self._at_another_place(
                searched[eligible[: len(located)]], located, headings, top_n - 1))
            if len(elsewhere) or len(located) == len(eligible):
                break
            located = np.concatenate([located, locate(
                eligible[len(located): len(located) + top_n])])
        chosen = np.append(np.arange(top_n - 1), elsewhere[0] if len(elsewhere) else top_n - 1)
        return eligible[chosen], located[chosen]

    def _at_another_place(self, references: np.ndarray, located: np.ndarray,
                          headings: np.ndarray, first: int) -> np.ndarray:
        """(len(references),) bool: the global alignment of each reference (located rows)
        puts the query at another place than those of the first `first` do: farther than
        rerank_agreement_m, or turned by more than local_rotation_range_deg (which the local
        stage would not search)."""
        shift_m, rotation = self._global_alignment(located, headings)
        implied = query_pose_from_alignment(self._planar_poses(references), shift_m,
                                            rotation)
        return ~same_place(implied[:, None], implied[None, :first], self.search).any(axis=1)

    def _global_alignment(self, located: np.ndarray, headings: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray]:
        """The shifts in metres (n, 2) and rotations in radians (n,) of global alignments
        (bank.locate rows)."""
        rotation = np.radians(self.global_angles[headings[located[:, 0].astype(np.int64)]])
        # located rows are (query, di, dj, score): di along y, dj along x, in pooled cells.
        return self._shift_m(located[:, [2, 1]] * (self.params.pool * self.params.voxel_size),
                             rotation), rotation

    def _shift_m(self, peak_m: np.ndarray, rotation: np.ndarray | float) -> np.ndarray:
        """The alignment's shift in metres (..., 2) from a correlation peak's offset in metres
        (..., 2) at rotation (radians, ...): the sensors' offsets from their cells' centres
        corrected, the query's turned with it."""
        cos, sin = np.cos(rotation), np.sin(rotation)
        query_x, query_y = self._query_offset
        turned = np.stack([cos * query_x - sin * query_y, sin * query_x + cos * query_y],
                          axis=-1)
        return peak_m + turned - self._map_offset

    def _allowed_headings(self, low_query: np.ndarray, searched: np.ndarray,
                          window: float | None = None) -> np.ndarray | None:
        """(len(searched), global angles) bool: the headings within window (default
        global_yaw_window_deg) of each candidate's prefilter angle, or of the opposite one;
        None when the window is off."""
        window = self.search.global_yaw_window_deg if window is None else window
        if window <= 0:
            return None
        angles = self.prefilter.angles(low_query, searched)
        offset = (self.global_angles[None, :] - angles[:, None] + 90.0) % 180.0 - 90.0
        # Never narrower than half a step: each candidate keeps at least its nearest heading.
        return np.abs(offset) <= max(window, self.search.rotation_step_deg / 2)

    def _nearest_place(self, occupancy: np.ndarray, match: MatchResult,
                       peaks: list["_LocalPeak"], ranked: np.ndarray, searched: np.ndarray,
                       columns: np.ndarray, prepared: PreparedQueries, headings: np.ndarray,
                       volume, n_refs: int) -> "_LocalPeak | None":
        """The reference nearest the matched pose, aligned, when it confirms the match.

        The best-scoring reference is often not the nearest: a reference a few metres away
        that sees more of the same scene can outscore it. The nearest reference (to the pose
        the match implies) is reported instead when its own alignment scores within
        rerank_margin of the match's and implies the same query pose (same_place): the
        nearer view of the same answer (_reported_at).
        """
        if self.search.rerank_margin <= 0:
            return None
        if self._headings_unknown:
            return self._nearest_by_distances(match, peaks, self._nearer_neighbours(
                occupancy, match, peaks, searched, columns, prepared, headings, volume, n_refs),
                ranked)
        nearest, _ = self._nearest_reference(match.pose[:2], n_refs)
        if nearest == peaks[0].reference:
            return None
        aligned = [peak for peak in peaks if peak.reference == nearest]
        candidate = aligned[0] if aligned else self._local(
            occupancy, nearest,
            self._coarse_angle(nearest, match, searched, columns, prepared, headings, volume))
        if candidate.score < (1.0 - self.search.rerank_margin) * peaks[0].score:
            return None
        if not same_place(self._result(candidate, ranked).pose, match.pose, self.search):
            return None
        return candidate

    def _nearest_by_distances(self, match: MatchResult, peaks: list["_LocalPeak"],
                              neighbours: list["_LocalPeak"], ranked: np.ndarray
                              ) -> "_LocalPeak | None":
        """_nearest_place where the map's headings are unknown (SearchParams.map_headings):
        of the other finalists and the matched reference's neighbours (_nearer_neighbours),
        the one the query is nearest to by its own alignment, when the two alignments put the
        two references as far apart as their map positions are (within rerank_agreement_m)
        and it scores within rerank_margin of the best. A position in the map frame needs a
        reference's heading; a distance does not. A neighbour must also score as well as the
        last finalist: it was not ranked for its score, and a distance agrees with the map by
        chance more often than a position does (an alignment slid along a street). Without
        that, rotated KITTI 00 lost right matches to neighbours 10-14 m off whose alignments,
        at 0.19-0.65 of the best score, put the query nearer (docs/RESULTS.md, session 41)."""
        floor = (1.0 - self.search.rerank_margin) * peaks[0].score
        finalist_floor = max(floor, min(peak.score for peak in peaks))
        origin = self.map.poses[match.reference_index, :2, 3]
        nearest, chosen = float(np.hypot(*match.shift_m)), None
        for peak, least in ([(peak, floor) for peak in peaks[1:]]
                            + [(peak, finalist_floor) for peak in neighbours]):
            if peak.score < least:
                continue
            other = self._result(peak, ranked)
            distance = float(np.hypot(*other.shift_m))
            if distance >= nearest:
                continue
            apart = float(np.hypot(*(self.map.poses[peak.reference, :2, 3] - origin)))
            aligned_apart = reference_distance(np.append(match.shift_m, match.rotation_rad),
                                               np.append(other.shift_m, other.rotation_rad))
            if abs(aligned_apart - apart) <= self.search.rerank_agreement_m:
                nearest, chosen = distance, peak
        return chosen

    def _nearer_neighbours(self, occupancy: np.ndarray, match: MatchResult,
                           peaks: list["_LocalPeak"], searched: np.ndarray, columns: np.ndarray,
                           prepared: PreparedQueries, headings: np.ndarray, volume,
                           n_refs: int) -> list["_LocalPeak"]:
        """Where the map's headings are unknown, the matched reference's map neighbours that
        may be nearer the query than it, aligned by the local stage: those within twice the
        query's distance from it (a reference nearer the query lies within that), and of
        them the searched one the global stage puts nearest the query, and the
        _UNSEARCHED_NEIGHBOURS nearest it that the candidate stage left out, each at its
        prefilter angle and the opposite one. The finalists alone often hold no nearer view:
        the best-scoring ones tend to be neighbours of each other a few metres past the
        query, where the map's positions would have named the nearer one had its headings
        been known (_nearest_place)."""
        origin = self.map.poses[match.reference_index, :2, 3]
        reach = 2.0 * float(np.hypot(*match.shift_m)) + self.search.rerank_agreement_m
        near = np.asarray(self._reference_positions().query_ball_point(origin, reach),
                          dtype=np.int64)
        aligned = [peak.reference for peak in peaks]
        near = near[(near < n_refs) & ~np.isin(near, aligned)]
        if not len(near):
            return []
        jobs = []
        positions = np.flatnonzero(np.isin(searched, near))
        if len(positions):
            located = (self.bank.peaks(volume, positions) if volume is not None
                       else self.bank.locate(prepared, columns[positions]))
            distance = np.hypot(*self._global_alignment(located, headings)[0].T)
            nearest = int(np.argmin(distance))
            jobs.append((int(searched[positions[nearest]]),
                         float(self.global_angles[headings[int(located[nearest, 0])]])))
        unsearched = near[~np.isin(near, searched)]
        if len(unsearched) and self.prefilter is not None:
            apart = np.hypot(*(self.map.poses[unsearched, :2, 3] - origin).T)
            unsearched = unsearched[np.argsort(apart, kind="stable")[:_UNSEARCHED_NEIGHBOURS]]
            upright = self._turned_and_pooled(occupancy, np.arange(1))[0]
            allowed = self._allowed_headings(upright, unsearched,
                                             window=self.search.rotation_step_deg / 2)
            jobs += [(int(reference), float(angle)) for reference, row in zip(unsearched, allowed)
                     for angle in self.global_angles[row]]
        return self._local_peaks(occupancy, jobs) if jobs else []

    def _reported_at(self, match: MatchResult, reference: int, ranked: np.ndarray
                     ) -> MatchResult:
        """match reported against another reference that confirmed it: the pose, its
        covariance, the score and the confidence stay the best alignment's (the evidence the
        match is decided on); the constraint is re-expressed in that reference's frame."""
        reference_pose = self._planar_poses(reference)
        shift_m, rotation_rad = alignment_from_poses(reference_pose, match.pose)
        return dataclasses.replace(
            match, reference_index=reference, scored_reference=match.reference_index,
            shift_m=shift_m, rotation_rad=rotation_rad,
            relative_covariance=rotate_covariance(match.covariance, -reference_pose[2]),
            candidates=_led_by(reference, ranked))

    def _coarse_angle(self, reference: int, match: MatchResult, searched: np.ndarray,
                      columns: np.ndarray, prepared: PreparedQueries, headings: np.ndarray,
                      volume) -> float:
        """The global-stage rotation for reference: its own best when the global stage scored
        it, else the one the match's pose implies (snapped to the global angles, whose
        rotation tables are prepared)."""
        column = np.flatnonzero(searched == reference)
        if len(column):
            located = (self.bank.peaks(volume, column) if volume is not None
                       else self.bank.locate(prepared, columns[column]))
            return float(self.global_angles[headings[int(located[0][0])]])
        return self._snapped_global_angle(
            math.degrees(match.pose[2] - self._planar_poses(reference)[2]))

    def _nearest_reference(self, position: np.ndarray, n_refs: int) -> tuple[int, float]:
        """The reference among the first n_refs nearest a map position, and its distance.
        From the spatial index: it runs on every query, and a scan over the poses costs
        11 ms at 250,000 references."""
        distance, nearest = self._reference_positions().query(position)
        if nearest < n_refs:
            return int(nearest), float(distance)
        # The nearest is not active yet (an evaluation's later scans): the active ones.
        offsets = self.map.poses[:n_refs, :2, 3] - position
        squared = np.einsum("nc,nc->n", offsets, offsets)
        nearest = int(np.argmin(squared))
        return nearest, float(np.sqrt(squared[nearest]))

    def _snapped_global_angle(self, turn_deg: float) -> float:
        """The global angle nearest turn_deg (their rotation tables are prepared): the step
        nearest it on the circle, or where a limited field of view leaves that turn out of
        the global angles, the nearest one kept."""
        step = self.search.rotation_step_deg
        nearest_step = (round(turn_deg / step) % round(360 / step)) * step
        gaps = np.abs((self.global_angles - nearest_step + 180.0) % 360.0 - 180.0)
        return float(self.global_angles[int(np.argmin(gaps))])

    @property
    def estimated_headings(self) -> np.ndarray | None:
        """The references' headings (radians) estimated from the map itself where its own are
        unknown (SearchParams.estimate_map_headings); None where they were not (known, off,
        or a reference without a neighbour in reach). Waits for a running query."""
        with self._query_lock:
            self._estimate_headings()
            return None if self._headings is None else self._headings.copy()

    @property
    def _headings_unknown(self) -> bool:
        """The map's headings are unknown (SearchParams.map_headings) and were not estimated."""
        return self.search.map_headings == "unknown" and self._headings is None

    def _planar_poses(self, references: "int | np.ndarray") -> np.ndarray:
        """The references' planar map poses (x, y, yaw), with their estimated headings where
        the map's own are unknown (_estimate_headings)."""
        poses = planar(self.map.poses[references])
        if self._headings is not None:
            poses[..., 2] = self._headings[references]
        return poses

    def _estimate_headings(self) -> None:
        """Where the map's headings are unknown, each new reference's heading from its
        alignments on its map neighbours (SearchParams.estimate_map_headings): the local
        stage puts the reference, as a query, at some shift and turn in a neighbour's view;
        the direction between their map positions against the direction of that shift gives
        the neighbour view's heading, and the turn the reference's. Every reference needs a
        neighbour between _HEADING_BASELINE_M and three quarters of max_shift_m (the
        alignment's peak inside the searched shifts, with room for its fit); else the map's
        headings stay unknown. Runs before a query's own state is set."""
        n_refs = len(self)
        if (self.search.map_headings != "unknown" or not self.search.estimate_map_headings
                or self.prefilter is None or n_refs <= self._headings_checked):
            return
        first, self._headings_checked = self._headings_checked, n_refs
        if first and self._headings is None:
            return
        positions = self.map.poses[:n_refs, :2, 3]
        reach = 0.75 * self.search.max_shift_m
        estimated = np.empty(n_refs)
        if first:
            estimated[:first] = self._headings
        self._query_offset = self._map_offset.copy()
        for reference in progress_bar(range(first, n_refs), desc="estimate map headings",
                                      unit="reference",
                                      enabled=n_refs - first > _HEADINGS_WITHOUT_PROGRESS):
            near = np.asarray(self._reference_positions().query_ball_point(
                positions[reference], reach), dtype=np.int64)
            apart = np.hypot(*(positions[near] - positions[reference]).T)
            keep = apart >= _HEADING_BASELINE_M
            if not keep.any():
                self._headings = None
                return
            near = near[keep][np.argsort(-apart[keep], kind="stable")[:_HEADING_NEIGHBOURS]]
            estimated[reference] = self._heading_from(reference, near, positions)
        self._headings = estimated

    def _heading_from(self, reference: int, neighbours: np.ndarray, positions: np.ndarray
                      ) -> float:
        """The reference's heading (radians) from its alignments on neighbours (map
        positions known): their circular mean weighted by confidence and distance, again
        without those off it by more than local_rotation_range_deg."""
        occupancy = self.map.occupancy(reference)
        half = self.prefilter.angles_between(reference, neighbours)
        peaks = self._local_peaks(occupancy, [(int(neighbour), float(angle))
                                              for neighbour, turn in zip(neighbours, half)
                                              for angle in (turn, turn + 180.0)],
                                  _Views(self._seen(occupancy)))
        headings, weights = [], []
        for pair in range(len(neighbours)):
            peak = max(peaks[2 * pair: 2 * pair + 2], key=lambda aligned: aligned.score)
            shift_m, rotation, _, _ = self._local_alignment(peak)
            between = positions[reference] - positions[peak.reference]
            headings.append(math.atan2(between[1], between[0])
                            - math.atan2(shift_m[1], shift_m[0]) + rotation)
            weights.append(peak.confidence * float(np.hypot(*between)))
        headings, weights = np.array(headings), np.array(weights)
        mean = _circular_mean(headings, weights)
        close = np.abs(wrap_angle(headings - mean)) <= np.radians(
            self.search.local_rotation_range_deg)
        return _circular_mean(headings[close], weights[close]) if close.any() else mean

    def _reference_positions(self) -> cKDTree:
        """The references' positions as a spatial index, built when first needed after the map
        grew (not on every sync of a live map)."""
        if self._positions is None or self._positions.n != len(self):
            self._positions = cKDTree(self.map.poses[: len(self), :2, 3])
        return self._positions

    def place_similarity(self, reference: int, n_refs: int | None = None) -> float:
        """How alike the map's own views of a place are: the confidence of the nearest other
        reference among the first n_refs (the active ones; default all), within
        distinct_radius_m, aligned on this one by the local stage; NaN without one. Waits
        for a running query (it uses the query's buffers)."""
        with self._query_lock:
            self._estimate_headings()
            return self._place_similarity_of(reference, n_refs)

    def _place_similarity_of(self, reference: int, n_refs: int | None = None) -> float:
        """place_similarity, inside a query.

        The two views are aligned at the yaw between their map poses and at the yaw their
        prefilter spectra give (both halves), the best kept: where the map's headings are off
        (a map of turned images), its places still measure as alike as they are, and where
        the spectra's angle is off (views farther apart), the poses' holds. A map whose
        headings are unknown (SearchParams.map_headings) offers the spectra's angle alone,
        and no yardstick (NaN) without a prefilter. Kept per reference while its nearest
        other view stays the same (a growing map may bring a nearer one). The view is aligned
        as a query of its own (its own _Views), the query's left as they are.
        """
        n_refs = len(self) if n_refs is None else min(n_refs, len(self))
        position = self.map.poses[reference, :2, 3]
        near = np.array([found for found in self._reference_positions().query_ball_point(
            position, self.search.distinct_radius_m) if found < n_refs and found != reference],
            dtype=np.int64)
        if not len(near):
            return math.nan
        offsets = self.map.poses[near, :2, 3] - position
        neighbour = int(near[np.argmin(np.einsum("nc,nc->n", offsets, offsets))])
        kept = self._place_similarity.get(reference)
        if kept is not None and kept[0] == neighbour:
            return kept[1]
        occupancy = self.map.occupancy(neighbour)
        yaws = [] if self._headings_unknown else [
            math.degrees(self._planar_poses(neighbour)[2] - self._planar_poses(reference)[2])]
        if self.prefilter is not None:
            half = float(self.prefilter.angles_between(neighbour, np.array([reference]))[0])
            yaws += [half, half + 180.0]
        if not yaws:
            return math.nan
        similarity = max(peak.confidence for peak in self._local_peaks(
            occupancy, [(reference, yaw) for yaw in yaws], _Views(self._seen(occupancy))))
        self._place_similarity[reference] = (neighbour, similarity)
        return similarity

    def _rotated(self, image: np.ndarray, angles: np.ndarray, only: np.ndarray | None
                 ) -> np.ndarray:
        """rotate_occupancy, from the tables prepared at start-up when angles is one of their
        sets (the global headings, or a global heading's local angles). Any other set, a
        place's similarity's own yaws, gets a table for this call alone: one kept for every
        place measured would fill the cache."""
        return rotate_occupancy(image, angles, only,
                                cached=rotation_key(angles) in self._prepared_angle_sets)

    def _elsewhere(self, searched: np.ndarray, reference: int) -> np.ndarray:
        """Positions in searched of the references farther than distinct_radius_m from
        reference: another place."""
        offsets = self.map.poses[searched, :2, 3] - self.map.poses[reference, :2, 3]
        return np.flatnonzero(np.einsum("nc,nc->n", offsets, offsets)
                              > self.search.distinct_radius_m ** 2)

    def _distinctiveness_tests(self, searched: np.ndarray, scores: np.ndarray,
                               match: "_LocalPeak", match_pose: np.ndarray, confident: bool,
                               ranked: np.ndarray, align: Callable[[int], "_LocalPeak"],
                               aligned: dict[int, "_LocalPeak"]) -> tuple[float, float]:
        """(distinctiveness, local_distinctiveness) of the match (see MatchResult). The
        alignments that refine them are made only for a match that passes confidence and
        would fail distinctiveness: elsewhere it changes nothing that is published."""
        elsewhere = self._elsewhere(searched, match.reference)
        distinctiveness = self._distinctiveness(searched, scores, match.reference, elsewhere)
        search = self.search
        if distinctiveness >= search.min_distinctiveness or not confident:
            return distinctiveness, math.nan
        if search.distinct_aligned_rivals > 0:
            elsewhere = self._other_answers(searched, scores, elsewhere, match_pose, ranked,
                                            align)
            distinctiveness = self._distinctiveness(searched, scores, match.reference,
                                                    elsewhere)
        if distinctiveness >= search.min_distinctiveness or search.min_local_distinctiveness <= 0:
            return distinctiveness, math.nan
        return distinctiveness, self._local_distinctiveness(searched, scores, elsewhere, match,
                                                            align, aligned)

    def _distinctiveness(self, searched: np.ndarray, scores: np.ndarray, reference: int,
                         elsewhere: np.ndarray) -> float:
        """1 - (best global score among the positions elsewhere) / (reference's global
        score)."""
        own = scores[searched == reference]
        if not len(own) or own[0] <= 0 or not len(elsewhere):
            return 0.0
        return float(np.clip(1.0 - scores[elsewhere].max() / own[0], 0.0, 1.0))

    def _other_answers(self, searched: np.ndarray, scores: np.ndarray, elsewhere: np.ndarray,
                       match_pose: np.ndarray, ranked: np.ndarray,
                       align: Callable[[int], "_LocalPeak"]) -> np.ndarray:
        """elsewhere less its best-scoring references (up to distinct_aligned_rivals, best
        first, until one disagrees) whose own alignment puts the query where the match does
        (same_place): a reference farther along the same road that sees the query's place
        gives the same answer, not a look-alike's."""
        best_first = elsewhere[np.argsort(-scores[elsewhere], kind="stable")]
        same = []
        for position in best_first[: self.search.distinct_aligned_rivals]:
            if not same_place(self._result(align(int(position)), ranked).pose, match_pose,
                              self.search):
                break
            same.append(position)
        return np.setdiff1d(elsewhere, same) if same else elsewhere

    def _local_distinctiveness(self, searched: np.ndarray, scores: np.ndarray,
                               elsewhere: np.ndarray, match: "_LocalPeak",
                               align: Callable[[int], "_LocalPeak"],
                               aligned: dict[int, "_LocalPeak"]) -> float:
        """1 - (local score of the best other place: the best-scoring position elsewhere, or
        any reference elsewhere aligned already, a finalist say, that scored higher) / (the
        match's local score). At the global stage's resolution a straight street or a block
        grid looks alike all along; at the local stage's, what the match was decided on tells
        the places apart (docs/RESULTS.md, session 17)."""
        if match.score <= 0 or not len(elsewhere):
            return 0.0
        align(int(elsewhere[np.argmax(scores[elsewhere])]))
        other_places = set(searched[elsewhere].tolist())
        best_other = max(peak.score for reference, peak in aligned.items()
                         if reference in other_places)
        return float(np.clip(1.0 - best_other / match.score, 0.0, 1.0))

    def candidates(self, occupancy: np.ndarray, top_k: int, n_active: int | None = None
                   ) -> np.ndarray:
        """The references the exact global stage would search for this query with
        prefilter_top_k = top_k: the prefilter's top_k and their map neighbours (every
        reference when top_k is 0 or covers them all), without searching them: what a query's
        MatchResult.searched would hold, at the cost of the prefilter alone."""
        n_refs = len(self) if n_active is None else min(n_active, len(self))
        if self.prefilter is None or top_k <= 0 or n_refs <= top_k:
            return np.arange(n_refs)
        with self._query_lock:
            self._query_views = _Views(self._seen(occupancy))
            self._pooled_made[:] = False
            upright = self._turned_and_pooled(occupancy, np.arange(1))[0]
            return self._candidates(occupancy, upright, n_refs, top_k)

    def _candidates(self, occupancy: np.ndarray, low_query: np.ndarray, n_refs: int,
                    top_k: int) -> np.ndarray:
        wide_k = self.search.prefilter_rescore_k
        if self.coarse_bank is None or top_k >= wide_k:
            return self._expanded(self.prefilter.top(low_query, top_k, n_refs), n_refs)
        wide = self.prefilter.top(low_query, wide_k, n_refs)
        return self._expanded(self._rescored(occupancy, low_query, wide)[:top_k], n_refs)

    def _rescored(self, occupancy: np.ndarray, low_query: np.ndarray, wide: np.ndarray
                  ) -> np.ndarray:
        """wide (the prefilter's best references) reordered by the coarse matched filter:
        query and references pooled 2x2 once more, correlated within max_shift_m at the
        global heading nearest each one's prefilter angle and at the opposite one. The polar
        spectra ignore where things lie in the window; the correlation does not."""
        # The nearest heading and its opposite (a window of half a step): on the 8 m tuning
        # pairs the true place ranks as well as with the global stage's yaw window, at a third
        # of the pairs.
        allowed = self._allowed_headings(low_query, wide,
                                         window=self.search.rotation_step_deg / 2)
        headings = np.flatnonzero(allowed.any(axis=0))
        if self.spectra_on_demand:
            self.coarse_bank.refill(pool(self._low_in_order(wide), 2))
            columns = np.arange(len(wide))
        else:
            columns = wide
        prepared = self.coarse_bank.prepare_queries(
            pool(self._turned_and_pooled(occupancy, headings), 2))
        scores, _ = self.coarse_bank.best_of_subset(prepared, columns, self.search.chunk_size,
                                                    allowed[:, headings])
        scores = self._normalised(scores, self.coarse_bank.norms[columns])
        return wide[np.argsort(-scores, kind="stable")]

    def _normalised(self, scores: np.ndarray, reference_norms: np.ndarray) -> np.ndarray:
        """Global-stage scores as search.score_normalisation ranks them: divided by each
        reference image's norm under "cosine", as they are under "raw"."""
        if self.search.score_normalisation == "cosine":
            return scores / np.maximum(reference_norms, 1e-6)
        return scores

    def _expanded(self, searched: np.ndarray, n_refs: int) -> np.ndarray:
        """searched, then the references near its leaders that it lacks (prefilter_expand_m),
        at most as many as searched holds, the nearest to a leader first: along a trajectory
        a leader has a few neighbours, on a grid rendered 2 m apart dozens."""
        radius = self.search.prefilter_expand_m
        if radius <= 0:
            return searched
        leaders = self.map.poses[searched[:_EXPANDED_LEADERS], :2, 3]
        near = np.unique(np.concatenate(
            [np.asarray(found, dtype=np.int64)
             for found in self._reference_positions().query_ball_point(leaders, radius)]))
        near = np.setdiff1d(near[near < n_refs], searched, assume_unique=True)
        if len(near) > len(searched):
            distances, _ = cKDTree(leaders).query(self.map.poses[near, :2, 3])
            near = np.sort(near[np.argsort(distances, kind="stable")[: len(searched)]])
        return np.concatenate([searched, near])

    def _local(self, occupancy: np.ndarray, reference: int, global_angle: float) -> "_LocalPeak":
        return self._local_peaks(occupancy, [(reference, global_angle)])[0]

    def _local_peaks(self, occupancy: np.ndarray, jobs: list[tuple[int, float]],
                     views: "_Views | None" = None) -> list["_LocalPeak"]:
        """The local stage for each (reference, global angle) of jobs, every job's FFTs in one
        batch: finalists at one heading share their turned queries, and a few large batches
        cost less than many small ones. views: occupancy's (the query's by default), which
        keeps its turned weights for later jobs."""
        views = self._query_views if views is None else views
        w = self.params.unoccupied_weight
        correlation = self._local_correlation
        angle_sets = [global_angle + self.local_offsets for _, global_angle in jobs]
        # A place's similarity aligns one reference at three yaws: its image and spectrum once.
        references, image_of_job = np.unique([reference for reference, _ in jobs],
                                             return_inverse=True)
        reference_images = np.stack([weighted(self.map.occupancy(int(reference)), w,
                                              self.covered) for reference in references])
        reference_spectra = correlation.reference_spectra(reference_images)

        def correlate(job_of_pair: np.ndarray, angle_of_pair: np.ndarray) -> np.ndarray:
            """The surfaces of the query at angle_sets[job][angle] against job's reference,
            for each pair (job, angle), the query turned to those angles first."""
            self._turn_query(occupancy, [(angle_sets[job], angle_of_pair[job_of_pair == job])
                                         for job in np.unique(job_of_pair)], views)
            return correlation.correlate_pairs(
                [views.turned[float(angle_sets[job][angle])].spectrum
                 for job, angle in zip(job_of_pair, angle_of_pair)],
                reference_spectra, image_of_job[job_of_pair])

        surfaces = self._coarse_to_fine(correlate, len(jobs), len(self.local_offsets))
        return [self._local_peak(reference, angles, surface, reference_images[image], views)
                for (reference, _), angles, surface, image in zip(jobs, angle_sets, surfaces,
                                                                  image_of_job)]

    def _local_peak(self, reference: int, angles: np.ndarray, surface: np.ndarray,
                    reference_image: np.ndarray, views: "_Views") -> "_LocalPeak":
        """The local stage's peak over the surfaces (angles, 2S+1, 2S+1) of reference."""
        reference_norm = float(np.linalg.norm(reference_image))
        normaliser = reference_norm if self.search.score_normalisation == "cosine" else 1.0
        a, row, col = np.unravel_index(int(surface.argmax()), surface.shape)
        raw = float(surface[a, row, col])
        best = views.turned[float(angles[a])]
        best_query, best_covered = best.weights, best.covered
        query_norm = float(np.linalg.norm(best_query))
        di, dj = row - self.high_shift, col - self.high_shift
        if views.seen is not None:
            # The cosine over the cells the query saw: the reference beyond them is unknown
            # to the query, not a mismatch.
            reference_norm = _norm_under(reference_image, best_covered, di, dj)
        # A sharpened reference (search.local_sharpening) finds the alignment; the confidence
        # stays the cosine of the images themselves, as its thresholds read it.
        plain = (raw if self._local_correlation.emphasis is None
                 else _correlation_at(best_query, reference_image, di, dj))
        confidence = plain / max(query_norm * reference_norm, 1e-9)
        return _LocalPeak(reference=reference, score=raw / normaliser,
                          confidence=float(np.clip(confidence, 0.0, 1.0)), angles=angles,
                          surface=surface, angle_index=int(a), row=int(row), col=int(col))

    def _turn_query(self, occupancy: np.ndarray,
                    angle_sets: list[tuple[np.ndarray, np.ndarray]], views: "_Views") -> None:
        """occupancy turned to angles[indices] for each (angles, indices), those views has not
        turned yet, their spectra in one batch, into views.turned."""
        w = self.params.unoccupied_weight
        keys, weights, footprints = [], [], []
        for angles, indices in angle_sets:
            # An angle may recur in the sets of one batch: finalists a step apart share some.
            missing = np.array([index for index in np.unique(indices)
                                if float(angles[index]) not in views.turned
                                and float(angles[index]) not in keys], dtype=np.int64)
            if not len(missing):
                continue
            covered = self._query_covered(angles, missing, views.seen)
            weights.append(weighted(self._rotated(occupancy, angles, missing), w, covered))
            turns = covered is not None and covered.ndim == 3
            footprints += [covered[k] if turns else None for k in range(len(missing))]
            keys += [float(angle) for angle in angles[missing]]
        if not keys:
            return
        queries = np.concatenate(weights)
        spectra = self._local_correlation.spectra(queries)
        for k, key in enumerate(keys):
            views.turned[key] = _TurnedQuery(queries[k], footprints[k], spectra[k])

    def _seen(self, occupancy: np.ndarray) -> np.ndarray | None:
        """The query's own footprint when queries are matched by what they observed
        (search.query_footprint) and it did not see all round: the cells it has seen, within
        the map's footprint; else None (the map's footprint, exactly as without the option)."""
        if not self.observed_queries:
            return None
        seen = observed_cells(occupancy)
        if seen.all():
            return None
        return seen if self.covered is None else seen & self.covered

    def _query_covered(self, angles: np.ndarray, only: np.ndarray | None,
                       seen: np.ndarray | None) -> np.ndarray | None:
        """The footprint of a query that has seen the cells seen (None: the map's footprint)
        turned by each angle (of angles[only], when given): a field-of-view wedge and the cells
        seen turn with the sensor; the disc and the square window do not."""
        if seen is not None:
            return self._rotated(seen, angles, only) & self.covered_window
        if self.covered is None or not turns_with_sensor(self.params):
            return self.covered
        return self._rotated(self.covered, angles, only) & self.covered_window

    def _turned_and_pooled(self, occupancy: np.ndarray, headings: np.ndarray) -> np.ndarray:
        """The query's low-resolution weights turned to global_angles[headings]: (A, d, d),
        each heading made once per query (self._pooled_turns)."""
        headings = np.asarray(headings, dtype=np.int64)
        missing = headings[~self._pooled_made[headings]]
        if (2 * len(missing) > len(self.global_angles) and self._turned_pooling is not None
                and self._query_views.seen is None):
            # Every heading at once (TurnedPooling on the root headings, the rest laid out)
            # costs about what a third to a half of them turned one by one does.
            missing = np.arange(len(self.global_angles))
        if len(missing):
            self._turn_and_pool(occupancy, missing)
            self._pooled_made[missing] = True
        return self._pooled_turns[headings]

    def _turn_and_pool(self, occupancy: np.ndarray, headings: np.ndarray) -> None:
        """The query's low-resolution weights at global_angles[headings], into
        self._pooled_turns: their root headings turned (quarter_turn_roots), the others laid
        out from those by np.rot90."""
        roots = np.unique(self._heading_roots[headings])
        if (len(roots) == len(self._root_headings) and self._turned_pooling is not None
                and self._query_views.seen is None):
            turned = self._turned_pooling(occupancy)
        else:
            turned = pooled_weights(rotate_occupancy(occupancy, self.global_angles, roots),
                                    self.params.unoccupied_weight, self.params.pool,
                                    self._query_covered(self.global_angles, roots,
                                                        self._query_views.seen))
        rows = np.searchsorted(roots, self._heading_roots[headings])
        turns = self._heading_turns[headings]
        for quarter_turns in np.unique(turns):
            chosen = turns == quarter_turns
            self._pooled_turns[headings[chosen]] = np.rot90(
                turned, -int(quarter_turns), axes=(1, 2))[rows[chosen]]

    def _footprint_keeps_quarter_turns(self) -> bool:
        """Whether a query's weights turned by a quarter turn are its weights turned cell by
        cell by np.rot90: the footprint must not turn with the sensor, and a quarter turn must
        leave it and the window as they are."""
        if turns_with_sensor(self.params) or self.params.size % self.params.pool:
            return False
        return all(np.array_equal(np.rot90(cells), cells)
                   for cells in (self.covered, self.covered_window) if cells is not None)

    def _turned_from(self, headings: np.ndarray) -> np.ndarray | None:
        """SpectralBank.prepare_queries' turned_from for the query turned to headings: each
        heading whose root (quarter_turn_roots) another heading of the batch shares, from the
        first of them."""
        if len(self._root_headings) == len(self.global_angles):
            return None
        roots, turns = self._heading_roots[headings], self._heading_turns[headings]
        _, first_rows, group = np.unique(roots, return_index=True, return_inverse=True)
        source = first_rows[group]
        return np.stack([np.where(source == np.arange(len(headings)), -1, source),
                         (turns - turns[source]) % 4], axis=1)

    @staticmethod
    def _first_local_angles(n_angles: int) -> np.ndarray:
        """The local angles _coarse_to_fine correlates first (indices): every other one from the
        second, so that the two ends are each beside one of them; all of a few."""
        return np.arange(n_angles) if n_angles < 5 else np.arange(1, n_angles, 2)

    def _coarse_to_fine(self, correlate: Callable[[np.ndarray, np.ndarray], np.ndarray],
                        n_jobs: int, n_angles: int) -> np.ndarray:
        """Correlation surfaces (jobs, A, 2S+1, 2S+1) of the local angles that can hold each
        job's peak: every other angle first, then the two beside the best of those; the rest
        stay -inf (and the query is never turned to them). The score falls off smoothly over a
        few degrees, so the peak lies beside the best of every other angle, and the
        sub-degree fit needs only it and its two neighbours: 5 of 7 angles at the defaults.
        correlate(jobs, angles) gives the surfaces of the pairs (jobs[p], angles[p]), every
        job's pairs in one batch."""
        coarse = self._first_local_angles(n_angles)
        shifts = 2 * self.high_shift + 1
        surface = np.full((n_jobs, n_angles, shifts, shifts), -np.inf, dtype=np.float32)
        jobs, angles = np.repeat(np.arange(n_jobs), len(coarse)), np.tile(coarse, n_jobs)
        surface[jobs, angles] = correlate(jobs, angles)
        if len(coarse) == n_angles:
            return surface
        best = coarse[np.argmax(surface[:, coarse].reshape(n_jobs, len(coarse), -1).max(axis=2),
                                axis=1)]
        beside = np.array([(job, angle) for job in range(n_jobs)
                           for angle in (best[job] - 1, best[job] + 1) if 0 <= angle < n_angles])
        surface[beside[:, 0], beside[:, 1]] = correlate(beside[:, 0], beside[:, 1])
        return surface

    def _local_alignment(self, peak: "_LocalPeak"
                         ) -> tuple[np.ndarray, float, np.ndarray, float]:
        """The local stage's alignment refined between cells and between angles: (shift_m,
        rotation_rad, the peak's curvature over cells (2x2), its curvature over angles)."""
        surface = peak.surface
        offset, cell_hessian = subcell_peak(surface[peak.angle_index], peak.row, peak.col)
        per_angle = surface.reshape(len(peak.angles), -1).max(axis=1)
        angle_offset, angle_curvature = subsample_peak(per_angle, peak.angle_index)
        rotation_deg = (peak.angles[peak.angle_index]
                        + angle_offset * self.search.local_rotation_step_deg)
        shift_cells = np.array([peak.col - self.high_shift + offset[0],
                                peak.row - self.high_shift + offset[1]])
        rotation = math.radians(rotation_deg)
        return (self._shift_m(shift_cells * self.params.voxel_size, rotation), rotation,
                cell_hessian, angle_curvature)

    def _result(self, peak: "_LocalPeak", ranked: np.ndarray) -> MatchResult:
        voxel = self.params.voxel_size
        shift_m, rotation, cell_hessian, angle_curvature = self._local_alignment(peak)
        peak_value = max(float(peak.surface[peak.angle_index, peak.row, peak.col]), 1e-9)
        step = self.search.local_rotation_step_deg

        inflation = 1.0 / max(peak.confidence, _MIN_CONFIDENCE_FOR_COVARIANCE)
        relative_covariance = np.zeros((3, 3))
        normalised_hessian = -cell_hessian / peak_value
        if smallest_eigenvalue(normalised_hessian) > 1e-6:
            relative_covariance[:2, :2] = (inverse_2x2(normalised_hessian) * voxel ** 2
                                           * _CURVATURE_TO_VARIANCE * inflation)
        else:
            relative_covariance[:2, :2] = np.eye(2) * (self.search.max_shift_m / 2) ** 2
        yaw_curvature = -angle_curvature / (peak_value * step ** 2)
        if yaw_curvature > 1e-9:
            yaw_variance_deg2 = _CURVATURE_TO_VARIANCE / yaw_curvature * inflation
        else:
            yaw_variance_deg2 = self.search.local_rotation_range_deg ** 2
        relative_covariance[2, 2] = math.radians(1.0) ** 2 * yaw_variance_deg2

        reference_pose = self._planar_poses(peak.reference)
        pose = query_pose_from_alignment(reference_pose, shift_m, rotation)
        return MatchResult(
            reference_index=peak.reference, score=peak.score, confidence=peak.confidence,
            shift_m=shift_m, rotation_rad=rotation, pose=pose,
            covariance=rotate_covariance(relative_covariance, reference_pose[2]),
            relative_covariance=relative_covariance,
            candidates=_led_by(peak.reference, ranked))


def _circular_mean(angles: np.ndarray, weights: np.ndarray) -> float:
    return math.atan2(float(np.dot(weights, np.sin(angles))),
                      float(np.dot(weights, np.cos(angles))))


def _led_by(reference: int, ranked: np.ndarray) -> np.ndarray:
    """MatchResult.candidates: reference first, then the global ranking without it."""
    return np.concatenate([[reference], ranked[ranked != reference]])[:_REPORTED_CANDIDATES]


@dataclass
class _LocalPeak:
    reference: int
    score: float
    confidence: float
    angles: np.ndarray
    surface: np.ndarray
    angle_index: int
    row: int
    col: int


@dataclass
class _TurnedQuery:
    """The query at one local-stage angle: its weights, its footprint when that turns with it
    (else None), and its spectrum (LocalCorrelation.spectra)."""

    weights: np.ndarray
    covered: np.ndarray | None
    spectrum: object


@dataclass
class _Views:
    """What the local stage knows of one image it aligns as a query: the cells it has seen
    (None: the map's footprint) and its turned weights by angle, made as jobs need them."""

    seen: np.ndarray | None
    turned: dict[float, _TurnedQuery] = field(default_factory=dict)
