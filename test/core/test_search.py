import numpy as np
import pytest
from helpers import turned_view_map

from mf_lpr_ros.config import preset
from mf_lpr_ros.core.descriptor import (
    describe_density_image,
    describe_points,
    pooled_weights,
    rotate_occupancy,
)
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.pose import (
    alignment_from_poses,
    planar,
    planar_error,
    query_pose_from_alignment,
    reference_distance,
    wrap_angle,
)
from mf_lpr_ros.core.refine import refine_match
from mf_lpr_ros.core.search import MatchedFilterIndex
from mf_lpr_ros.params import DescriptorParams, SearchParams
from mf_lpr_ros.pipeline.mapping import describe_scan
from mf_lpr_ros.sim.synthetic import make_world, scan_world

PARAMS = DescriptorParams(voxel_size=0.4, z_min=-1.2)


def yaw_error_deg(a, b):
    return abs(np.degrees(wrap_angle(a - b)))


def five_places(world, params: DescriptorParams = PARAMS, first_yaw: float = 0.0) -> ReferenceMap:
    """A map of five places of the world, 25 m or more apart, the first at the origin facing
    first_yaw."""
    rng = np.random.default_rng(0)
    reference_map = ReferenceMap(params)
    for i, (x, y, yaw) in enumerate([(0, 0, first_yaw), (25, 0, 1.0), (0, 25, -2.0),
                                     (-25, -10, 2.5), (20, 20, 0.3)]):
        points, pose = scan_world(world, x, y, yaw, rng)
        reference_map.append(describe_points(points, params, reference=True, seed_key=i), pose,
                             float(i), i)
    return reference_map


@pytest.fixture(scope="module")
def synthetic_map(world):
    return five_places(world)


@pytest.mark.parametrize("truth,expected_ref", [((1.3, -0.7, 0.5), 0), ((24.1, 1.9, -2.0), 1),
                                                ((-0.5, 26.2, 3.0), 2), ((-23.7, -11.1, 1.2), 3),
                                                ((21.45, 18.2, -1.7), 4)])
@pytest.mark.parametrize("prefilter_top_k,yaw_window_deg", [(0, 0.0), (2, 0.0), (2, 6.0)])
def test_known_transform_is_recovered(world, synthetic_map, truth, expected_ref, prefilter_top_k,
                                      yaw_window_deg):
    # top_k 2 of 5 references: the polar-spectrum prefilter must keep the right one (and,
    # with a yaw window, its angle must hold the right heading).
    points, _ = scan_world(world, *truth, np.random.default_rng(1))
    result = MatchedFilterIndex(synthetic_map, SearchParams(
        prefilter_top_k=prefilter_top_k, global_yaw_window_deg=yaw_window_deg)
                                ).query(describe_points(points, PARAMS))
    assert result.reference_index == expected_ref
    assert np.hypot(*(result.pose[:2] - truth[:2])) < 0.15
    assert yaw_error_deg(result.pose[2], truth[2]) < 0.6
    # The loop-closure constraint: the query pose in the reference frame.
    reference = synthetic_map.planar_poses[expected_ref]
    c, s = np.cos(reference[2]), np.sin(reference[2])
    local = np.array([[c, s], [-s, c]]) @ (np.array(truth[:2]) - reference[:2])
    np.testing.assert_allclose(result.shift_m, local, atol=0.15)
    assert result.candidates[0] == expected_ref
    assert 0.3 < result.confidence <= 1.0
    # The local stage's finalists, the match itself first, then the others by score.
    assert len(result.hypotheses) >= 2
    assert result.hypotheses[0].reference_index == expected_ref
    assert np.array_equal(result.hypotheses[0].pose, result.pose)
    others = [hypothesis.score for hypothesis in result.hypotheses[1:]]
    assert others == sorted(others, reverse=True)
    assert np.all(np.linalg.eigvalsh(result.covariance) > 0)
    assert set(result.timings_ms) == {"global", "prefilter", "local"}


def test_the_default_yaw_window_scores_the_heading_nearest_the_true_yaw(synthetic_map):
    """The prefilter knows a candidate's yaw modulo half a turn, within 2.1 degrees on every
    right match measured: at the default window the heading nearest the true yaw is scored
    wherever within 2.4 degrees the angle falls, and about 4 of the 72 headings are (6 only
    where the angle lands on a heading)."""
    index = MatchedFilterIndex(synthetic_map, SearchParams(prefilter_top_k=2))
    headings = index.global_angles
    true_yaws = np.arange(0.0, 360.0, 0.7)
    gap = np.abs((headings[None, :] - true_yaws[:, None] + 180.0) % 360.0 - 180.0)
    nearest = np.argmin(gap, axis=1)
    for error in np.linspace(-2.4, 2.4, 9):
        index.prefilter.angles = lambda image, searched, error=error: (true_yaws + error) % 180.0
        allowed = index._allowed_headings(None, np.arange(len(true_yaws)))
        assert allowed[np.arange(len(true_yaws)), nearest].all(), error
        assert allowed.sum(axis=1).max() <= 6
        assert allowed.sum(axis=1).mean() <= 4.1


@pytest.mark.parametrize("prefilter_top_k", [0, 2, 5])
def test_a_match_says_which_references_its_candidate_stage_kept(world, synthetic_map,
                                                                prefilter_top_k):
    """The prefilter's list (and its map neighbours) when it narrowed the search; None when
    every reference was searched (no prefilter, or one that would keep them all)."""
    points, _ = scan_world(world, 24.1, 1.9, -2.0, np.random.default_rng(1))
    query = describe_points(points, PARAMS)
    index = MatchedFilterIndex(synthetic_map, SearchParams(prefilter_top_k=prefilter_top_k,
                                                           prefilter_expand_m=0.0))
    result = index.query(query)
    if prefilter_top_k in (0, len(synthetic_map)):
        assert result.searched is None
    else:
        assert result.searched.tolist() == index.candidates(query, prefilter_top_k).tolist()
        assert len(result.searched) == prefilter_top_k
        assert result.reference_index in result.searched


@pytest.mark.parametrize("prefilter_top_k", [0, 2])
def test_two_threads_find_what_one_finds(world, synthetic_map, prefilter_top_k):
    points, _ = scan_world(world, 21.45, 18.2, -1.7, np.random.default_rng(1))
    query = describe_points(points, PARAMS)
    one, two = (MatchedFilterIndex(synthetic_map, SearchParams(
        threads=threads, prefilter_top_k=prefilter_top_k)).query(query) for threads in (1, 2))
    assert two.reference_index == one.reference_index
    np.testing.assert_allclose(two.pose, one.pose, atol=1e-6)
    assert two.confidence == pytest.approx(one.confidence, abs=1e-6)
    assert ([h.reference_index for h in two.hypotheses]
            == [h.reference_index for h in one.hypotheses])


