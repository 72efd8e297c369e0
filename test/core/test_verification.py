"""Match verification: distinctiveness, odometry consistency and the order of the tests."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers import turned_view_map

from mf_lpr_ros.core.descriptor import describe_points
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.pose import (
    compose_planar,
    mean_planar,
    planar_error,
    relative_planar,
    wrap_angle,
)
from mf_lpr_ros.core.search import MatchedFilterIndex, MatchResult
from mf_lpr_ros.core.verification import (
    AWAITING_VOUCH,
    CONFIRMED_LATER,
    MATCHES_KEPT,
    VOUCHED,
    VOUCHED_WHERE_PREDICTED,
    MatchVerifier,
)
from mf_lpr_ros.errors import ConfigError
from mf_lpr_ros.params import DescriptorParams, SearchParams
from mf_lpr_ros.sim.synthetic import scan_world

PARAMS = DescriptorParams(voxel_size=0.4, z_min=-1.2)
PLACES = [(0.0, 0.0, 0.0), (25.0, 0.0, 1.0), (0.0, 25.0, -2.0), (-25.0, -10.0, 2.5)]


def _map(world, look_alike: bool) -> ReferenceMap:
    """References at PLACES; with look_alike, the first place's scan is stored a second time
    as if seen 40 m away (a place that looks the same as another)."""
    rng = np.random.default_rng(0)
    reference_map = ReferenceMap(PARAMS)
    for index, place in enumerate(PLACES):
        points, pose = scan_world(world, *place, rng)
        reference_map.append(describe_points(points, PARAMS, reference=True, seed_key=index),
                             pose, float(index), index)
        if look_alike and index == 0:
            elsewhere = pose.copy()
            elsewhere[:2, 3] += [40.0, 40.0]
            reference_map.append(describe_points(points, PARAMS, reference=True, seed_key=99),
                                 elsewhere, 0.5, 99)
    return reference_map


def test_a_planted_look_alike_place_is_rejected(world):
    search = SearchParams(min_confidence=0.3, consistency_min_support=0)
    points, _ = scan_world(world, 0.8, -0.5, 0.2, np.random.default_rng(5))
    query = describe_points(points, PARAMS)
    for look_alike, expected in ((False, True), (True, False)):
        match = MatchedFilterIndex(_map(world, look_alike), search).query(query)
        verdict = MatchVerifier(search, odometry_known=False).verify(match)
        assert match.confidence >= search.min_confidence
        assert verdict.accepted is expected, (look_alike, match.distinctiveness, verdict.reason)
        if look_alike:
            assert match.distinctiveness < 0.05 and "distinctiveness" in verdict.reason
        else:
            assert match.distinctiveness > 0.3


def _swapped_within_pooling_blocks(occupancy: np.ndarray) -> np.ndarray:
    """Each cell moved to the opposite corner of its 2 x 2 pooling block: the same global-stage
    descriptor (the block averages), another one at full resolution."""
    size = occupancy.shape[0]
    blocks = occupancy.reshape(size // 2, 2, size // 2, 2)
    return np.ascontiguousarray(blocks[:, ::-1, :, ::-1]).reshape(size, size)


def test_a_place_alike_only_when_pooled_is_told_apart_at_full_resolution(world):
    """A look-alike that only the pooled descriptor confuses fails the global test
    (distinctiveness 0) and passes at the local stage's resolution when that test is on; an
    exact copy fails both."""
    rng = np.random.default_rng(0)
    points, pose = scan_world(world, *PLACES[0], rng)
    place = describe_points(points, PARAMS, reference=True, seed_key=0)
    query_points, _ = scan_world(world, 0.8, -0.5, 0.2, np.random.default_rng(5))
    query = describe_points(query_points, PARAMS)
    elsewhere = pose.copy()
    elsewhere[:2, 3] += [40.0, 40.0]
    outcomes = {}
    for kind, look_alike in (("pooled", _swapped_within_pooling_blocks(place)),
                             ("copy", place.copy())):
        reference_map = _map(world, look_alike=False)
        reference_map.append(look_alike, elsewhere, 9.0, 99)
        for min_local in (0.0, 0.3):
            search = SearchParams(min_confidence=0.3, consistency_min_support=0,
                                  min_local_distinctiveness=min_local)
            match = MatchedFilterIndex(reference_map, search).query(query)
            assert match.reference_index == 0 and match.distinctiveness < 0.02
            verdict = MatchVerifier(search, odometry_known=False).verify(match)
            outcomes[kind, min_local] = (verdict.accepted, match.local_distinctiveness)
            if not verdict.accepted:
                assert "distinctiveness" in verdict.reason
    assert not outcomes["pooled", 0.0][0] and math.isnan(outcomes["pooled", 0.0][1])
    assert outcomes["pooled", 0.3][0] and outcomes["pooled", 0.3][1] >= 0.3
    assert not outcomes["copy", 0.3][0] and outcomes["copy", 0.3][1] < 0.05


def test_local_distinctiveness_is_only_computed_when_the_global_test_fails(world):
    search = SearchParams(min_confidence=0.3, consistency_min_support=0,
                          min_local_distinctiveness=0.3)
    points, _ = scan_world(world, 0.8, -0.5, 0.2, np.random.default_rng(5))
    match = MatchedFilterIndex(_map(world, False), search).query(describe_points(points, PARAMS))
    assert match.distinctiveness >= search.min_distinctiveness
    assert math.isnan(match.local_distinctiveness)


def _match(pose, confidence=0.8, distinctiveness=0.8,
           local_distinctiveness=math.nan, score=1.0, place_similarity=math.nan) -> MatchResult:
    return MatchResult(reference_index=0, score=score, confidence=confidence,
                       shift_m=np.zeros(2), rotation_rad=0.0, pose=np.asarray(pose, float),
                       covariance=np.eye(3), relative_covariance=np.eye(3),
                       candidates=np.zeros(1, int), distinctiveness=distinctiveness,
                       local_distinctiveness=local_distinctiveness,
                       place_similarity=place_similarity)


@pytest.mark.parametrize("relative, similarity, accepted", [
    (0.9, 0.32, True), (0.9, 0.40, False), (0.0, 0.32, False), (0.9, math.nan, False)])
def test_a_weak_match_passes_where_its_place_is_as_weakly_alike(relative, similarity, accepted):
    """Under min_confidence, a match passes the confidence test when it reaches
    min_relative_confidence of its place's similarity (0.3 >= 0.9 x 0.32), not where the
    place's own views are more alike (0.9 x 0.40), nor with the test off or no yardstick."""
    search = SearchParams(min_confidence=0.4, min_relative_confidence=relative,
                          consistency_min_support=0)
    verdict = MatchVerifier(search, odometry_known=False).verify(
        _match([1.0, 2.0, 0.1], confidence=0.3, place_similarity=similarity))
    assert verdict.accepted is accepted, verdict.reason
    if not accepted:
        assert verdict.reason.startswith("confidence 0.300 < min_confidence 0.4")
        assert ("place similarity" in verdict.reason) is (relative > 0 and similarity > 0)
        assert ("no other view" in verdict.reason) is (relative > 0 and math.isnan(similarity))


