"""Verification of matches before they are published: the tests that keep false loop closures
out of a pose graph (docs/METHOD.md, our additions). One code path for the live nodes, `localise`
and `evaluate`.

A match is published when, in this order (cheap tests first, each only on what passed before):
1. its confidence reaches search.min_confidence, or else search.min_relative_confidence of
   its place's similarity (MatchResult.place_similarity: a revisit matches about as well as
   the map's own neighbouring views match each other), and its score reaches min_score;
2. its distinctiveness (best place vs the best other place, MatchResult.distinctiveness)
   reaches search.min_distinctiveness, or the same comparison at the local stage's
   resolution (local_distinctiveness) reaches search.min_local_distinctiveness: a look-alike
   place scores nearly as well;
3. geometric verification, where clouds exist and search.verify_fitness > 0: ICP fitness
   against the reference's stored cloud;
4. odometry consistency, where the scans' odometry is known and
   search.consistency_min_support > 0: other candidates within consistency_window_m of travel
   (and far enough that their submaps share no scan) must imply the same map-to-odometry
   alignment. A false match is a one-off; a true revisit repeats along the path, each match
   agreeing with the odometry between them.

Agreement is symmetric: a candidate that lacked support when it came is confirmed as soon as
enough later candidates agree with it (Verdict.confirms names it to the caller, with the
reason it is published for, and the caller publishes it then: a pose graph takes a closure
late as well as on time). So the first matches of a revisit are published too, on the same
evidence as the ones after them.

A confirmed closure vouches (search.consistency_vouch) for the matches near it on the path that
fail confidence or distinctiveness (or both) and nothing else, or odometry consistency alone (a
candidate that found too few agreeing ones): such a match is published when it agrees with a
confirmed candidate within consistency_vouch_window_m of travel, earlier or later, of it or of
the latest match it vouched for (its reach: a closure vouches along the whole revisit it
anchors, for as long as the revisit's matches keep agreeing with it). Confidence
asks how much of the query the reference explains, distinctiveness whether another place looks
as alike, support whether the match repeats; once odometry and an independently confirmed
closure put the query there, a match that lands within consistency_tolerance_m of where they
predict is that place, however little of the place the query saw. A weak match (under
min_confidence) is published where the vouching closures put the query, not where its own
weak peak does: it names the place, they give the pose, and its covariance: theirs, carried
along the odometry with the odometry's drift (search.odometry_drift; a carried pose is no
better than the closure it carries), widened by the gap between the two poses and never
narrower than its own peak's (take_pose). Independently: a closure that a
candidate's own agreement helped confirm does not vouch for it. Only confirmed candidates
vouch, never a vouched match, so agreement cannot creep along a road from one vouched match to
the next: every match of a revisit is held to where the one closure, carried along the
odometry, puts it, and the odometry's drift over a long revisit ends the agreement, not the
window.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from functools import partial
from typing import Any, Callable, Iterable

import numpy as np

from mf_lpr_ros.core.pose import (
    alignment_from_poses,
    compose_planar,
    composed_covariance,
    enclosing_covariance,
    mean_planar,
    relative_planar,
    rotate_covariance,
    wrap_angle,
)
from mf_lpr_ros.core.search import MatchResult, distinct, passes_confidence, within_tolerance
from mf_lpr_ros.errors import ConfigError
from mf_lpr_ros.params import SearchParams


@dataclass
class Verdict:
    """Whether a match is published, why not, and what the tests measured. awaiting_vouch: it
    failed only tests a confirmed closure outweighs (confidence, distinctiveness), and a later
    one may still vouch for it."""

    accepted: bool
    reason: str
    fitness: float = math.nan
    support: int = -1
    confirms: dict[Any, str] = field(default_factory=dict)
    awaiting_vouch: bool = False

    @property
    def candidate(self) -> bool:
        """It passed every test but odometry consistency (it may support later matches)."""
        return self.support >= 0

    @property
    def may_be_confirmed(self) -> bool:
        """Not published now, but a later match may confirm it (Verdict.confirms)."""
        return not self.accepted and (self.candidate or self.awaiting_vouch)


CONFIRMED_LATER = "accepted: confirmed by later matches"
VOUCHED = "accepted: a confirmed closure vouches for it"
# A match the revisit check reported (MatchResult.revisit_predicted).
VOUCHED_WHERE_PREDICTED = VOUCHED + " where its revisit put the scan"
AWAITING_VOUCH = "no confirmed closure vouches for it yet"


def published_late(verdict: Verdict, reason: str) -> Verdict:
    """An earlier match's verdict once a later verdict's confirms name it, with reason."""
    return Verdict(True, reason, verdict.fitness, verdict.support)


# Matches kept per list (candidates, matches awaiting a vouch), newest first: the travel window
# bounds them while the robot moves; this bounds them when it stands still (30 m at 10 Hz and
# 0.15 m/s).
MATCHES_KEPT = 2000
# Matches a caller keeps in case a later verdict confirms them (Verdict.may_be_confirmed): as
# many as the verifier may still confirm, its candidates and the matches awaiting a vouch.
MAY_BE_CONFIRMED_KEPT = 2 * MATCHES_KEPT


@dataclass(eq=False)
class _Candidate:
    odometry: np.ndarray
    estimate: np.ndarray
    travelled_m: float
    key: Any
    support: int
    confirmed: bool
    published: bool = False
    # The serials of the candidates it counted for and was counted by (serials, not the
    # candidates: links would keep every candidate of a long run alive).
    serial: int = -1
    linked: set[int] = field(default_factory=set)
    # Called with the pose its vouchers put it at and that pose's covariance, when one vouches
    # for it.
    on_vouch: Callable[[np.ndarray, np.ndarray], None] | None = None
    # Its estimate's covariance (3x3, map frame): a confirmed candidate lends it, carried, to
    # the matches it vouches for (a match awaiting a vouch lends nothing).
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    # A confirmed candidate's reach: the travel of the latest match it vouched for, or its
    # own; it vouches while the robot is within the vouch window of its reach.
    reach_m: float = -math.inf

    def extend_reach(self, travelled_m: float) -> None:
        self.reach_m = max(self.reach_m, travelled_m)


def _stacked(matches: "_Candidate | Iterable[_Candidate]") -> tuple[np.ndarray, np.ndarray]:
    """(odometry, estimate) of one match, or of several stacked."""
    if isinstance(matches, _Candidate):
        return matches.odometry, matches.estimate
    return (np.stack([m.odometry for m in matches]), np.stack([m.estimate for m in matches]))


def _carry(estimate: np.ndarray, odometry: np.ndarray, to_odometry: np.ndarray) -> np.ndarray:
    """Where a match's estimate (planar, map frame), carried along the odometry from its
    query's odometry pose to another query's, puts that query (either side one or several
    poses, broadcast)."""
    return compose_planar(estimate, relative_planar(odometry, to_odometry))


def _carried(earlier, later) -> np.ndarray:
    """_carry from earlier matches to later ones (either side one match or several)."""
    earlier_odometry, earlier_estimate = _stacked(earlier)
    return _carry(earlier_estimate, earlier_odometry, _stacked(later)[0])


def take_pose(match: MatchResult, pose: np.ndarray, covariance: np.ndarray) -> None:
    """Move match to pose (planar, map frame) in place, its reference kept: its alignment to
    that reference follows (as ICP refinement moves it, core/refine.py). Its covariance (and
    the alignment's) becomes the given one (3x3, map frame) widened along the gap between its
    own estimate and pose (two estimates of one pose that disagree say how far off either
    may be, whatever their covariances claim), and never narrower than its own: a carried
    pose is as good as the closures it carries, and their covariances can claim too much
    (docs/RESULTS.md, session 58)."""
    reference_pose = compose_planar(
        match.pose, relative_planar([*match.shift_m, match.rotation_rad], np.zeros(3)))
    pose = np.asarray(pose, dtype=np.float64)
    gap = match.pose - pose
    gap[2] = wrap_angle(gap[2])
    match.pose = pose
    match.shift_m, match.rotation_rad = alignment_from_poses(reference_pose, match.pose)
    widened = np.asarray(covariance, dtype=np.float64) + np.outer(gap, gap)
    match.covariance = enclosing_covariance(match.covariance, widened)
    match.relative_covariance = rotate_covariance(match.covariance, -float(reference_pose[2]))


def carried_covariance(anchor: "_Candidate", carried: np.ndarray, to_travelled_m: float,
                       search: SearchParams) -> np.ndarray:
    """The covariance (3x3, map frame) of anchor's estimate carried along the odometry to the
    pose carried (_carry), at to_travelled_m of travel: the anchor's own, swung by its heading
    error about its position, plus the odometry's drift over the travel between the two
    (search.odometry_drift, odometry_yaw_drift_deg_per_m)."""
    travel_m = abs(to_travelled_m - anchor.travelled_m)
    drift = np.diag([(search.odometry_drift * travel_m) ** 2] * 2
                    + [math.radians(search.odometry_yaw_drift_deg_per_m * travel_m) ** 2])
    return composed_covariance(anchor.estimate, anchor.covariance, carried, drift)


def pooled_covariance(places: np.ndarray, covariances: list[np.ndarray]) -> np.ndarray:
    """The covariance of the mean (mean_planar) of several vouchers' places: their covariances'
    mean (one revisit's closures share their errors, so averaging them narrows nothing) plus
    the places' own spread about their mean."""
    places = np.asarray(places, dtype=np.float64)
    deviation = places - mean_planar(places)
    deviation[:, 2] = wrap_angle(deviation[:, 2])
    return np.mean(covariances, axis=0) + deviation.T @ deviation / len(places)


class OdometryConsistency:
    """Counts the candidates whose implied poses, carried along the odometry between them,
    agree (SearchParams.consistency_*): each new candidate with the earlier ones in the window,
    and each earlier one gains the new one's agreement. Keeps, in the same window, the matches
    that await a vouch from a confirmed candidate (module doc).

    Only candidates at least min_separation_m apart count for each other: closer than the
    descriptor's submap window, two queries are described from the same scans and one wrong
    match simply repeats in the other. A vouch needs no separation: the confirmed candidate
    was confirmed without the match it vouches for.
    """

    def __init__(self, search: SearchParams, min_separation_m: float | None = None) -> None:
        self.search = search
        self.min_separation_m = (search.consistency_min_separation_m if min_separation_m is None
                                 else min_separation_m)
        self.travelled_m = 0.0
        self._last_odometry: np.ndarray | None = None
        self._candidates: deque[_Candidate] = deque(maxlen=MATCHES_KEPT)
        # Confirmed candidates whose reach (_Candidate.reach_m) lies in the vouch window.
        self._anchors: list[_Candidate] = []
        self._serials = 0
        self._awaiting_vouch: deque[_Candidate] = deque(maxlen=MATCHES_KEPT)

    def advance(self, odometry: np.ndarray) -> None:
        """Record the odometry of a query (every query, matched or not): the window is travel."""
        odometry = np.asarray(odometry, dtype=np.float64)
        if self._last_odometry is not None:
            self.travelled_m += float(np.hypot(*(odometry[:2] - self._last_odometry[:2])))
        self._last_odometry = odometry
        search = self.search
        for kept, window in ((self._candidates, search.consistency_window_m),
                             (self._awaiting_vouch, search.consistency_vouch_window_m)):
            while kept and self.travelled_m - kept[0].travelled_m > window:
                kept.popleft()
        self._anchors = [anchor for anchor in self._anchors
                         if self.travelled_m - anchor.reach_m <= search.consistency_vouch_window_m]
        if len(self._anchors) > MATCHES_KEPT:
            self._anchors = sorted(self._anchors, key=lambda anchor: anchor.reach_m)[-MATCHES_KEPT:]

    def _agreeing(self, earlier, later, min_separation_m: float) -> np.ndarray:
        """Whether each earlier match's estimate, carried along the odometry to the later's,
        lies within the tolerances of the later one's (either side one match or several,
        broadcast), the two queries at least min_separation_m apart."""
        earlier_odometry, earlier_estimate = _stacked(earlier)
        later_odometry, later_estimate = _stacked(later)
        separated = np.hypot(*(earlier_odometry[..., :2] - later_odometry[..., :2]).T) \
            >= min_separation_m
        predicted = _carry(earlier_estimate, earlier_odometry, later_odometry)
        return separated & self._within_tolerance(predicted, later_estimate)

    def _within_tolerance(self, predicted: np.ndarray, estimate: np.ndarray) -> np.ndarray:
        """Whether each predicted pose lies within the consistency tolerances of estimate."""
        return within_tolerance(predicted, estimate, self.search)

    def support(self, odometry: np.ndarray, estimate: np.ndarray, covariance: np.ndarray,
                key: Any = None) -> tuple[int, dict[Any, str], bool]:
        """(earlier candidates agreeing with this one, the earlier matches that this
        agreement confirms or, once a candidate is confirmed, that it vouches for (key ->
        CONFIRMED_LATER or VOUCHED), whether a confirmed candidate vouches for this one that
        lacks support); the current one is then remembered as a candidate. covariance: the
        estimate's (3x3, map frame), lent to the matches it vouches for once confirmed."""
        odometry = np.asarray(odometry, dtype=np.float64)
        estimate = np.asarray(estimate, dtype=np.float64)
        needed = self.search.consistency_min_support
        self._serials += 1
        current = _Candidate(odometry, estimate, self.travelled_m, key, 0, False,
                             serial=self._serials,
                             covariance=np.asarray(covariance, dtype=np.float64))
        agree = (self._agreeing(self._candidates, current, self.min_separation_m)
                 if self._candidates else [])
        agreeing = [c for c, agrees in zip(self._candidates, agree) if agrees]
        newly_confirmed = []
        for candidate in agreeing:
            candidate.support += 1
            candidate.linked.add(current.serial)
            current.linked.add(candidate.serial)
            if not candidate.confirmed and candidate.support >= needed:
                candidate.confirmed = True
                newly_confirmed.append(candidate)
        current.support = count = len(agreeing)
        current.confirmed = count >= needed
        self._candidates.append(current)
        if current.confirmed:
            newly_confirmed.append(current)
        confirmed = {c.key: CONFIRMED_LATER for c in newly_confirmed
                     if c is not current and not c.published}
        for anchor in newly_confirmed:
            anchor.published = True
            anchor.extend_reach(anchor.travelled_m)
            self._anchors.append(anchor)
        vouched = False
        if self.search.consistency_vouch:
            for anchor in newly_confirmed:
                confirmed.update(dict.fromkeys(self._vouch_from(anchor), VOUCHED))
            if not current.published:
                # A closure confirmed without this candidate vouches for it, as for a match
                # that fails confidence or distinctiveness; else it waits for one, as they do.
                vouched = current.published = self._vouched_now(current)
                if not vouched:
                    self._awaiting_vouch.append(current)
        return count, confirmed, vouched

    def places_elsewhere(self, odometry: np.ndarray, estimate: np.ndarray) -> np.ndarray:
        """(k, 3) planar map poses at which the confirmed candidates in reach (as of the last
        advance), carried along the odometry, put the query, when none of them puts it
        where estimate does; else (0, 3)."""
        if not self._anchors:
            return np.zeros((0, 3))
        anchors_odometry, anchors_estimate = _stacked(self._anchors)
        places = _carry(anchors_estimate, anchors_odometry, np.asarray(odometry, dtype=np.float64))
        if self._within_tolerance(places, np.asarray(estimate, dtype=np.float64)).any():
            return np.zeros((0, 3))
        return places

    def _vouch_from(self, anchor: _Candidate) -> list[Any]:
        """Keys of the matches awaiting a vouch that agree with a newly confirmed candidate
        (they are published and forgotten)."""
        if not self._awaiting_vouch:
            return []
        # A vouch needs no separation (class doc): agreement is the tolerance alone.
        places = _carried(anchor, self._awaiting_vouch)
        agree = self._within_tolerance(places, _stacked(self._awaiting_vouch)[1])
        vouched = []
        for match, agrees, place in zip(self._awaiting_vouch, agree, places):
            if agrees and not match.published and match.serial not in anchor.linked:
                match.published = True
                anchor.extend_reach(match.travelled_m)
                vouched.append(match.key)
                if match.on_vouch is not None:
                    match.on_vouch(place, carried_covariance(anchor, place, match.travelled_m,
                                                             self.search))
        self._awaiting_vouch = deque((m for m in self._awaiting_vouch if not m.published),
                                     maxlen=MATCHES_KEPT)
        return vouched

    def _vouched_now(self, match: _Candidate) -> bool:
        """Whether a confirmed candidate in reach agrees with match and was confirmed
        without it (match did not count for it); if so, its reach moves to match, and
        match.on_vouch hears the mean of the poses where those that agree put it, and that
        mean's covariance (pooled_covariance)."""
        anchors = [a for a in self._anchors if a.serial not in match.linked]
        if not anchors:
            return False
        places = _carried(anchors, match)
        agree = self._within_tolerance(places, match.estimate)
        if not agree.any():
            return False
        vouchers = [anchor for anchor, agrees in zip(anchors, agree) if agrees]
        for anchor in vouchers:
            anchor.extend_reach(match.travelled_m)
        if match.on_vouch is not None:
            match.on_vouch(mean_planar(places[agree]), pooled_covariance(
                places[agree], [carried_covariance(anchor, place, match.travelled_m, self.search)
                                for anchor, place in zip(vouchers, places[agree])]))
        return True

    def vouched(self, odometry: np.ndarray, estimate: np.ndarray, key: Any = None,
                on_vouch: Callable[[np.ndarray, np.ndarray], None] | None = None) -> bool:
        """Whether a confirmed candidate in reach agrees with this match; when none
        does, it is kept in case a later confirmed candidate will. on_vouch: called, now or
        then, with the pose at which the vouching closures, carried along the odometry, put
        the query (their mean), and its covariance (3x3, map frame): the closures' own,
        carried (carried_covariance), pooled (pooled_covariance)."""
        odometry = np.asarray(odometry, dtype=np.float64)
        estimate = np.asarray(estimate, dtype=np.float64)
        match = _Candidate(odometry, estimate, self.travelled_m, key, -1, False,
                           on_vouch=on_vouch)
        if self._vouched_now(match):
            return True
        self._awaiting_vouch.append(match)
        return False


class MatchVerifier:
    """Applies the tests of the module doc to a stream of matches, in query time order.

    odometry_known: the caller passes each query's odometry pose (planar x, y, yaw in any fixed
    frame); without it the consistency test cannot run and is skipped (`consistency_active`).
    submap_m: the descriptor's submap window (DescriptorParams.submap_m): matches agree only
    when at least this far apart (and consistency_min_separation_m), so that no two of them
    were described from the same scans.
    """

    def __init__(self, search: SearchParams, *, min_score: float = 0.0,
                 odometry_known: bool = True, submap_m: float = 0.0) -> None:
        self.search = search
        self.min_score = min_score
        self.consistency_active = search.consistency_min_support > 0 and odometry_known
        if self.consistency_active and submap_m >= search.consistency_window_m:
            # Supporters lie submap_m apart as the crow flies, so farther apart in travel.
            raise ConfigError(
                f"odometry consistency can confirm no match: matches support each other only "
                f"descriptor.submap_m = {submap_m:g} m apart (their submaps share no scan), and "
                f"only within search.consistency_window_m = {search.consistency_window_m:g} m of "
                f"travel; widen the window beyond the submap, or set "
                f"search.consistency_min_support to 0")
        self.consistency = OdometryConsistency(
            search, max(search.consistency_min_separation_m, submap_m))

    def revisit_places(self, match: MatchResult, odometry: np.ndarray | None) -> np.ndarray:
        """(k, 3) planar map poses at which the revisit the robot is on puts the query, when
        match contradicts it: the confirmed closures in reach (within
        consistency_vouch_window_m of travel of them or of the latest match they vouched for,
        as of the last verified query), carried along the odometry, and none of them puts
        the query where match does. A weak match there suggests the candidate stage left
        the place out (SearchParams.prefilter_retry "revisits"), an indistinct one that a
        look-alike outscored the place (SearchParams.revisit_check). Else (0, 3)."""
        if not self.consistency_active or odometry is None:
            return np.zeros((0, 3))
        return self.consistency.places_elsewhere(odometry, match.pose)

    def verify(self, match: MatchResult | None, odometry: np.ndarray | None = None,
               fitness_of: Callable[[MatchResult], float] | None = None,
               key: Any = None) -> Verdict:
        """The verdict on one query's match (None: nothing to match against). fitness_of runs
        the geometric verification (ICP) and is called only when the cheap tests pass. key
        names this query to later verdicts: Verdict.confirms maps the keys of earlier
        matches that this match's agreement confirms or vouches for to the reason they are
        published for (publish them now)."""
        if self.consistency_active:
            if odometry is None:
                raise ValueError("odometry consistency is on (search.consistency_min_support > "
                                 "0) but this scan has no odometry pose")
            self.consistency.advance(odometry)
        if match is None:
            return Verdict(False, "no reference to search yet")
        search = self.search
        reasons = []
        weak = not passes_confidence(match.confidence, match.place_similarity, search)
        if weak:
            reasons.append(self._weak_reason(match))
        # The caller's own floor: no closure vouches past it.
        below_min_score = match.score < self.min_score
        if below_min_score:
            reasons.append(f"score {match.score:.4g} < min_score {self.min_score}")
        if not distinct(match, search):
            reasons.append(self._indistinct_reason(match))
        a_vouch_may_save = (bool(reasons) and not below_min_score and self.consistency_active
                            and search.consistency_vouch)
        if reasons and not a_vouch_may_save:
            return Verdict(False, "; ".join(reasons))
        fitness = math.nan
        if search.verify_fitness > 0:
            if fitness_of is None:
                return Verdict(False, "search.verify_fitness needs the scan's points and the "
                                      "reference's cloud")
            fitness = fitness_of(match)
            if not fitness >= search.verify_fitness:
                return Verdict(False, f"ICP fitness {fitness:.3f} < verify_fitness "
                                      f"{search.verify_fitness}", fitness)
        if reasons:
            # A weak peak places the query less precisely than the vouching closures do
            # (docs/RESULTS.md, sessions 20 and 51): a weak match takes their pose.
            on_vouch = partial(take_pose, match) if weak else None
            if self.consistency.vouched(odometry, match.pose, key, on_vouch):
                return Verdict(True, VOUCHED_WHERE_PREDICTED if match.revisit_predicted
                               else VOUCHED, fitness)
            return Verdict(False, f"{'; '.join(reasons)}; {AWAITING_VOUCH}", fitness,
                           awaiting_vouch=True)
        if not self.consistency_active:
            return Verdict(True, "accepted", fitness)
        support, confirms, vouched = self.consistency.support(odometry, match.pose,
                                                              match.covariance, key)
        if vouched:
            return Verdict(True, VOUCHED, fitness, support, confirms)
        if support < search.consistency_min_support:
            return Verdict(False, f"odometry consistency: {support} earlier match(es) agree, "
                                  f"consistency_min_support is {search.consistency_min_support}",
                           fitness, support, confirms)
        return Verdict(True, "accepted", fitness, support, confirms)

    def _weak_reason(self, match: MatchResult) -> str:
        search = self.search
        if search.min_relative_confidence <= 0:
            relative = ""
        elif math.isnan(match.place_similarity):
            relative = " (no other view of the place to measure it against)"
        else:
            relative = (f" and < min_relative_confidence {search.min_relative_confidence} x "
                        f"place similarity {match.place_similarity:.3f}")
        return (f"confidence {match.confidence:.3f} < min_confidence {search.min_confidence}"
                + relative)

    def _indistinct_reason(self, match: MatchResult) -> str:
        search = self.search
        return (f"distinctiveness {match.distinctiveness:.3f} < min_distinctiveness "
                f"{search.min_distinctiveness}"
                + (f" and local {match.local_distinctiveness:.3f} < min_local_distinctiveness "
                   f"{search.min_local_distinctiveness}"
                   if search.min_local_distinctiveness > 0 else ""))