def test_finalists_at_one_heading_turn_the_query_once(world, monkeypatch):
    # Three references of one place: the finalists share the global heading, so the local
    # stage turns and transforms the query once per local angle, not once per finalist.
    reference_map = ReferenceMap(PARAMS)
    for i, x in enumerate((0.0, 0.4, 0.8)):
        points, pose = scan_world(world, x, 0, 0, np.random.default_rng(i))
        reference_map.append(describe_points(points, PARAMS, reference=True, seed_key=i), pose, i)
    index = MatchedFilterIndex(reference_map, SearchParams(threads=1, top_n=3))
    points, _ = scan_world(world, 0.3, 0.2, 0.05, np.random.default_rng(9))
    query = describe_points(points, PARAMS)
    turned = []
    original = index._rotated

    def counting(image, angles, only):
        if image is query:
            turned.append(len(angles) if only is None else len(only))
        return original(image, angles, only)

    monkeypatch.setattr(index, "_rotated", counting)
    result = index.query(query)
    assert {h.reference_index for h in result.hypotheses} == {0, 1, 2}
    n_angles = len(index.local_offsets)
    # Each finalist alone turns the query to 5 of the 7 angles: 15 for three.
    assert 0 < sum(turned) <= n_angles


def test_the_last_finalist_is_another_place_than_the_others(world):
    # Three views of the query's place filed 200 m away (a look-alike street, as far as the
    # map can tell) outrank the true place's one view, 3.5 m off. Top_n 3 by rank aligns the
    # look-alike three times; another_place_finalist spends the third alignment on the true
    # place. Not where the map's headings are unknown: no alignment says where the query is.
    reference_map = ReferenceMap(PARAMS)
    for i, x in enumerate((0.0, 2.0, -2.0)):
        points, pose = scan_world(world, x, 0, 0, np.random.default_rng(i))
        pose[0, 3] += 200.0
        reference_map.append(describe_points(points, PARAMS, reference=True, seed_key=i), pose, i)
    points, pose = scan_world(world, 3.5, 0, 0, np.random.default_rng(3))
    reference_map.append(describe_points(points, PARAMS, reference=True, seed_key=3), pose, 3)
    points, _ = scan_world(world, 0.3, 0.2, 0.05, np.random.default_rng(9))
    query = describe_points(points, PARAMS)

    def finalists(another_place, map_headings="known", min_distinctiveness=0.15):
        match = MatchedFilterIndex(reference_map, SearchParams(
            top_n=3, map_headings=map_headings, another_place_finalist=another_place,
            min_distinctiveness=min_distinctiveness)).query(query)
        return match, {h.reference_index for h in match.hypotheses}

    by_rank, aligned = finalists(False)
    assert aligned == {0, 1, 2} and by_rank.candidates[3] == 3
    _, aligned = finalists(True)
    assert 3 in aligned and len(aligned & {0, 1, 2}) == 2
    _, aligned = finalists(True, "unknown")
    assert aligned == {0, 1, 2}
    # Only a rival that would leave the match indistinct takes the place of a view.
    _, aligned = finalists(True, min_distinctiveness=0.01)
    assert aligned == {0, 1, 2}


@pytest.mark.parametrize("n_angles", [7, 11])
def test_the_local_stage_finds_a_smooth_peak_at_any_angle_from_part_of_them(synthetic_map,
                                                                            n_angles):
    """Every other angle, then the two beside the best: a peak that falls off smoothly is
    found wherever it lies, the ends included, with both its neighbours correlated for the
    sub-degree fit, from (n - 1) / 2 + 2 of the n angles."""
    index = MatchedFilterIndex(synthetic_map, SearchParams(threads=1))
    shifts = 2 * index.high_shift + 1
    for peak in range(n_angles):
        correlated = []

        def correlate(jobs, indices, peak=peak):
            assert (jobs == 0).all()
            correlated.extend(indices.tolist())
            heights = np.exp(-0.5 * ((indices - peak) / 1.5) ** 2)
            return np.broadcast_to(heights[:, None, None], (len(indices), shifts, shifts))

        surface = index._coarse_to_fine(correlate, 1, n_angles)[0]
        per_angle = surface.reshape(n_angles, -1).max(axis=1)
        assert int(np.argmax(per_angle)) == peak
        neighbours = [k for k in (peak - 1, peak + 1) if 0 <= k < n_angles]
        assert np.isfinite(per_angle[neighbours]).all()
        assert len(correlated) == len(set(correlated)) == (n_angles - 1) // 2 + 2


def test_the_local_stage_batches_finalists_each_to_its_own_peak(synthetic_map):
    """Several jobs in one batch: each job's angles are chosen from its own surfaces."""
    index = MatchedFilterIndex(synthetic_map, SearchParams(threads=1))
    shifts = 2 * index.high_shift + 1
    n_angles, peaks = 7, np.array([0, 3, 6, 4])
    calls = []

    def correlate(jobs, indices):
        calls.append(len(jobs))
        heights = np.exp(-0.5 * ((indices - peaks[jobs]) / 1.5) ** 2)
        return np.broadcast_to(heights[:, None, None], (len(indices), shifts, shifts))

    surfaces = index._coarse_to_fine(correlate, len(peaks), n_angles)
    assert (surfaces.reshape(len(peaks), n_angles, -1).max(axis=2).argmax(axis=1)
            == peaks).all()
    # Two batches, whatever the number of jobs.
    assert len(calls) == 2


def test_a_sharpened_local_stage_keeps_the_images_cosine_as_confidence(world, synthetic_map):
    points, _ = scan_world(world, 1.3, -0.7, 0.5, np.random.default_rng(1))
    query = describe_points(points, PARAMS)
    plain, sharpened = (MatchedFilterIndex(synthetic_map, SearchParams(local_sharpening=s)
                                           ).query(query) for s in (0.0, 0.25))
    assert sharpened.reference_index == plain.reference_index == 0
    # The same cell and angle: the sharpened peak only scores them differently.
    np.testing.assert_allclose(sharpened.pose, plain.pose, atol=0.1)
    assert sharpened.score > plain.score
    assert sharpened.confidence == pytest.approx(plain.confidence, abs=1e-5)


def test_sub_cell_refinement_beats_cell_quantisation(world, synthetic_map):
    rng = np.random.default_rng(2)
    errors = []
    for offset in np.linspace(0.05, 0.35, 7):
        truth = (offset, -offset / 2, 0.0)
        points, _ = scan_world(world, *truth, rng)
        result = MatchedFilterIndex(synthetic_map, SearchParams()).query(
            describe_points(points, PARAMS))
        errors.append(np.hypot(*(result.pose[:2] - truth[:2])))
    # Rounding to the 0.4 m cell would err by up to 0.2 m per axis.
    assert np.mean(errors) < 0.08