@pytest.mark.parametrize("min_local, local, accepted", [
    (0.0, 0.9, False), (0.3, 0.9, True), (0.3, 0.29, False), (0.3, math.nan, False)])
def test_the_local_test_admits_only_what_the_global_test_refused(min_local, local, accepted):
    search = SearchParams(min_distinctiveness=0.15, min_local_distinctiveness=min_local,
                          consistency_min_support=0)
    verifier = MatchVerifier(search, odometry_known=False)
    verdict = verifier.verify(_match(np.zeros(3), distinctiveness=0.1,
                                     local_distinctiveness=local))
    assert verdict.accepted is accepted
    if not accepted:
        assert "distinctiveness 0.100 < min_distinctiveness" in verdict.reason
        assert ("local" in verdict.reason) is (min_local > 0)
    assert verifier.verify(_match(np.zeros(3), distinctiveness=0.2,
                                  local_distinctiveness=0.0)).accepted


def _drive(n: int, step_m: float = 1.5) -> np.ndarray:
    """Planar poses along a gentle curve."""
    poses = [np.zeros(3)]
    for _ in range(n - 1):
        poses.append(compose_planar(poses[-1], np.array([step_m, 0.0, math.radians(3)])))
    return np.array(poses)


def test_odometry_consistency_accepts_repeated_agreement_and_rejects_a_one_off():
    search = SearchParams(consistency_min_support=2)
    verifier = MatchVerifier(search)
    odometry = _drive(12)
    # The map frame is the odometry frame turned and moved (another session's map).
    map_T_odom = np.array([100.0, -20.0, 0.7])
    truth = compose_planar(map_T_odom, odometry)
    verdicts = []
    for index, (odo, pose) in enumerate(zip(odometry, truth)):
        estimate = pose + [15.0, 4.0, 0.5] if index == 6 else pose + [0.2, -0.1, 0.01]
        verdicts.append(verifier.verify(_match(estimate), odo))
    accepted = [v.accepted for v in verdicts]
    # The first two true matches wait for support; the one-off false match (6) never gets it,
    # nor does it count as support for the later true ones.
    assert accepted[:2] == [False, False] and "odometry consistency" in verdicts[0].reason
    assert accepted[2:6] == [True] * 4 and accepted[7:] == [True] * 5
    assert not accepted[6] and verdicts[6].support == 0
    assert verdicts[5].support == 5 and verdicts[7].support == 6


def test_later_agreement_confirms_the_first_matches_of_a_revisit_but_not_a_one_off():
    verifier = MatchVerifier(SearchParams(consistency_min_support=2))
    odometry = _drive(12)
    truth = compose_planar(np.array([100.0, -20.0, 0.7]), odometry)
    confirms = []
    for index, (odo, pose) in enumerate(zip(odometry, truth)):
        estimate = pose + [15.0, 4.0, 0.5] if index in (0, 6) else pose + [0.2, -0.1, 0.01]
        match = _match(estimate) if index != 3 else None       # 3: no reference found
        confirms.append(verifier.verify(match, odo, key=f"scan {index}").confirms)
    # The revisit's first true matches (1, 2) lack support when they come (none, then one);
    # the third (4) agrees with both and confirms them, once. The false ones (0, 6) agree with
    # nothing and are never confirmed.
    assert confirms[4] == {"scan 1": CONFIRMED_LATER, "scan 2": CONFIRMED_LATER}
    assert all(not keys for index, keys in enumerate(confirms) if index != 4)


def test_a_run_of_two_confirms_neither():
    verifier = MatchVerifier(SearchParams(consistency_min_support=2))
    odometry = _drive(2)
    verdicts = [verifier.verify(_match(pose + [10.0, 0.0, 0.0]), pose, key=k)
                for k, pose in enumerate(odometry)]
    assert verdicts[1].support == 1 and not verdicts[1].accepted
    assert not verdicts[0].confirms and not verdicts[1].confirms