def test_unseen_place_gets_low_confidence(world, synthetic_map):
    from mf_lpr_ros.sim.synthetic import make_world

    elsewhere = make_world(seed=99)
    points, _ = scan_world(elsewhere, 0, 0, 0, np.random.default_rng(3))
    unseen = MatchedFilterIndex(synthetic_map, SearchParams()).query(describe_points(points,
                                                                                     PARAMS))
    points, _ = scan_world(world, 0.5, 0.5, 0.2, np.random.default_rng(3))
    seen = MatchedFilterIndex(synthetic_map, SearchParams()).query(describe_points(points, PARAMS))
    assert unseen.confidence < 0.5 * seen.confidence


def _ranking_prefilter(index, ranking):
    """index's prefilter made to rank the references in the given order; records each k."""
    asked = []

    def top(image, k, stop=None):
        asked.append(k)
        return np.array([r for r in ranking if stop is None or r < stop][:k])
    index.prefilter.top = top
    return asked


# Where a stream's revisit puts the scan when it contradicts the weak match
# (MatchVerifier.revisit_places): None, no verifier's answer; "agrees", nowhere (the weak
# match is where the revisit puts it); "mapped", at the query's true place; "unmapped", 900 m
# from any reference (a revisit carried on past the mapped route).
_REVISIT_PLACES = {"agrees": np.zeros((0, 3)), "mapped": np.array([[1.3, -0.7, 0.5]]),
                   "unmapped": np.array([[900.0, 900.0, 0.0]])}


@pytest.mark.parametrize("retry_top_k, retry, answers_request, revisit, retried", [
    (0, "every_query", True, "mapped", False),      # no wider list to search
    (4, "requests", False, "mapped", False),        # a stream's query, even where contradicted
    (4, "requests", True, "agrees", True),          # a relocalisation request
    (4, "revisits", False, None, False),            # a stream without a verifier's answer
    (4, "revisits", False, "agrees", False),
    (4, "revisits", False, "mapped", True),
    (4, "revisits", False, "unmapped", False),
    (4, "revisits", True, "agrees", True),
    (4, "every_query", False, "agrees", True)])
def test_a_weak_match_is_searched_again_over_the_wider_candidate_list(
        world, synthetic_map, retry_top_k, retry, answers_request, revisit, retried):
    points, _ = scan_world(world, 1.3, -0.7, 0.5, np.random.default_rng(1))
    query = describe_points(points, PARAMS)
    # The retry alone: the revisit check would read the same places (the test below).
    index = MatchedFilterIndex(synthetic_map, SearchParams(
        prefilter_top_k=1, prefilter_rescore_k=0, prefilter_retry_top_k=retry_top_k,
        prefilter_retry=retry, prefilter_expand_m=0.0, revisit_check=False))
    # The prefilter puts the true place (reference 0) fourth.
    asked = _ranking_prefilter(index, [3, 4, 1, 0, 2])
    asked_of = []

    def revisit_places(weak):
        asked_of.append(weak.reference_index)
        return _REVISIT_PLACES[revisit]

    result = index.query(query, request=answers_request,
                         revisit_places=None if revisit is None else revisit_places)
    # The stream is asked about a weak match only, and only where its answer decides.
    assert asked_of == ([3] if retry == "revisits" and not answers_request
                        and revisit is not None else [])
    if retried:
        assert asked == [1, 4]
        assert result.reference_index == 0
        assert np.hypot(*(result.pose[:2] - (1.3, -0.7))) < 0.15
    else:
        assert asked == [1]
        assert result.reference_index == 3
        assert result.confidence < SearchParams().min_confidence


@pytest.mark.parametrize("revisit_check, revisit_pose, reported", [
    (True, (1.3, -0.7, 0.5), 0),           # the revisit's place: reported, as it aligns there
    (False, (1.3, -0.7, 0.5), 3),          # the option off
    (True, (3.8, 1.0, 0.5), 3),            # 3 m off the place the scan aligns at
    (True, (1.3, -0.7, 0.95), 3),          # turned 26 degrees from the scan's alignment
    (True, (900.0, 900.0, 0.0), 3),        # past the mapped route
    (True, None, 3)])                      # no revisit contradicts the match
def test_a_match_that_contradicts_the_revisit_gives_way_to_the_place_the_revisit_predicts(
        world, synthetic_map, revisit_check, revisit_pose, reported):
    points, _ = scan_world(world, 1.3, -0.7, 0.5, np.random.default_rng(1))
    index = MatchedFilterIndex(synthetic_map, SearchParams(
        prefilter_top_k=1, prefilter_rescore_k=0, prefilter_retry_top_k=0,
        prefilter_expand_m=0.0, revisit_check=revisit_check))
    # The candidate stage hands on a wrong place alone (reference 3): a weak match.
    _ranking_prefilter(index, [3, 4, 1, 0, 2])
    asked_of = []

    def revisit_places(match):
        asked_of.append(match.reference_index)
        return np.zeros((0, 3)) if revisit_pose is None else np.array([revisit_pose])

    result = index.query(describe_points(points, PARAMS), revisit_places=revisit_places)
    assert asked_of == ([3] if revisit_check else [])
    assert result.reference_index == reported
    if reported == 0:
        assert np.hypot(*(result.pose[:2] - (1.3, -0.7))) < 0.15
        assert yaw_error_deg(result.pose[2], 0.5) < 0.6
        # The images alone did not single it out: only a vouch publishes it.
        assert result.distinctiveness == 0.0 and result.revisit_predicted
        assert [h.reference_index for h in result.hypotheses][:2] == [0, 3]
    else:
        assert result.confidence < SearchParams().min_confidence
        assert not result.revisit_predicted


def test_the_revisit_checks_reference_is_listed_once_among_the_hypotheses(world, synthetic_map):
    # The true place (reference 0) is a finalist beside a wrong one, and weak under a high
    # confidence floor; the revisit names that place again: one answer, listed once.
    points, _ = scan_world(world, 1.3, -0.7, 0.5, np.random.default_rng(1))
    index = MatchedFilterIndex(synthetic_map, SearchParams(
        prefilter_top_k=2, prefilter_rescore_k=0, prefilter_retry_top_k=0,
        prefilter_expand_m=0.0, top_n=2, min_confidence=0.99, min_relative_confidence=0.0))
    _ranking_prefilter(index, [3, 0, 4, 1, 2])
    result = index.query(describe_points(points, PARAMS),
                         revisit_places=lambda match: np.array([[1.3, -0.7, 0.5]]))
    references = [h.reference_index for h in result.hypotheses]
    assert result.revisit_predicted and references[0] == 0
    assert sorted(references) == [0, 3]


def test_a_strong_match_is_not_searched_again(world, synthetic_map):
    points, _ = scan_world(world, 1.3, -0.7, 0.5, np.random.default_rng(1))
    index = MatchedFilterIndex(synthetic_map, SearchParams(
        prefilter_top_k=1, prefilter_rescore_k=0, prefilter_retry_top_k=4,
        prefilter_expand_m=0.0))
    asked = _ranking_prefilter(index, [0, 3, 4, 1, 2])
    result = index.query(describe_points(points, PARAMS), request=True)
    assert asked == [1]
    assert result.reference_index == 0
    assert result.confidence >= SearchParams().min_confidence


@pytest.mark.parametrize("rescore_k", [0, 5])
def test_the_coarse_filter_ranks_again_what_the_prefilter_ranked_low(
        world, synthetic_map, rescore_k):
    points, _ = scan_world(world, 1.3, -0.7, 0.5, np.random.default_rng(1))
    query = describe_points(points, PARAMS)
    index = MatchedFilterIndex(synthetic_map, SearchParams(
        prefilter_top_k=1, prefilter_rescore_k=rescore_k, prefilter_retry_top_k=0,
        prefilter_expand_m=0.0))
    # The prefilter puts the true place (reference 0) fourth; one candidate goes on.
    asked = _ranking_prefilter(index, [3, 4, 1, 0, 2])
    result = index.query(query)
    if rescore_k:
        assert asked == [5]
        assert list(result.searched) == [0]
        assert result.reference_index == 0
        assert np.hypot(*(result.pose[:2] - (1.3, -0.7))) < 0.15
    else:
        assert asked == [1]
        assert list(result.searched) == [3]
    assert list(index.candidates(query, 1)) == list(result.searched)


def test_n_active_restricts_the_search(world, synthetic_map):
    points, _ = scan_world(world, 20, 20, 0.3, np.random.default_rng(4))
    index = MatchedFilterIndex(synthetic_map, SearchParams())
    assert index.query(describe_points(points, PARAMS)).reference_index == 4
    assert index.query(describe_points(points, PARAMS), n_active=4).reference_index != 4
    assert MatchedFilterIndex(ReferenceMap(PARAMS), SearchParams()).query(
        describe_points(points, PARAMS)) is None


def test_index_follows_a_growing_map(world):
    reference_map = ReferenceMap(PARAMS)
    index = MatchedFilterIndex(reference_map, SearchParams())
    rng = np.random.default_rng(5)
    for i, x in enumerate((0.0, 30.0)):
        points, pose = scan_world(world, x, 0, 0, rng)
        reference_map.append(describe_points(points, PARAMS, reference=True, seed_key=i), pose, i)
    assert index.sync() == 2 and len(index) == 2
    points, _ = scan_world(world, 29, 1, 0.1, rng)
    assert index.query(describe_points(points, PARAMS)).reference_index == 1


def test_real_kitti07_relative_poses(data_dir):
    from mf_lpr_ros.datasets import open_source

    config = preset("kitti")
    scans = list(open_source(data_dir / "kitti07_keyframes").iter_scans())
    for before, after in zip(scans, scans[1:]):
        reference_map = ReferenceMap(config.descriptor)
        reference_map.append(describe_scan(before, config.descriptor, reference=True), before.pose,
                             before.stamp)
        result = MatchedFilterIndex(reference_map, SearchParams(max_shift_m=14)).query(
            describe_scan(after, config.descriptor, reference=False))
        truth = planar(after.pose)
        # Keyframes 3.3 to 11.9 m apart: the relative pose comes back to decimetres.
        assert np.hypot(*(result.pose[:2] - truth[:2])) < 0.3
        assert yaw_error_deg(result.pose[2], truth[2]) < 1.0


def test_real_kitti_bev_rotated_copies(data_dir):
    """00_rot holds each 00 image rotated about the sensor by an unknown angle."""
    from mf_lpr_ros.datasets import open_source

    config = preset("kitti")
    frames = [0, 700, 1500, 2600, 3900]
    upright = {s.index: s for s in open_source(data_dir / "kitti_bev/00").iter_scans(frames)}
    rotated = {s.index: s for s in open_source(data_dir / "kitti_bev/00_rot").iter_scans(frames)}
    for frame in frames:
        reference_map = ReferenceMap(config.descriptor)
        reference_map.append(describe_scan(upright[frame], config.descriptor, reference=True),
                             upright[frame].pose, 0.0)
        result = MatchedFilterIndex(reference_map, config.search).query(
            describe_scan(rotated[frame], config.descriptor, reference=False))
        # Rotation about the sensor does not move it. BEVPlace images put the sensor at a pixel
        # centre, ours at a cell corner: up to ~0.57 m of offset at 180 degrees.
        assert np.linalg.norm(result.shift_m) < 0.6
        assert result.confidence > 0.4
        # Undoing the found rotation must bring the rotated copy back onto the upright one.
        query = describe_scan(rotated[frame], config.descriptor, reference=False)
        original = describe_scan(upright[frame], config.descriptor, reference=False)
        found = np.degrees(result.rotation_rad)
        back, wrong = rotate_occupancy(query, np.array([found, found + 20.0]))
        overlap = (back & original).sum() / original.sum()
        assert overlap > 0.35 and overlap > 2 * (wrong & original).sum() / original.sum()


def _street(clouds: bool = False) -> tuple[ReferenceMap, np.ndarray]:
    """References every 2 m along a street of the synthetic world (x positions), with their
    clouds when asked."""
    world = make_world(7)
    street = ReferenceMap(PARAMS)
    xs = np.arange(-20.0, 21.0, 2.0)
    for i, x in enumerate(xs):
        points, pose = scan_world(world, x, 0.0, 0.0, np.random.default_rng(i))
        street.append(describe_points(points, PARAMS, reference=True, seed_key=i), pose,
                      float(i), i, cloud=points if clouds else None)
    return street, xs


def _queries_along_the_street():
    """(x, points, world_T_sensor) of 25 queries between the street's references, 1.5 m to its
    side and turned 0.7 rad."""
    world = make_world(7)
    for k, x in enumerate(np.linspace(-18.3, 18.7, 25)):
        points, pose = scan_world(world, x, 1.5, 0.7, np.random.default_rng(k))
        yield x, points, pose


def test_nearest_place_reranking_reports_the_nearest_reference():
    # A query between two references often scores best against one a few metres off that sees
    # more of its scene. Re-ranking reports the nearest.
    street, xs = _street()

    def not_nearest(margin):
        index = MatchedFilterIndex(street, SearchParams(rerank_margin=margin))
        misses = 0
        for x, points, pose in _queries_along_the_street():
            match = index.query(describe_points(points, PARAMS))
            misses += abs(xs[match.reference_index] - x) > 1.01
            assert np.hypot(*(match.pose[:2] - pose[:2, 3])) < 0.3
        return misses

    assert not_nearest(0.1) == 0
    assert not_nearest(0.0) >= 3