def test_a_stationary_robot_repeating_a_false_match_gets_no_support():
    verifier = MatchVerifier(SearchParams(consistency_min_support=2,
                                          consistency_min_separation_m=1.0))
    wrong = np.array([50.0, 50.0, 1.0])
    verdicts = [verifier.verify(_match(wrong), np.zeros(3)) for _ in range(10)]
    assert not any(v.accepted for v in verdicts)
    assert {v.support for v in verdicts} == {0}


def test_a_robot_standing_still_keeps_a_bounded_number_of_matches():
    """Travel bounds what odometry consistency keeps; standing still, so does MATCHES_KEPT."""
    verifier = MatchVerifier(SearchParams(consistency_min_support=2))
    for index in range(2 * MATCHES_KEPT + 500):
        doubt = DOUBTS["indistinct"] if index % 2 else {}
        verifier.verify(_match(np.array([50.0, 50.0, 1.0]), **doubt), np.zeros(3), key=index)
    assert len(verifier.consistency._candidates) == MATCHES_KEPT
    assert len(verifier.consistency._awaiting_vouch) == MATCHES_KEPT


def test_matches_of_overlapping_submaps_do_not_support_each_other():
    # A wrong place matched by four scans 0.6 m apart (1.8 m of travel), as a sparse sensor's
    # 3 m submaps of one street do: without the window they confirm each other.
    odometry = _drive(4, step_m=0.6)
    wrong = compose_planar(np.array([60.0, -40.0, 3.1]), odometry)
    search = SearchParams(consistency_min_support=2, consistency_min_separation_m=1.0)
    for submap_m, published in ((0.0, True), (3.0, False)):
        verifier = MatchVerifier(search, submap_m=submap_m)
        verdicts = [verifier.verify(_match(pose), odo, key=k)
                    for k, (odo, pose) in enumerate(zip(odometry, wrong))]
        confirmed = any(v.accepted or v.confirms for v in verdicts)
        assert confirmed is published, submap_m
    # A revisit longer than the window still gathers support from its farther matches.
    odometry = _drive(12, step_m=1.5)
    truth = compose_planar(np.array([100.0, -20.0, 0.7]), odometry)
    verifier = MatchVerifier(search, submap_m=3.0)
    verdicts = [verifier.verify(_match(pose), odo) for odo, pose in zip(odometry, truth)]
    assert all(v.accepted for v in verdicts[4:])
    assert verdicts[-1].support == 9           # every earlier match 3 m or more back


def test_a_submap_as_long_as_the_consistency_window_is_refused_by_name():
    """Matches support each other only a submap apart (above), and only within the window: a
    submap as long as the window leaves no match anything to agree with, and every match would
    be refused for want of support (a 30 m window of a narrow sensor's scans did this)."""
    search = SearchParams(consistency_min_support=2, consistency_window_m=30.0)
    with pytest.raises(ConfigError, match=r"submap_m = 30 m.*consistency_window_m = 30 m"):
        MatchVerifier(search, submap_m=30.0)
    MatchVerifier(search, submap_m=29.0)
    MatchVerifier(search, submap_m=30.0, odometry_known=False)
    MatchVerifier(SearchParams(consistency_min_support=0), submap_m=30.0)


INDISTINCT = 0.05
MAP_T_ODOM = np.array([100.0, -20.0, 0.7])
DOUBTS = {"indistinct": {"distinctiveness": INDISTINCT, "local_distinctiveness": INDISTINCT},
          "weak": {"confidence": 0.2},
          "weak and indistinct": {"confidence": 0.2, "distinctiveness": INDISTINCT,
                                  "local_distinctiveness": INDISTINCT}}


def _revisit(doubtful: dict[int, np.ndarray], n: int = 12, search: SearchParams | None = None,
             doubt: str = "indistinct"):
    """Verdicts on a revisit of n matches, each true (0.2 m off) but those in doubtful, which
    fail the tests DOUBTS[doubt] names and are off by the given (x, y, yaw) from the truth."""
    verifier = MatchVerifier(search or SearchParams(consistency_min_support=2))
    odometry = _drive(n)
    truth = compose_planar(MAP_T_ODOM, odometry)
    verdicts = []
    for index, (odo, pose) in enumerate(zip(odometry, truth)):
        if index in doubtful:
            match = _match(pose + doubtful[index], **DOUBTS[doubt])
        else:
            match = _match(pose + [0.2, -0.1, 0.01])
        verdicts.append(verifier.verify(match, odo, key=index))
    return verdicts


def test_a_confirmed_closure_vouches_for_agreeing_indistinct_matches_on_time_and_late():
    right, wrong = np.array([0.3, 0.2, 0.02]), np.array([15.0, 4.0, 0.5])
    verdicts = _revisit({1: right, 8: right, 9: wrong})
    # 1 comes before any closure is confirmed: it waits, and the match that confirms the
    # revisit's first candidates (3 confirms 0 and 2) vouches for it too.
    assert not verdicts[1].accepted and verdicts[1].may_be_confirmed
    assert verdicts[1].reason.endswith(AWAITING_VOUCH)
    assert verdicts[3].accepted
    assert verdicts[3].confirms == {0: CONFIRMED_LATER, 1: VOUCHED, 2: CONFIRMED_LATER}
    # 8 comes after: vouched for on time. It is no candidate and supports no one: 10's
    # support is 7's and 7 itself.
    assert verdicts[8].accepted and verdicts[8].reason == VOUCHED and not verdicts[8].candidate
    assert verdicts[10].support == verdicts[7].support + 1
    # 9 lands 15 m from where the revisit puts it: nothing vouches for it, then or later.
    assert not verdicts[9].accepted
    assert all(9 not in v.confirms for v in verdicts)