def test_a_nearer_view_that_turns_the_query_does_not_confirm_the_match():
    # A map that drifted between visits, as a SLAM map does before its loop closes: the
    # nearer views that re-ranking reports on the street, each given a heading 20 degrees off
    # its view's. Such a reference's own alignment still puts the query within a metre of where
    # the match does (its shift of under 2 m turns with it), but facing 20 degrees away: not
    # the same answer, so not reported as the match's nearer view (the constraint
    # re-expressed in its frame would carry the drift). One may still win on its own score.
    street, _ = _street()
    search = SearchParams(rerank_margin=0.9)
    index = MatchedFilterIndex(street, search)
    queries = [describe_points(points, PARAMS) for _, points, _ in _queries_along_the_street()]
    nearer = {}
    for query_number, query in enumerate(queries):
        match = index.query(query)
        if match.scored_reference not in (None, match.reference_index):
            nearer[query_number] = (match.scored_reference, match.reference_index)
    assert len(nearer) >= 3
    turned = {reported for _, reported in nearer.values()}
    drifted = MatchedFilterIndex(turned_view_map(street, [
        (view, np.radians(20.0) if view in turned else 0.0, 0.0)
        for view in range(len(street))]), search)
    for query_number in nearer:
        match = drifted.query(queries[query_number])
        assert match.scored_reference is None or match.reference_index not in turned


def _heading_errors(count: int) -> np.ndarray:
    """Headings off by 30-170 degrees each: a map whose yaws are not its views' (BEVPlace's
    rotated copies, references tagged with a position alone)."""
    return np.random.default_rng(3).uniform(np.radians(30), np.radians(170), count)


# Headings unknown and left so: the re-ranking by distances between alignments.
_UNESTIMATED = {"map_headings": "unknown", "estimate_map_headings": False}


def test_a_map_of_unknown_headings_estimates_them_from_its_neighbours():
    # The street's views turned by 30-170 degrees against their poses' yaws. Each reference,
    # aligned on its map neighbours, gives its view's heading: the direction between their
    # positions against the direction of the alignment's shift. With those the map searches
    # as one of known headings: a query's pose lies in the map frame, and the reference
    # nearest it is reported. Left unknown, the poses carry the turns.
    street, xs = _street()
    wrong = turned_view_map(street, [(view, turn, 0.0) for view, turn in
                                     enumerate(_heading_errors(len(street)))])
    index = MatchedFilterIndex(wrong, SearchParams(map_headings="unknown"))
    errors = np.degrees(np.abs(wrap_angle(index.estimated_headings
                                          - planar(street.poses)[:, 2])))
    assert errors.max() < 2.0
    unestimated = MatchedFilterIndex(wrong, SearchParams(**_UNESTIMATED))
    assert unestimated.estimated_headings is None
    misplaced = 0
    for x, points, pose in _queries_along_the_street():
        query = describe_points(points, PARAMS)
        match = index.query(query)
        assert abs(xs[match.reference_index] - x) <= 1.01
        assert np.hypot(*(match.pose[:2] - pose[:2, 3])) < 0.3
        misplaced += np.hypot(*(unestimated.query(query).pose[:2] - pose[:2, 3])) > 1.0
    assert misplaced >= 20


def test_a_growing_map_of_unknown_headings_estimates_its_new_references_at_the_next_query():
    street, _ = _street()
    views = list(enumerate(_heading_errors(len(street))))
    whole = turned_view_map(street, [(view, turn, 0.0) for view, turn in views])
    growing = turned_view_map(street, [(view, turn, 0.0) for view, turn in views[:10]])
    index = MatchedFilterIndex(growing, SearchParams(map_headings="unknown"))
    assert len(index.estimated_headings) == 10
    for view in range(10, len(street)):
        growing.append(whole.occupancy(view), whole.poses[view], float(view), view)
    index.sync()
    errors = np.degrees(np.abs(wrap_angle(index.estimated_headings
                                          - planar(street.poses)[:, 2])))
    assert len(errors) == len(street) and errors.max() < 2.0


def test_headings_stay_unknown_where_a_reference_has_no_neighbour_in_reach():
    # One view every 8 m: no neighbour lies within three quarters of max_shift_m (6 m), so no
    # alignment can tell a heading, and the map searches as one of unknown headings.
    street, xs = _street()
    sparse = turned_view_map(street, [(view, turn, 0.0) for view, turn in zip(
        range(0, len(street), 4), _heading_errors(len(street)))])
    index = MatchedFilterIndex(sparse, SearchParams(map_headings="unknown"))
    assert index.estimated_headings is None
    unestimated = MatchedFilterIndex(sparse, SearchParams(**_UNESTIMATED))
    for x, points, _ in _queries_along_the_street():
        query = describe_points(points, PARAMS)
        first, second = index.query(query), unestimated.query(query)
        assert first.reference_index == second.reference_index
        np.testing.assert_allclose(first.pose, second.pose)


def test_query_poses_from_a_batch_of_alignments_are_each_alignments_pose():
    rng = np.random.default_rng(4)
    references = np.c_[rng.uniform(-30, 30, (6, 2)), rng.uniform(-np.pi, np.pi, 6)]
    shifts, rotations = rng.uniform(-8, 8, (6, 2)), rng.uniform(-np.pi, np.pi, 6)
    batch = query_pose_from_alignment(references, shifts, rotations)
    assert batch.shape == (6, 3)
    for row, reference, shift, rotation in zip(batch, references, shifts, rotations):
        single = query_pose_from_alignment(reference, shift, rotation)
        assert single.shape == (3,)
        np.testing.assert_allclose(row, single)
        # The alignment the pose came from is recovered from it.
        recovered_shift, recovered_rotation = alignment_from_poses(reference, single)
        np.testing.assert_allclose(recovered_shift, shift, atol=1e-9)
        assert abs(wrap_angle(recovered_rotation - rotation)) < 1e-9


def test_two_alignments_of_one_query_give_the_distance_between_their_references():
    # Any headings: the distance needs none of them, only the query's pose in each frame.
    rng = np.random.default_rng(5)
    for _ in range(20):
        first, second, query = (np.append(rng.uniform(-30, 30, 2), rng.uniform(-np.pi, np.pi))
                                for _ in range(3))
        on_first, on_second = (np.append(*alignment_from_poses(reference, query))
                               for reference in (first, second))
        assert reference_distance(on_first, on_second) == pytest.approx(
            np.hypot(*(first[:2] - second[:2])))
        assert reference_distance(on_second, on_first) == pytest.approx(
            np.hypot(*(first[:2] - second[:2])))