@pytest.mark.parametrize("doubt", ["weak", "weak and indistinct"])
def test_a_confirmed_closure_vouches_for_agreeing_weak_matches_as_for_indistinct_ones(doubt):
    """Under min_confidence (the query saw little of the place), alone or with an indistinct
    place: 1 waits and is vouched for late, 8 on time, while 9, as weak but 15 m from where
    the revisit puts it, is never published. A weak match is no candidate: it supports no one."""
    right, wrong = np.array([0.3, 0.2, 0.02]), np.array([15.0, 4.0, 0.5])
    verdicts = _revisit({1: right, 8: right, 9: wrong}, doubt=doubt)
    assert verdicts[1].reason.startswith("confidence 0.200 < min_confidence")
    assert verdicts[1].reason.endswith(AWAITING_VOUCH) and verdicts[1].may_be_confirmed
    assert verdicts[3].confirms == {0: CONFIRMED_LATER, 1: VOUCHED, 2: CONFIRMED_LATER}
    assert verdicts[8].accepted and verdicts[8].reason == VOUCHED and not verdicts[8].candidate
    assert verdicts[10].support == verdicts[7].support + 1
    assert not verdicts[9].accepted and all(9 not in v.confirms for v in verdicts)
    assert ("distinctiveness" in verdicts[9].reason) is (doubt == "weak and indistinct")


def test_a_vouched_weak_match_takes_the_pose_where_the_closures_that_vouch_put_it():
    """A weak peak places the query less precisely than confirmed closures do. Weak matches 1
    (vouched for late) and 8 (on time) lie 0.9 m off and move to where the vouching closures,
    carried along the odometry, put the query: late, one of the closures confirmed then; on
    time, the mean over the agreeing ones. The alignment to the reference follows the pose. An
    indistinct but confident match (9) keeps its own pose."""
    verifier = MatchVerifier(SearchParams(consistency_min_support=2))
    odometry = _drive(12)
    truth = compose_planar(MAP_T_ODOM, odometry)
    off = np.array([0.9, -0.6, 0.03])
    doubts = {1: "weak", 8: "weak", 9: "indistinct"}
    matches, verdicts = [], []
    for index, (odo, pose) in enumerate(zip(odometry, truth)):
        estimate = pose + (off if index in doubts else [0.2, -0.1, 0.01])
        reference_pose = pose + [3.0, 1.0, 0.2]
        match = _match(estimate, **DOUBTS.get(doubts.get(index), {}))
        relative = relative_planar(reference_pose, estimate)
        match.shift_m, match.rotation_rad = relative[:2], float(relative[2])
        matches.append(match)
        verdicts.append(verifier.verify(match, odo, key=index))

    def carried(anchors, index):
        return compose_planar(np.stack([truth[a] + [0.2, -0.1, 0.01] for a in anchors]),
                              relative_planar(odometry[anchors], odometry[index]))

    assert 1 in verdicts[3].confirms and verdicts[8].reason == VOUCHED
    assert any(np.allclose(matches[1].pose, pose) for pose in carried([0, 2, 3], 1))
    assert np.allclose(matches[8].pose, mean_planar(carried([0, 2, 3, 4, 5, 6, 7], 8)))
    for index in (1, 8):
        assert planar_error(matches[index].pose, truth[index])[0] < 0.3
        reference_pose = truth[index] + [3.0, 1.0, 0.2]
        assert np.allclose(compose_planar(reference_pose, [*matches[index].shift_m,
                                                           matches[index].rotation_rad]),
                           matches[index].pose)
    assert verdicts[9].reason == VOUCHED and np.allclose(matches[9].pose, truth[9] + off)


CLOSURE_COVARIANCE = np.diag([0.2 ** 2, 0.2 ** 2, math.radians(0.3) ** 2])


def _carried_by_hand(anchor_pose: np.ndarray, carried_pose: np.ndarray, travel_m: float,
                     search: SearchParams) -> np.ndarray:
    """A closure's covariance carried along the odometry, its swing taken by finite
    differences of compose_planar: the anchor's heading nudged moves the carried pose."""
    offset = relative_planar(anchor_pose, carried_pose)
    swing = np.eye(3)
    for axis in range(3):
        nudge = np.zeros(3)
        nudge[axis] = 1e-6
        swing[:, axis] = wrap_angle(compose_planar(anchor_pose + nudge, offset)
                                    - carried_pose) / 1e-6
    drift = np.diag([(search.odometry_drift * travel_m) ** 2] * 2
                    + [math.radians(search.odometry_yaw_drift_deg_per_m * travel_m) ** 2])
    return swing @ CLOSURE_COVARIANCE @ swing.T + drift


def _dominates(larger: np.ndarray, smaller: np.ndarray) -> bool:
    return bool(np.linalg.eigvalsh(larger - smaller).min() > -1e-9)


def _gap(own: np.ndarray, moved: np.ndarray) -> np.ndarray:
    gap = np.asarray(own, float) - moved
    gap[2] = wrap_angle(gap[2])
    return np.outer(gap, gap)