def test_a_map_of_unknown_headings_reports_a_nearer_view_by_distances():
    # Where the map's yaws are not its views', a position in the map frame cannot be had, but
    # the alignments' distances can: told so (map_headings "unknown"), the re-ranking reports a
    # finalist the query is nearer to when the two alignments put the two references as far
    # apart as the map does. Never a view farther than the best-scoring one.
    street, xs = _street()
    wrong = turned_view_map(street, [(view, turn, 0.0) for view, turn in
                                     enumerate(_heading_errors(len(street)))])
    off = MatchedFilterIndex(wrong, SearchParams(**_UNESTIMATED, rerank_margin=0.0))
    unknown = MatchedFilterIndex(wrong, SearchParams(**_UNESTIMATED))
    nearer = 0
    for x, points, _ in _queries_along_the_street():
        query = describe_points(points, PARAMS)
        best, reported = off.query(query), unknown.query(query)
        gap_best, gap_reported = (abs(xs[match.reference_index] - x) for match in (best, reported))
        assert gap_reported <= gap_best
        nearer += gap_reported < gap_best
        assert reported.scored_reference in (None, best.reference_index)
    assert nearer >= 2


def test_a_nearer_view_of_a_look_alike_place_is_not_reported_when_headings_are_unknown():
    # The same street again 500 m off: its views tie with the street's own, and a copy of the
    # query's nearer view aligns nearer than the best one. Only the distances between the
    # references tell the two streets apart; the report stays on the best one's street.
    street, xs = _street()
    n_views = len(street)
    turns = _heading_errors(2 * n_views)
    doubled = turned_view_map(street, [(k % n_views, turn, 0.0 if k < n_views else 500.0)
                                       for k, turn in enumerate(turns)])
    off = MatchedFilterIndex(doubled, SearchParams(**_UNESTIMATED, rerank_margin=0.0, top_n=4))
    unknown = MatchedFilterIndex(doubled, SearchParams(**_UNESTIMATED, top_n=4))
    across = 0
    for _, points, _ in _queries_along_the_street():
        query = describe_points(points, PARAMS)
        best, reported = off.query(query), unknown.query(query)
        assert (best.reference_index < n_views) == (reported.reference_index < n_views)
        finalists = {h.reference_index for h in best.hypotheses}
        across += len({r < n_views for r in finalists}) == 2
    # The look-alike is among the finalists: the test could fail.
    assert across >= 10


def test_a_reported_nearer_reference_keeps_the_best_alignments_evidence():
    # The nearer reference only confirms the match: the pose, score and confidence stay the
    # best alignment's, and the constraint to the reported reference leads to that same pose.
    street, _ = _street()
    moved = 0
    for _, best, reported in _best_and_reported(street):
        assert reported.score == best.score and reported.confidence == best.confidence
        np.testing.assert_allclose(reported.pose, best.pose)
        np.testing.assert_allclose(reported.covariance, best.covariance)
        assert _constraint_leads_to(street, reported, best.pose, 1e-9)
        assert reported.candidates[0] == reported.reference_index
        listed = [h.reference_index for h in reported.hypotheses]
        assert listed[0] == reported.reference_index and len(set(listed)) == len(listed)
        np.testing.assert_allclose(reported.hypotheses[0].pose, best.pose)
        if reported.reference_index != best.reference_index:
            assert best.reference_index not in listed
            moved += 1
    assert moved >= 3


def test_icp_verifies_the_scored_alignment_when_a_nearer_reference_is_reported():
    # Verification tests the evidence: ICP runs against the cloud of the reference the match
    # was scored on, and the refined pose is re-expressed against the reported one.
    street, _ = _street(clouds=True)
    checked = 0
    for points, best, reported in _best_and_reported(street):
        if reported.reference_index == best.reference_index:
            continue
        assert reported.scored_reference == best.reference_index
        on_best, on_reported = refine_match(best, points, street), refine_match(reported, points,
                                                                                street)
        assert on_reported.fitness == pytest.approx(on_best.fitness, abs=1e-6)
        np.testing.assert_allclose(reported.pose[:2], best.pose[:2], atol=1e-6)
        assert _constraint_leads_to(street, reported, best.pose, 1e-6)
        checked += 1
    assert checked >= 3


def _best_and_reported(street):
    """(query points, match without re-ranking, match with it) of the street's queries."""
    plain = MatchedFilterIndex(street, SearchParams(rerank_margin=0.0))
    reranked = MatchedFilterIndex(street, SearchParams(rerank_margin=0.5))
    for _, points, _ in _queries_along_the_street():
        query = describe_points(points, PARAMS)
        yield points, plain.query(query), reranked.query(query)


def _constraint_leads_to(reference_map, match, pose, tolerance):
    """Whether the match's reference pose composed with its alignment gives pose."""
    position_gap, yaw_gap_deg = planar_error(query_pose_from_alignment(
        planar(reference_map.poses[match.reference_index]), match.shift_m, match.rotation_rad),
        pose)
    return position_gap < tolerance and yaw_gap_deg < tolerance


def _pixel_centred_image(points, pixel=0.4, size=151):
    """Occupied points per pixel, the sensor at the centre of pixel (size // 2, size // 2), as
    BEVPlace draws its KITTI images."""
    points = points[points[:, 2] > -1.2]
    cols = np.floor(points[:, 0] / pixel + 0.5).astype(int) + size // 2
    rows = np.floor(points[:, 1] / pixel + 0.5).astype(int) + size // 2
    inside = (cols >= 0) & (cols < size) & (rows >= 0) & (rows < size)
    image = np.zeros((size, size), np.float32)
    np.add.at(image, (rows[inside], cols[inside]), 1.0)
    return np.minimum(image, 10.0)


@pytest.mark.parametrize("offset_m,worst_m", [(0.2, 0.1), (0.0, None)])
def test_pixel_centred_sensor_offset_is_corrected(offset_m, worst_m):
    # Revisits from the opposite direction: half a pixel of sensor offset turns into ~0.5 m of
    # pose error unless the search accounts for it.
    world = make_world(7)
    points, pose = scan_world(world, 3.0, -2.0, 0.3, np.random.default_rng(1))
    reference_map = ReferenceMap(PARAMS, metadata={"sensor_offset_m": offset_m})
    reference_map.append(describe_density_image(_pixel_centred_image(points), 0.4, PARAMS,
                                                reference=True), pose, 0.0, 0)
    index = MatchedFilterIndex(reference_map, SearchParams())
    errors = []
    for dx, dy, dyaw in [(1.0, 0.6, np.pi + 0.17), (-0.8, 1.2, np.pi - 0.4), (0.5, -1.0, 2.0)]:
        points, truth = scan_world(world, 3.0 + dx, -2.0 + dy, 0.3 + dyaw,
                                   np.random.default_rng(2))
        match = index.query(describe_density_image(_pixel_centred_image(points), 0.4, PARAMS),
                            sensor_offset_m=offset_m)
        errors.append(np.hypot(*(match.pose[:2] - truth[:2, 3])))
    if worst_m is not None:
        assert max(errors) < worst_m
    else:
        assert min(errors) > 0.3


def _wedge(points, half_width_deg=35.0):
    """What a forward-looking sensor (a Livox Avia's ~70 degrees) returns of a scan."""
    azimuth = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
    return points[np.abs(azimuth) <= half_width_deg]


def test_observed_cells_are_the_directions_a_narrow_scan_saw(world):
    from mf_lpr_ros.core.descriptor import observed_cells

    points, _ = scan_world(world, 3.0, -2.0, 0.4, np.random.default_rng(3))
    full = describe_points(points, PARAMS)
    assert observed_cells(full).all()                     # all round: every cell counts
    grid = MatchedFilterIndex(_rendered_map(world), SearchParams(query_footprint="observed"))
    window = MatchedFilterIndex(_rendered_map(world), SearchParams(query_footprint="window"))
    assert grid.query(full).confidence == window.query(full).confidence
    narrow = observed_cells(describe_points(_wedge(points), PARAMS))
    centre = PARAMS.size // 2
    ahead, behind = narrow[centre, centre + 5:], narrow[centre, :centre - 5]
    assert ahead.all() and not behind.any()
    assert 0.1 < narrow.mean() < 0.4                       # ~70 degrees of 360, and a margin


def _rendered_map(world):
    """References as a global-map grid holds them: complete 360-degree views, marked as a grid."""
    reference_map = ReferenceMap(PARAMS, metadata={"kind": "global_map_grid"})
    rng = np.random.default_rng(4)
    for i, (x, y) in enumerate([(0, 0), (6, 0), (0, 6), (-6, 0), (0, -6), (6, 6)]):
        points, pose = scan_world(world, x, y, 0.0, rng, dropout=0.0)
        reference_map.append(describe_points(points, PARAMS, reference=True, seed_key=i), pose,
                             float(i), i)
    return reference_map


@pytest.mark.parametrize("query_footprint, observed", [("auto", True), ("observed", True),
                                                       ("window", False)])
def test_a_grid_map_matches_queries_by_what_they_observed(world, query_footprint, observed):
    reference_map = _rendered_map(world)
    index = MatchedFilterIndex(reference_map, SearchParams(query_footprint=query_footprint))
    assert index.observed_queries is observed
    points, _ = scan_world(world, 5.6, 0.3, 0.2, np.random.default_rng(5))
    result = index.query(describe_points(_wedge(points), PARAMS))
    if observed:
        # The wedge's unseen cells no longer count as free space against the complete view.
        window = MatchedFilterIndex(reference_map, SearchParams(query_footprint="window")).query(
            describe_points(_wedge(points), PARAMS))
        assert result.confidence > window.confidence + 0.05
        assert result.reference_index == 1
        assert np.hypot(result.pose[0] - 5.6, result.pose[1] - 0.3) < 0.5


def test_maps_of_scans_keep_the_window_by_default(synthetic_map):
    assert not MatchedFilterIndex(synthetic_map, SearchParams()).observed_queries
    assert MatchedFilterIndex(synthetic_map,
                              SearchParams(query_footprint="observed")).observed_queries



@pytest.mark.parametrize("candidates", [
    {},
    # The candidate stage keeps the two best-ranked alone: the neighbours are not searched.
    {"prefilter_top_k": 2, "prefilter_expand_m": 0.0},
], ids=["searched", "left_out"])
def test_a_map_of_unknown_headings_reports_the_nearest_view_among_the_matchs_neighbours(
        candidates):
    # The finalists are often neighbours of each other a few metres past the query; the
    # nearest view is then a map neighbour of the match that no finalist is. Where the map's
    # yaws are not its views', the match's neighbours within twice the query's distance are
    # aligned too (the one the global stage puts nearest, and the two nearest left out of the
    # candidates), and the nearest of them whose alignment agrees with the map's distances
    # is reported.
    street, xs = _street()
    wrong = turned_view_map(street, [(view, turn, 0.0) for view, turn in
                                     enumerate(_heading_errors(len(street)))])
    off = MatchedFilterIndex(wrong, SearchParams(**_UNESTIMATED, rerank_margin=0.0,
                                                 **candidates))
    unknown = MatchedFilterIndex(wrong, SearchParams(**_UNESTIMATED, **candidates))
    nearest = beside_finalists = 0
    for x, points, _ in _queries_along_the_street():
        query = describe_points(points, PARAMS)
        best, reported = off.query(query), unknown.query(query)
        gap_best, gap_reported = (abs(xs[match.reference_index] - x) for match in (best, reported))
        assert gap_reported <= gap_best
        nearest += gap_reported <= 1.01
        beside_finalists += reported.reference_index not in best.candidates[:2]
    assert nearest >= 23 and beside_finalists >= 3


def test_the_query_at_each_heading_is_made_once_and_is_the_query_turned_to_it(world):
    rng = np.random.default_rng(5)
    reference_map = ReferenceMap(PARAMS)
    for i, (x, y) in enumerate([(0, 0), (25, 0), (0, 25)]):
        points, pose = scan_world(world, x, y, 0.8 * i, rng)
        reference_map.append(describe_points(points, PARAMS, reference=True, seed_key=i),
                             pose, float(i), i)
    index = MatchedFilterIndex(reference_map, SearchParams())
    query = describe_points(scan_world(world, 3.0, -1.0, 0.7, rng)[0], PARAMS)
    angles = index.global_angles
    expected = pooled_weights(rotate_occupancy(query, angles), PARAMS.unoccupied_weight,
                              PARAMS.pool, index._query_covered(angles, None, None))
    index.query(query)
    index._pooled_made[:] = False
    made = []
    turn_and_pool = index._turn_and_pool
    index._turn_and_pool = lambda occupancy, headings: (made.append(headings.tolist())
                                                        or turn_and_pool(occupancy, headings))
    # A few headings turned one by one, then more than half of them at once (the roots turned,
    # the rest laid out by quarter turns): each the query turned to its heading, made once.
    few = np.array([40, 0, 5])
    np.testing.assert_array_equal(index._turned_and_pooled(query, few), expected[few])
    np.testing.assert_array_equal(index._turned_and_pooled(query, few[:2]), expected[few[:2]])
    assert made == [[40, 0, 5]]
    every = np.arange(len(angles))
    np.testing.assert_array_equal(index._turned_and_pooled(query, every[::-1]),
                                  expected[::-1])
    assert made[1] == every.tolist()
    assert len(index._root_headings) < len(angles) / 3
    # The next query starts afresh.
    other = describe_points(scan_world(world, 20.0, 2.0, -1.1, rng)[0], PARAMS)
    index.query(other)
    made_for_other = index._pooled_made.copy()
    assert made_for_other.any()
    np.testing.assert_array_equal(
        index._pooled_turns[made_for_other],
        pooled_weights(rotate_occupancy(other, angles), PARAMS.unoccupied_weight, PARAMS.pool,
                       index._query_covered(angles, None, None))[made_for_other])