@pytest.mark.parametrize("drift", [0.01, 0.05])
def test_a_vouched_weak_match_carries_the_closures_covariance_and_the_odometrys_drift(drift):
    """A weak match moved to where the vouching closures put it takes their covariance too:
    each closure's own, swung by its heading error over the distance carried, plus the
    odometry's drift over that travel, averaged over the vouchers, plus their places' spread,
    plus the gap between its own estimate and where it is moved (here 0.7 m: the two
    disagree that much). Never narrower than its own peak's: 8's (falsely sharp) gives way,
    1's (wide across the road) stays where it is wider. The alignment's covariance follows in
    the reference's frame; a confident but indistinct match keeps its own."""
    search = SearchParams(consistency_min_support=2, odometry_drift=drift,
                          odometry_yaw_drift_deg_per_m=0.02)
    verifier = MatchVerifier(search)
    step_m = 1.5
    odometry = _drive(12, step_m)
    truth = compose_planar(MAP_T_ODOM, odometry)
    doubts = {1: "weak", 8: "weak", 9: "indistinct"}
    sharp, across = np.diag([1e-4, 1e-4, 1e-6]), np.diag([1e-4, 9.0, 1e-6])
    matches, own = [], {}
    for index, (odo, pose) in enumerate(zip(odometry, truth)):
        estimate = pose + ([0.7, 0.0, 0.02] if index in doubts else [0.2 * (-1) ** index, -0.1,
                                                                      0.01])
        own[index] = estimate
        match = _match(estimate, **DOUBTS.get(doubts.get(index), {}))
        match.covariance = {1: across, 8: sharp, 9: sharp}.get(index, CLOSURE_COVARIANCE).copy()
        reference_pose = pose + [3.0, 1.0, 0.2]
        relative = relative_planar(reference_pose, estimate)
        match.shift_m, match.rotation_rad = relative[:2], float(relative[2])
        matches.append(match)
        verifier.verify(match, odo, key=index)

    anchors = [0, 2, 3, 4, 5, 6, 7]
    places = compose_planar(np.stack([matches[a].pose for a in anchors]),
                            relative_planar(odometry[anchors], odometry[8]))
    deviation = places - mean_planar(places)
    expected = (np.mean([_carried_by_hand(matches[a].pose, place, step_m * (8 - a), search)
                         for a, place in zip(anchors, places)], axis=0)
                + deviation.T @ deviation / len(anchors) + _gap(own[8], matches[8].pose))
    assert np.allclose(matches[8].covariance, expected, rtol=1e-4, atol=1e-10)
    # Vouched for late by one of the closures confirmed then, from its own place, and as wide
    # as its own peak's across the road.
    late = [_carried_by_hand(matches[a].pose, matches[1].pose, step_m * abs(a - 1), search)
            + _gap(own[1], matches[1].pose) for a in (0, 2, 3)]
    assert any(_dominates(matches[1].covariance, carried) and _dominates(carried + across,
                                                                         matches[1].covariance)
               for carried in late)
    assert _dominates(matches[1].covariance, across)
    for index in (1, 8):
        covariance = matches[index].covariance
        assert np.all(np.linalg.eigvalsh(covariance[:2, :2] - CLOSURE_COVARIANCE[:2, :2]) > 0)
        reference_yaw = truth[index][2] + 0.2
        cos, sin = math.cos(reference_yaw), math.sin(reference_yaw)
        turn = np.array([[cos, -sin, 0.0], [sin, cos, 0.0], [0.0, 0.0, 1.0]])
        assert np.allclose(turn @ matches[index].relative_covariance @ turn.T, covariance)
    # 8 is carried 1.5-12 m: at 5 % drift the odometry's share outweighs the closures' 0.2 m.
    carried = matches[8].covariance - _gap(own[8], matches[8].pose)
    widened = np.trace(carried[:2, :2]) > 3 * np.trace(CLOSURE_COVARIANCE[:2, :2])
    assert bool(widened) is (drift == 0.05)
    assert np.array_equal(matches[9].covariance, sharp)
    assert np.allclose(matches[9].pose, own[9])


def test_a_confirmed_closure_picks_out_the_agreeing_ones_among_waiting_matches():
    verdicts = _revisit({1: np.array([15.0, 4.0, 0.5]), 2: np.array([0.3, 0.2, 0.02])})
    confirms = [key for v in verdicts for key in v.confirms]
    assert 2 in confirms and 1 not in confirms
    assert verdicts[1].may_be_confirmed and verdicts[2].may_be_confirmed


def test_without_a_confirmed_closure_indistinct_matches_publish_nothing():
    """A look-alike street driven along agrees with the odometry all the way, and never with a
    closure confirmed on distinct matches: it stays unpublished however long it is."""
    verdicts = _revisit({index: np.array([40.0, 0.0, 0.0]) for index in range(12)})
    assert not any(v.accepted or v.confirms for v in verdicts)
    assert all(v.reason.endswith(AWAITING_VOUCH) for v in verdicts)


def test_a_vouched_match_vouches_for_no_other():
    """Agreement cannot creep: 6 is vouched for (1.2 m off where the revisit puts it), 7 agrees
    with 6 but lies 2.4 m off, outside the tolerance of the confirmed closures."""
    search = SearchParams(consistency_min_support=2, consistency_tolerance_m=1.5)
    verdicts = _revisit({6: np.array([1.2, 0.0, 0.0]), 7: np.array([2.4, 0.0, 0.0])},
                        search=search)
    assert verdicts[6].accepted and verdicts[6].reason == VOUCHED
    assert not verdicts[7].accepted
    assert all(7 not in v.confirms for v in verdicts)