def test_a_map_searched_whole_is_correlated_once_and_its_finalists_located_in_it(world):
    rng = np.random.default_rng(6)
    reference_map = ReferenceMap(PARAMS)
    for i, (x, y) in enumerate([(0, 0), (25, 0), (0, 25), (25, 25)]):
        points, pose = scan_world(world, x, y, 0.5 * i, rng)
        reference_map.append(describe_points(points, PARAMS, reference=True, seed_key=i),
                             pose, float(i), i)
    query = describe_points(scan_world(world, 24.0, 1.0, 0.6, rng)[0], PARAMS)
    index = MatchedFilterIndex(reference_map, SearchParams())
    correlated = []
    correlate = index.bank._correlate
    index.bank._correlate = lambda rows, columns: (correlated.append(columns.shape[-1])
                                                   or correlate(rows, columns))
    match = index.query(query)
    # Under prefilter_top_k the whole map is every reference's candidate, correlated in one
    # chunk; its finalists are located in those scores, not correlated a second time.
    assert correlated == [4]
    assert match.reference_index == 1
    exact = MatchedFilterIndex(reference_map, SearchParams(chunk_size=2))
    exact_match = exact.query(query)
    assert exact_match.reference_index == match.reference_index
    np.testing.assert_allclose(exact_match.pose, match.pose, atol=1e-4)


@pytest.mark.parametrize("descriptor,search", [
    (PARAMS, SearchParams(prefilter_top_k=4)),
    (DescriptorParams(voxel_size=0.4, z_min=-1.2, crop="disc"), SearchParams(prefilter_top_k=4)),
    (PARAMS, SearchParams(prefilter_top_k=4, query_footprint="observed")),
    (PARAMS, SearchParams(prefilter_top_k=0)),
    (DescriptorParams(voxel_size=0.4, z_min=-1.2, field_of_view_deg=120.0),
     SearchParams(prefilter_top_k=4)),
])
def test_headings_laid_out_by_quarter_turns_give_the_matches_of_headings_turned_one_by_one(
        world, monkeypatch, descriptor, search):
    # Views of scattered places at headings 0.8 rad apart, queried at others: the candidates'
    # headings and their opposites fall on every quarter of the circle.
    rng = np.random.default_rng(4)
    reference_map = ReferenceMap(descriptor)
    places = [(0, 0), (25, 0), (0, 25), (-25, -10), (20, 20), (-15, 18), (10, -22), (-20, 5)]
    for i, (x, y) in enumerate(places):
        points, pose = scan_world(world, x, y, 0.8 * i, rng)
        reference_map.append(describe_points(points, descriptor, reference=True, seed_key=i),
                             pose, float(i), i)
    queries = [describe_points(scan_world(world, x + 1.1, y - 0.6, yaw, rng)[0], descriptor)
               for (x, y), yaw in zip(places, [2.9, -1.3, 0.4, 1.9, -2.6, 3.1, -0.2, 1.2])]
    laid_out = MatchedFilterIndex(reference_map, search)
    turns_used = set()
    prepare = laid_out.bank.prepare_queries

    def recording(images, pairs=False, turned_from=None):
        if turned_from is not None:
            turns_used.update(turned_from[turned_from[:, 0] >= 0, 1].tolist())
        return prepare(images, pairs=pairs, turned_from=turned_from)

    monkeypatch.setattr(laid_out.bank, "prepare_queries", recording)
    monkeypatch.setattr(MatchedFilterIndex, "_footprint_keeps_quarter_turns", lambda self: False)
    one_by_one = MatchedFilterIndex(reference_map, search)
    assert len(one_by_one._root_headings) == len(one_by_one.global_angles)
    symmetric = descriptor.field_of_view_deg >= 360
    assert (len(laid_out._root_headings) < len(laid_out.global_angles) / 3) == symmetric
    for query in queries:
        expected, got = one_by_one.query(query), laid_out.query(query)
        assert got.reference_index == expected.reference_index
        np.testing.assert_allclose(got.pose, expected.pose, atol=1e-6)
        assert got.confidence == pytest.approx(expected.confidence, abs=1e-6)
        assert got.distinctiveness == pytest.approx(expected.distinctiveness, abs=1e-5)
    # The global stage's spectra were laid out from a quarter, a half and three quarters of a
    # turn, where the candidate stage chose headings (an exhaustive search builds no pairs).
    assert turns_used == ({1, 2, 3} if symmetric and search.prefilter_top_k else set())


def test_a_turn_snaps_to_the_nearest_heading_the_sensor_is_searched_at(world):
    """The revisit check and the nearer view align a reference at the global heading nearest a
    turn; a sensor with a limited field of view is searched at the turns within it only, so
    the nearest is one of those, not the heading at the same place in the full circle."""
    narrow = DescriptorParams(voxel_size=0.4, z_min=-1.2, field_of_view_deg=90.0)
    for params, turns in ((PARAMS, [(-10.0, 350.0), (12.0, 10.0), (177.4, 175.0)]),
                          (narrow, [(-10.0, 350.0), (349.0, 350.0), (12.0, 10.0),
                                    (-87.0, 275.0), (170.0, 85.0), (200.0, 275.0)])):
        index = MatchedFilterIndex(five_places(world, params), SearchParams())
        for turn, expected in turns:
            snapped = index._snapped_global_angle(turn)
            assert snapped == pytest.approx(expected), (params.field_of_view_deg, turn)
            assert snapped in index.global_angles


def test_a_narrow_sensors_revisit_check_aligns_at_the_turn_the_revisit_implies(world):
    """The revisit's turn is the difference of two yaws, here either side of +-180 degrees
    (-344 degrees, a turn of 16): the place's reference is aligned from the heading nearest
    it among those a 120-degree field of view is searched at, and reported."""
    narrow = DescriptorParams(voxel_size=0.4, z_min=-1.2, field_of_view_deg=120.0)
    index = MatchedFilterIndex(five_places(world, narrow, first_yaw=3.0), SearchParams(
        prefilter_top_k=1, prefilter_rescore_k=0, prefilter_retry_top_k=0,
        prefilter_expand_m=0.0))
    assert 345.0 in index.global_angles and 180.0 not in index.global_angles
    # The candidate stage hands on a wrong place alone (reference 3): a weak match.
    _ranking_prefilter(index, [3, 4, 1, 0, 2])
    points, _ = scan_world(world, 1.3, -0.7, -3.0, np.random.default_rng(1))
    result = index.query(describe_points(points, narrow),
                         revisit_places=lambda match: np.array([[1.3, -0.7, -3.0]]))
    assert result.reference_index == 0 and result.revisit_predicted
    assert np.hypot(*(result.pose[:2] - (1.3, -0.7))) < 0.3
    assert yaw_error_deg(result.pose[2], -3.0) < 1.0