@pytest.mark.parametrize("doubt", ["indistinct", "weak"])
@pytest.mark.parametrize("change", ["vouch off", "min_score", "icp", "window"])
def test_a_vouch_needs_the_setting_min_score_icp_and_a_closure_within_the_window(change, doubt):
    """A right but indistinct or weak match 9 m after a confirmed revisit is vouched for
    unless one of these changes: the setting off, a score under the caller's min_score, an ICP
    fitness under verify_fitness, or a travel window shorter than the 9 m (it then waits)."""
    def verdict_after_a_confirmed_revisit(change: str):
        search = SearchParams(consistency_min_support=2, consistency_vouch=change != "vouch off",
                              consistency_vouch_window_m=6.0 if change == "window" else 30.0,
                              verify_fitness=0.6 if change == "icp" else 0.0)
        verifier = MatchVerifier(search, min_score=2.0 if change == "min_score" else 0.0)
        odometry = _drive(12)
        truth = compose_planar(MAP_T_ODOM, odometry)

        def fitness(match):
            return 0.5 if change == "icp" and match.score < 3.0 else 0.9
        for odo, pose in zip(odometry[:4], truth[:4]):
            assert not verifier.verify(_match(pose + [0.2, -0.1, 0.01], score=3.0), odo,
                                       fitness).reason.startswith(("score", "ICP"))
        for odo in odometry[4:10]:                     # 9 m travelled without a match
            verifier.verify(None, odo)
        return verifier.verify(_match(truth[10] + [0.3, 0.2, 0.02], **DOUBTS[doubt]),
                               odometry[10], fitness)

    assert verdict_after_a_confirmed_revisit("none").accepted
    verdict = verdict_after_a_confirmed_revisit(change)
    assert not verdict.accepted and verdict.may_be_confirmed is (change == "window")
    failed = "distinctiveness" if doubt == "indistinct" else "min_confidence"
    expected = {"vouch off": failed, "min_score": "min_score", "icp": "ICP fitness",
                "window": AWAITING_VOUCH}[change]
    assert expected in verdict.reason


@pytest.mark.parametrize("vouch_window_m", [30.0, 60.0])
def test_a_vouch_reaches_its_own_window_while_support_keeps_the_consistency_window(
        vouch_window_m):
    """A revisit confirmed on its first 4 matches, 45 m without a match, then a right but
    indistinct match and a distinct one. The distinct one finds no support that far back
    (support keeps consistency_window_m); both are vouched for only when the vouch window
    reaches 45 m. The same holds backwards: a match waiting 45 m before a revisit is confirmed
    is vouched for late only within the vouch window."""
    search = SearchParams(consistency_min_support=2, consistency_window_m=30.0,
                          consistency_vouch_window_m=vouch_window_m)
    odometry = _drive(36)
    truth = compose_planar(MAP_T_ODOM, odometry)
    near = np.array([0.2, -0.1, 0.01])
    forward = MatchVerifier(search)
    for odo, pose in zip(odometry[:4], truth[:4]):
        forward.verify(_match(pose + near), odo)
    for odo in odometry[4:34]:                         # 45 m without a match
        forward.verify(None, odo)
    indistinct = forward.verify(_match(truth[34] + near, **DOUBTS["indistinct"]), odometry[34])
    distinct = forward.verify(_match(truth[35] + near), odometry[35])
    assert indistinct.accepted is (vouch_window_m == 60.0)
    assert distinct.support == 0 and distinct.accepted is (vouch_window_m == 60.0)

    backward = MatchVerifier(search)
    waiting = backward.verify(_match(truth[0] + near, **DOUBTS["indistinct"]), odometry[0],
                              key="waiting")
    assert waiting.may_be_confirmed and not waiting.accepted
    for odo in odometry[1:31]:
        backward.verify(None, odo)
    confirms = [key for odo, pose in zip(odometry[31:], truth[31:])
                for key in backward.verify(_match(pose + near), odo).confirms]
    assert ("waiting" in confirms) is (vouch_window_m == 60.0)


def _long_revisit(search: SearchParams, indistinct: dict[int, np.ndarray], n: int,
                  skipped: range = range(0), odometry_scale: float = 1.0) -> list:
    """Verdicts on a revisit of n matches 1.5 m apart: the first 4 distinct and right, the
    rest indistinct and off by indistinct.get(index, 0.2 m); none at the indices skipped. The
    odometry handed to the verifier is the truth scaled by odometry_scale (drift)."""
    verifier = MatchVerifier(search)
    truth_odometry = _drive(n)
    truth = compose_planar(MAP_T_ODOM, truth_odometry)
    odometry = truth_odometry * [odometry_scale, odometry_scale, 1.0]
    near = np.array([0.2, -0.1, 0.01])
    verdicts = []
    for index, (odo, pose) in enumerate(zip(odometry, truth)):
        if index in skipped:
            verdicts.append(verifier.verify(None, odo))
        elif index < 4:
            verdicts.append(verifier.verify(_match(pose + near), odo, key=index))
        else:
            verdicts.append(verifier.verify(_match(pose + indistinct.get(index, near),
                                                   **DOUBTS["indistinct"]), odo, key=index))
    return verdicts


def test_a_vouch_names_a_match_the_revisit_check_reported():
    # The same revisit; at index 6 the search reported the place the revisit predicted
    # (SearchParams.revisit_check): its verdict says so, the others' do not.
    search = SearchParams(consistency_min_support=2)
    verifier = MatchVerifier(search)
    odometry = _drive(10)
    truth = compose_planar(MAP_T_ODOM, odometry)
    reasons = []
    for index, (odo, pose) in enumerate(zip(odometry, truth)):
        match = _match(pose + [0.2, -0.1, 0.01],
                       **(DOUBTS["indistinct"] if index >= 4 else {}))
        match.revisit_predicted = index == 6
        reasons.append(verifier.verify(match, odo, key=index).reason)
    assert reasons[6] == VOUCHED_WHERE_PREDICTED
    assert all(reason == VOUCHED for reason in reasons[4:6] + reasons[7:])


def test_a_closure_vouches_along_the_whole_revisit_it_anchors():
    """A revisit confirmed on its first 4 matches goes on for 100 m of indistinct matches,
    with a vouch window of 20 m: each is vouched for, the closure's reach moving with the
    matches it vouches for. A match 15 m off does not move it: past 20 m of such matches the
    revisit's right ones wait. A gap longer than the window ends the reach as well."""
    search = SearchParams(consistency_min_support=2, consistency_vouch_window_m=20.0)
    verdicts = _long_revisit(search, {}, 70)
    assert all(v.accepted for v in verdicts[3:])
    assert all(v.reason == VOUCHED for v in verdicts[4:])

    wrong = {index: np.array([15.0, 4.0, 0.5]) for index in range(10, 26)}   # 22.5 m
    verdicts = _long_revisit(search, wrong, 40)
    assert all(v.accepted for v in verdicts[4:10])
    assert not any(v.accepted for v in verdicts[10:])
    assert all(v.may_be_confirmed for v in verdicts[26:])

    verdicts = _long_revisit(search, {}, 40, skipped=range(10, 25))
    assert all(v.accepted for v in verdicts[4:10])
    assert not any(v.accepted for v in verdicts[25:])


def test_the_odometry_drift_ends_a_long_revisit_vouch():
    """With odometry 3 % short, where the closure puts the query strays from the truth by
    ~4.5 cm a metre: the right matches of the revisit are vouched for until the gap passes
    consistency_tolerance_m (1.5 m, ~50 m on), then wait, though each lies within the window
    of the last one vouched for."""
    search = SearchParams(consistency_min_support=2, consistency_vouch_window_m=20.0,
                          consistency_tolerance_m=1.5)
    verdicts = _long_revisit(search, {}, 70, odometry_scale=0.97)
    vouched = [index for index, v in enumerate(verdicts) if v.reason == VOUCHED]
    assert vouched[0] == 4 and vouched == list(range(4, vouched[-1] + 1))
    assert 20 < vouched[-1] < 50
    assert not any(v.accepted for v in verdicts[vouched[-1] + 2:])


def test_a_closure_vouches_for_an_unsupported_match_only_if_confirmed_without_it():
    """Distinct matches that lack support (fewer than 2 agree) are vouched for, like
    indistinct ones, by a closure confirmed in the vouch window, but never by a closure that
    their own agreement confirmed. A (true), B (1 m off) and C (1 m off the other way) each
    agree with A, not with each other: C's agreement confirms A, so A vouches for neither B
    nor C. D, 4 steps later, lacks support but agrees with A, confirmed without it: vouched,
    and so is the match after it. The one after that is confirmed by those two; neither is
    published a second time, and the closure it makes, confirmed without B and C, vouches for
    them (each within the tolerance of where it puts them): they are published for the vouch,
    not as confirmed."""
    # Support from the last 6 m only: A, B and C count for one another, not for D.
    verifier = MatchVerifier(SearchParams(consistency_min_support=2, consistency_window_m=6.0))
    odometry = _drive(10)
    truth = compose_planar(MAP_T_ODOM, odometry)
    ahead, behind = np.array([0.0, 1.0, 0.0]), np.array([0.0, -1.0, 0.0])
    verdicts = {}
    for key, index, offset in (("A", 0, np.zeros(3)), ("B", 1, ahead), ("C", 2, behind)):
        verdicts[key] = verifier.verify(_match(truth[index] + offset), odometry[index], key=key)
    assert [verdicts[k].support for k in "ABC"] == [0, 1, 1]
    assert verdicts["C"].confirms == {"A": CONFIRMED_LATER} and not verdicts["C"].accepted
    assert verdicts["C"].may_be_confirmed
    for index in (3, 4, 5, 6):
        verifier.verify(None, odometry[index])
    verdicts["D"] = verifier.verify(_match(truth[7]), odometry[7], key="D")
    assert verdicts["D"].support == 0 and verdicts["D"].accepted
    assert verdicts["D"].reason == VOUCHED
    later = [verifier.verify(_match(truth[index]), odometry[index], key=index)
             for index in (8, 9)]
    assert later[0].support == 1 and later[0].reason == VOUCHED
    assert later[1].support == 2 and later[1].reason == "accepted"
    assert later[1].confirms == {"B": VOUCHED, "C": VOUCHED}


def test_support_expires_after_the_travel_window():
    verifier = MatchVerifier(SearchParams(consistency_min_support=1, consistency_window_m=10.0))
    odometry = _drive(20, step_m=2.0)
    first = verifier.verify(_match(odometry[0]), odometry[0])
    for pose in odometry[1:8]:
        verifier.verify(None, pose)                    # travel without a match: 14 m
    later = verifier.verify(_match(odometry[8]), odometry[8])
    assert first.support == 0 and later.support == 0 and not later.accepted


def test_a_revisit_names_where_it_puts_the_query_only_when_a_match_contradicts_it():
    # What a stream's search asks of a weak match (SearchParams.prefilter_retry "revisits"):
    # within consistency_vouch_window_m of travel after a confirmed closure, where do the
    # confirmed closures, carried along the odometry, put the query, if not where the match
    # does?
    search = SearchParams(consistency_min_support=2, consistency_vouch_window_m=20.0)
    verifier = MatchVerifier(search)
    odometry = _drive(30, step_m=2.0)
    map_T_odom = np.array([100.0, -20.0, 0.7])
    truth = compose_planar(map_T_odom, odometry)
    elsewhere = truth + [40.0, 15.0, 0.3]
    here, there = [], []
    for index, (odo, pose) in enumerate(zip(odometry, truth)):
        here.append(verifier.revisit_places(_match(pose), odo))
        there.append(verifier.revisit_places(_match(elsewhere[index]), odo))
        verifier.verify(_match(pose + [0.2, -0.1, 0.01]) if index < 4 else None, odo)
    # Asked before each scan is verified: the revisit begins with the scan after the third
    # match (which two agreeing ones confirm), and ends once the scan before has travelled
    # 20 m past the last confirmed one (the fourth, at 6 m). Where the revisit puts the
    # query, nothing contradicts it.
    assert not any(len(places) for places in here)
    assert [len(places) > 0 for places in there] == [False] * 3 + [True] * 12 + [False] * 15
    for index in range(3, 15):
        # One pose per confirmed closure, each where the match it was confirmed on puts it.
        assert there[index].shape[1] == 3
        assert np.abs(there[index][:, :2] - (truth[index, :2] + [0.2, -0.1])).max() < 0.3
        assert np.abs(wrap_angle(there[index][:, 2] - truth[index, 2] - 0.01)).max() < 0.01
    assert not len(MatchVerifier(search, odometry_known=False).revisit_places(
        _match(elsewhere[5]), odometry[5]))


def test_cheap_tests_run_before_icp_and_icp_decides():
    search = SearchParams(min_confidence=0.5, min_distinctiveness=0.2, verify_fitness=0.6,
                          consistency_min_support=0)
    verifier = MatchVerifier(search)
    calls = []

    def fitness(value):
        def run(match):
            calls.append(match)
            return value
        return run

    assert not verifier.verify(_match(np.zeros(3), confidence=0.4), None, fitness(0.9)).accepted
    assert not verifier.verify(_match(np.zeros(3), distinctiveness=0.1), None,
                               fitness(0.9)).accepted
    assert calls == []
    low = verifier.verify(_match(np.zeros(3)), None, fitness(0.5))
    high = verifier.verify(_match(np.zeros(3)), None, fitness(0.7))
    assert (low.accepted, high.accepted) == (False, True) and len(calls) == 2
    assert low.fitness == 0.5 and "ICP fitness" in low.reason
    missing = verifier.verify(_match(np.zeros(3)), None, None)
    assert not missing.accepted and "verify_fitness" in missing.reason


def test_consistency_without_odometry_is_refused_or_skipped():
    search = SearchParams(consistency_min_support=2)
    with pytest.raises(ValueError, match="odometry"):
        MatchVerifier(search).verify(_match(np.zeros(3)), None)
    skipped = MatchVerifier(search, odometry_known=False)
    assert not skipped.consistency_active
    assert skipped.verify(_match(np.zeros(3)), None).accepted


def test_a_reference_farther_along_that_puts_the_query_where_the_match_does_is_no_rival(world):
    """Between two references 11 m apart (farther than distinct_radius_m) a query sees the
    same place from both: both align it to one pose. The farther one is the same answer, not
    a look-alike; counted as the other place, it made the match indistinct."""
    rng = np.random.default_rng(0)
    reference_map = ReferenceMap(PARAMS)
    for index, place in enumerate([(0.0, 0.0, 0.0), (11.0, 0.0, 0.0), (0.0, 25.0, -2.0),
                                   (-25.0, -10.0, 2.5)]):
        points, pose = scan_world(world, *place, rng)
        reference_map.append(describe_points(points, PARAMS, reference=True, seed_key=index),
                             pose, float(index), index)
    points, truth = scan_world(world, 5.5, 0.4, 0.05, np.random.default_rng(7))
    query = describe_points(points, PARAMS)
    outcomes = {}
    for rivals in (0, 3):
        search = SearchParams(min_confidence=0.3, consistency_min_support=0,
                              min_local_distinctiveness=0.0, distinct_aligned_rivals=rivals)
        match = MatchedFilterIndex(reference_map, search).query(query)
        assert match.reference_index in (0, 1)
        assert np.hypot(*(match.pose[:2] - truth[:2, 3])) < 0.5
        verdict = MatchVerifier(search, odometry_known=False).verify(match)
        outcomes[rivals] = (verdict.accepted, match.distinctiveness)
    assert outcomes[0][0] is False and outcomes[0][1] < 0.15
    assert outcomes[3][0] is True and outcomes[3][1] >= 0.15
    # The farther reference's heading 8 degrees off its view's (a map drifted between the
    # two): its alignment still lands within a metre of the match's, but turned more than
    # the local stage searches. Not the same answer: a rival again.
    drifted = turned_view_map(reference_map, [(0, 0.0, 0.0), (1, np.radians(8.0), 0.0),
                                              (2, 0.0, 0.0), (3, 0.0, 0.0)])
    search = SearchParams(min_confidence=0.3, consistency_min_support=0,
                          min_local_distinctiveness=0.0, distinct_aligned_rivals=3)
    match = MatchedFilterIndex(drifted, search).query(query)
    assert match.reference_index in (0, 1) and match.distinctiveness < 0.15
    assert not MatchVerifier(search, odometry_known=False).verify(match).accepted
