"""The evaluation protocol's selection and the metrics, on small hand-made sequences/records."""

import importlib.util
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from mf_lpr_ros.config import preset
from mf_lpr_ros.core.pose import euler_pose
from mf_lpr_ros.datasets import Scan, Sequence
from mf_lpr_ros.evaluation import protocol as protocol_module
from mf_lpr_ros.evaluation.benchmarks import SUITES
from mf_lpr_ros.evaluation.methods import Retrieval
from mf_lpr_ros.evaluation.metrics import POSE_FIGURES, QueryRecord, summarise
from mf_lpr_ros.evaluation.protocol import (
    Protocol,
    ProtocolRun,
    evaluate_pair,
    run_protocol,
    select,
    thinned_scan,
)


class Line(Sequence):
    """Scans every step_m metres along x, one per second; optional NaN poses."""

    def __init__(self, n, step_m=1.0, invalid=()):
        self.name = "line"
        self.stamps = np.arange(n, dtype=float)
        self.poses = np.tile(np.eye(4), (n, 1, 1))
        self.poses[:, 0, 3] = np.arange(n) * step_m
        self.poses[list(invalid)] = np.nan


def test_reference_and_query_spacing_along_the_path():
    selection = select(Line(31, invalid=[4]), Protocol(3.0, reference_spacing_m=2.0,
                                                       query_spacing_m=10.0),
                       spacing_m=99.0, query=Line(31, step_m=0.5))
    # References every 2 m skipping the invalid scan; queries every 10 m of the query path.
    assert selection.references.tolist() == [0, 2, 5, 7] + list(range(9, 31, 2))
    assert selection.queries.tolist() == [0, 20]
    assert selection.n_active.tolist() == [len(selection.references)] * 2


def test_loop_closure_exclusion_by_frames_and_seconds():
    line = Line(20)
    frames = select(line, Protocol(3.0, exclude_recent_frames=5), spacing_m=1.0)
    # A query sees references more than 5 frames older; the first 6 scans have none.
    assert frames.queries[0] == 6 and frames.n_active[0] == 1
    assert (frames.n_active == frames.queries - 5).all()
    seconds = select(line, Protocol(3.0, exclude_recent_s=7.5), spacing_m=1.0)
    assert seconds.queries[0] == 8 and (seconds.n_active == seconds.queries - 7).all()
    own = select(line, Protocol(3.0), spacing_m=1.0)
    assert (own.n_active == own.queries).all()          # never itself


def test_frame_ranges_split_one_sequence_into_database_and_queries():
    # BEVPlace's way: database frames 0-9 (every one a reference), queries 15-24.
    protocol = Protocol(5.0, reference_spacing_m=0.0, reference_frames=(0, 9),
                        query_frames=(15, 24))
    selection = select(Line(30), protocol, spacing_m=2.0)
    assert selection.references.tolist() == list(range(10))
    assert selection.queries.tolist() == list(range(15, 25))
    assert (selection.n_active == 10).all()
    with pytest.raises(ValueError, match="query_frames"):
        Protocol(5.0, query_frames=(9, 3))


def test_query_split_restricts_queries_by_stamp():
    selection = select(Line(10), Protocol(3.0), spacing_m=1.0, query=Line(10),
                       query_stamps=np.array([3.00001, 7.0, 42.0]))
    assert selection.queries.tolist() == [3, 7]


def _record(nearest, retrieved, rte, rre, confidence, candidates, published=False):
    return QueryRecord(query_index=0, stamp=0.0, truth=[0.0, 0.0, 0.0], estimate=[0.0, 0.0, 0.0],
                       reference_index=0, nearest_reference_m=nearest,
                       retrieved_distance_m=retrieved, candidate_distances_m=candidates,
                       rte_m=rte, rre_deg=rre, confidence=confidence, published=published,
                       ms_descriptor=1.0, ms_global=2.0, ms_local=3.0)


def test_published_closure_metrics_count_what_a_back_end_would_receive():
    records = [
        _record(1.0, 1.0, 0.5, 1.0, 0.9, [1.0], published=True),    # correct closure
        _record(1.0, 9.0, 2.5, 3.0, 0.8, [9.0], published=True),    # far reference, right pose
        _record(8.0, 8.0, 8.0, 9.0, 0.85, [8.0], published=True),   # false: pose 8 m off
        _record(1.0, 1.0, 0.4, 1.0, 0.95, [1.0]),                   # correct, not published
        _record(1.0, 1.0, 6.0, 1.0, 0.7, [1.0]),                    # wrong pose, not published
    ]
    summary = summarise(records, tolerance_m=3.0, n_references=4)
    assert summary["closures_published"] == 3
    assert summary["closures_false"] == 1
    assert summary["precision_published"] == pytest.approx(2 / 3)
    assert summary["recall_published"] == pytest.approx(2 / 4)      # 4 revisit queries
    # By confidence: 0.95 T, 0.9 T, 0.85 F -> two of four before the first false match.
    assert summary["recall_at_100_precision"] == pytest.approx(2 / 4)
    nothing = summarise([_record(1.0, 1.0, 0.5, 1.0, 0.9, [1.0])], 3.0, 1)
    assert nothing["closures_published"] == 0 and np.isnan(nothing["precision_published"])


def test_published_covariances_are_judged_by_the_errors_they_claim():
    """d2 of each published closure: its position error under its published (x, y)
    covariance. An error along the wide axis counts less than the same error across it;
    closures not published, and records without a covariance, are left out."""
    def record(error, covariance, published=True):
        closure = _record(1.0, 1.0, float(np.hypot(*error)), 1.0, 0.9, [1.0], published)
        closure.estimate = [*error, 0.0]
        closure.position_covariance = covariance
        return closure

    records = [record([2.0, 0.0], [4.0, 0.0, 1.0]),            # 1 sigma along x: d2 1
               record([0.0, 2.0], [4.0, 0.0, 1.0]),            # 2 sigma along y: d2 4
               record([1.0, 1.0], [2.0, 1.0, 2.0]),            # along the correlation: 2/3
               record([5.0, 5.0], [0.01, 0.0, 0.01], False),   # not published
               record([1.0, 0.0], [np.nan] * 3)]               # no covariance
    summary = summarise(records, tolerance_m=3.0, n_references=4)
    assert summary["published_d2_median"] == pytest.approx(1.0)
    assert summary["published_d2_p90"] == pytest.approx(1.0 + 0.8 * 3.0)
    assert np.isnan(summarise(records[3:], 3.0, 4)["published_d2_median"])


def test_where_headings_are_unknown_retrieval_is_scored_and_poses_are_not():
    """Images turned by unknown yaws (BEVPlace's rotated copies): a retrieval still counts,
    but a pose, carrying the reference image's unknown turn, is not scored, nor are the
    closures judged by it."""
    records = [_record(1.0, 1.0, 9.0, 130.0, 0.9, [1.0], published=True),
               _record(1.0, 9.0, 0.5, 1.0, 0.8, [9.0, 1.0])]
    scored = summarise(records, tolerance_m=3.0, n_references=2)
    unscored = summarise(records, tolerance_m=3.0, n_references=2, poses_scored=False)
    assert scored["closures_false"] == 1 and scored["recall_at_1_corrected"] == 0.5
    for figure in POSE_FIGURES:
        assert np.isnan(unscored[figure]), figure
    assert all(np.isnan(unscored["recall_vs_threshold"]["corrected"]))
    for figure in ("recall_at_1", "recall_at_5", "closures_published", "f1_max"):
        assert unscored[figure] == scored[figure], figure
    assert unscored["recall_at_1"] == 0.5 and unscored["closures_published"] == 1


def _search_told(monkeypatch, read) -> list:
    """What evaluate_pair tells the search (read of its SearchParams), one entry a pair, the
    run itself skipped."""
    told = []

    def method_of(name, config):
        told.append(read(config.search))
        return SimpleNamespace(name=name)

    monkeypatch.setattr(protocol_module, "make_method", method_of)
    monkeypatch.setattr(protocol_module, "run_protocol",
                        lambda *args, **kwargs: protocol_module.ProtocolRun([], []))
    return told


def test_where_headings_are_unknown_the_search_is_told_and_poses_are_not_scored(monkeypatch):
    # One fact, known to either side: a protocol's turned copies tell the search
    # (SearchParams.map_headings), and a search told so leaves the poses unscored.
    told = _search_told(monkeypatch, lambda search: search.map_headings)
    monkeypatch.setattr(protocol_module, "summarise",
                        lambda records, tolerance_m, n_references, poses_scored:
                        {"poses_scored": poses_scored})
    kitti = preset("kitti")
    told_unknown = replace(kitti, search=replace(kitti.search, map_headings="unknown"))
    for config, headings_known, expected in ((kitti, True, ("known", True)),
                                             (kitti, False, ("unknown", False)),
                                             (told_unknown, True, ("unknown", False))):
        result = evaluate_pair(Line(10), config, Protocol(3.0, exclude_recent_frames=2,
                                                          headings_known=headings_known))
        assert (told[-1], result.summary["poses_scored"]) == expected


def test_a_protocol_of_requests_searches_each_query_as_a_relocalisation_request(monkeypatch):
    # BEVPlace's protocol asks where each scan is: its [requests] pairs search as `localise`
    # does, a weak match again over the prefilter's wider list; every other pair as a stream
    # (which retries only while on a revisit).
    told = _search_told(monkeypatch, lambda search: search.prefilter_retry)
    for requests, expected in ((False, "revisits"), (True, "every_query")):
        evaluate_pair(Line(10), preset("kitti"), Protocol(3.0, exclude_recent_frames=2,
                                                          requests=requests))
        assert told[-1] == expected
    labelled = {rule.references[0]: rule.label for rule in SUITES["kitti-bevplace"].rules
                if rule.protocol.requests}
    assert labelled == {f"{folder}/{sequence}{suffix}": "requests"
                        for folder, sequences in (("kitti_bev", ("00",)),
                                                  ("holdout/kitti_bev", ("02", "05", "06")))
                        for sequence in sequences for suffix in ("", "_rot")}
    assert not any(rule.protocol.requests for rule in SUITES["tuning"].rules)


def test_only_the_rotated_copies_leave_their_poses_unscored():
    for suite in ("tuning", "kitti-bevplace"):
        for rule in SUITES[suite].rules:
            rotated = any(pattern.endswith("_rot") for pattern in rule.references)
            assert rule.protocol.headings_known is not rotated, rule


def test_summary_metrics_follow_their_definitions():
    records = [
        _record(1.0, 1.0, 0.5, 1.0, 0.9, [1.0, 9.0]),     # retrieved, corrected, success
        _record(1.0, 9.0, 2.5, 3.0, 0.8, [9.0, 2.0]),     # wrong retrieval, corrected, top-2 hit
        _record(1.0, 2.9, 2.5, 1.0, 0.7, [2.9]),          # retrieved, RTE too big for success
        _record(8.0, 8.0, 8.0, 90.0, 0.6, [8.0]),         # no reference in reach: not counted
    ]
    summary = summarise(records, tolerance_m=3.0, n_references=4)
    assert summary["n_queries"] == 3 and summary["n_evaluated"] == 4
    assert summary["recall_at_1"] == pytest.approx(2 / 3)
    assert summary["recall_at_1_corrected"] == pytest.approx(1.0)
    assert summary["recall_at_n"][:2] == pytest.approx([2 / 3, 1.0])
    assert summary["recall_at_5"] == pytest.approx(1.0)
    assert summary["success_rate"] == pytest.approx(1 / 2)
    assert summary["rte_mean_m"] == pytest.approx(0.5)
    # Accepting by confidence: TP, FP, TP, FP -> best F1 at 2 TP of 3 with 3 accepted.
    assert summary["f1_max"] == pytest.approx(2 * (2 / 3) * (2 / 3) / (4 / 3))
    assert summary["confidence_at_f1_max"] == pytest.approx(0.7)
    assert summary["pr_curve"]["precision"] == pytest.approx([1.0, 0.5, 2 / 3, 0.5])
    curve = summary["recall_vs_threshold"]
    assert curve["threshold_m"][-1] == pytest.approx(6.0)
    at_1m = int(np.argmin(np.abs(np.array(curve["threshold_m"]) - 1.0)))
    assert curve["threshold_m"][at_1m] == pytest.approx(1.05)      # 40 steps of 0.15 m
    assert curve["corrected"][at_1m] == pytest.approx(1 / 3)
    assert np.all(np.diff(curve["retrieval"]) >= 0)
    assert summary["ms_per_query"] == pytest.approx(6.0)


def test_map_closures_baseline_runs_or_is_refused_by_name(tmp_path):
    from mf_lpr_ros.config import preset
    from mf_lpr_ros.errors import MissingDependencyError
    from mf_lpr_ros.evaluation.methods import make_method

    if importlib.util.find_spec("map_closures") is None:
        with pytest.raises(MissingDependencyError, match="pip install map-closures"):
            make_method("map-closures", preset("default"))
        return
    from types import SimpleNamespace

    method = make_method("map-closures", preset("default"))
    cloud = np.random.default_rng(0).uniform(-20, 20, (500, 3))
    method.build([cloud] * 3, np.tile(np.eye(4), (3, 1, 1)), np.zeros(3))
    asked = []

    def closures(query_id, points, k):
        asked.append(query_id)
        return [SimpleNamespace(source_id=2, target_id=query_id, number_of_inliers=90),
                SimpleNamespace(source_id=0, target_id=query_id, number_of_inliers=40),
                SimpleNamespace(source_id=1, target_id=0, number_of_inliers=99)]

    method._closures = SimpleNamespace(get_top_k_closures=closures)
    # Reference 2 is too recent for this query; the closure between two references is ignored.
    retrieval = method.query(cloud, n_active=2, odometry=np.zeros(3))
    assert (retrieval.reference, retrieval.confidence) == (0, 40.0)
    assert method.query(cloud, n_active=3, odometry=np.zeros(3)).reference == 2
    assert asked == [3, 4]                      # queries get fresh ids after the references


def test_each_record_says_why_its_match_was_or_was_not_published(tmp_path, world):
    from mf_lpr_ros.config import preset
    from mf_lpr_ros.datasets import open_source
    from mf_lpr_ros.evaluation.protocol import evaluate_pair
    from mf_lpr_ros.sim.synthetic import route, write_kitti_sequence

    write_kitti_sequence(tmp_path / "first", world, route(40), seed=1)
    write_kitti_sequence(tmp_path / "second", world, route(16, lateral_offset_m=1.0), seed=2)
    config = preset("kitti")
    result = evaluate_pair(open_source(tmp_path / "first"), config, Protocol(5.0),
                           query=open_source(tmp_path / "second"), progress=False)
    records = result.records
    assert len(records) == 16 and any(record.published for record in records)
    for record in records:
        assert record.reason.startswith("accepted") is record.published, record.reason
        assert 0.0 <= record.distinctiveness <= 1.0
        # The full-resolution figure is taken only where the pooled one falls short of a
        # match that passes confidence.
        needed = (record.distinctiveness < config.search.min_distinctiveness
                  and record.confidence >= config.search.min_confidence)
        assert bool(np.isfinite(record.local_distinctiveness)) is needed
        if not record.published and needed and record.local_distinctiveness < 0.3:
            assert "local" in record.reason


def test_candidate_recall_counts_revisits_whose_true_place_was_compared_in_full():
    def searched(nearest, searched_nearest):
        record = _record(nearest, 9.0, 9.0, 1.0, 0.5, [9.0])
        record.searched_nearest_m = searched_nearest
        return record

    records = [searched(1.0, 1.0), searched(1.0, 4.0), searched(2.0, 2.5),
               searched(8.0, 8.0)]     # the last has no reference in reach: not counted
    assert summarise(records, 3.0, 4)["candidate_recall"] == pytest.approx(2 / 3)
    # A method that does not say what it compared has no candidate recall.
    assert np.isnan(summarise([_record(1.0, 1.0, 0.5, 1.0, 0.9, [1.0])], 3.0, 1)
                    ["candidate_recall"])


def test_each_record_holds_the_nearest_place_its_candidate_stage_kept(tmp_path, world):
    """Searching every reference, the nearest searched is the nearest there is; a candidate
    stage that keeps one reference leaves nearer ones out."""
    import dataclasses

    from mf_lpr_ros.config import preset
    from mf_lpr_ros.datasets import open_source
    from mf_lpr_ros.evaluation.protocol import evaluate_pair
    from mf_lpr_ros.sim.synthetic import route, write_kitti_sequence

    write_kitti_sequence(tmp_path / "first", world, route(40), seed=1)
    write_kitti_sequence(tmp_path / "second", world, route(12, lateral_offset_m=1.0), seed=2)
    config = preset("kitti")

    def records(top_k: int):
        search = dataclasses.replace(config.search, prefilter_top_k=top_k,
                                     prefilter_expand_m=0.0)
        return evaluate_pair(open_source(tmp_path / "first"),
                             dataclasses.replace(config, search=search), Protocol(5.0),
                             query=open_source(tmp_path / "second"), progress=False).records

    exact, narrowed = records(0), records(1)
    assert [r.searched_nearest_m for r in exact] == [r.nearest_reference_m for r in exact]
    assert all(r.searched_nearest_m >= r.nearest_reference_m for r in narrowed)
    assert any(r.searched_nearest_m > r.nearest_reference_m + 1.0 for r in narrowed)


def test_thinning_removes_the_same_world_columns_from_every_scan():
    rng = np.random.default_rng(4)
    cell = protocol_module.THINNING_CELL_M
    world = rng.uniform(-40, 40, (40000, 2))
    poses = [euler_pose([0.0, 0.0, 0.0], [0.0, 0.0, 0.0]),
             euler_pose([3.7, -1.2, 0.0], [0.0, 0.0, 0.6])]
    kept_in_world = []
    for index, pose in enumerate(poses):
        local = (world - pose[:2, 3]) @ pose[:2, :2]
        scan = Scan(index, 0.0, pose, points=np.column_stack([local, np.ones(len(local))]))
        kept = thinned_scan(scan, 0.5).points[:, :2] @ pose[:2, :2].T + pose[:2, 3]
        kept_in_world.append(set(map(tuple, np.round(kept, 6))))
    # Both scans lose the same things: what is gone is gone from the world, not from a view.
    assert kept_in_world[0] == kept_in_world[1]
    kept = np.array(sorted(kept_in_world[0]))
    cells = {tuple(c) for c in np.floor(world / cell).astype(int).tolist()}
    kept_cells = {tuple(c) for c in np.floor(kept / cell).astype(int).tolist()}
    assert len(kept_cells) / len(cells) == pytest.approx(0.5, abs=0.05)
    # A column goes whole.
    in_kept_cell = np.array([tuple(c) in kept_cells
                             for c in np.floor(world / cell).astype(int).tolist()])
    assert in_kept_cell.sum() == len(kept)
    with pytest.raises(ValueError, match="pose"):
        thinned_scan(Scan(0, 0.0, None, points=np.ones((5, 3))), 0.5)


def test_a_thinned_density_image_loses_what_its_pixels_points_would():
    # The image's geometry (rows along y, columns along x, the sensor sensor_offset_m from the
    # corner before the central pixel) read as points must lose the same cells.
    rng = np.random.default_rng(5)
    density = np.where(rng.random((151, 151)) < 0.3, rng.integers(1, 10, (151, 151)), 0)
    pose = euler_pose([12.0, -30.0, 0.0], [0, 0, 1.1])
    image = Scan(2, 0.0, pose, density=density.astype(np.float32), density_pixel_m=0.4,
                 sensor_offset_m=0.2)
    thinned = thinned_scan(image, 0.4).density
    occupied, kept = image.density > 0, thinned > 0
    assert not (kept & ~occupied).any()
    assert np.array_equal(thinned[kept], image.density[kept])
    assert kept.sum() / occupied.sum() == pytest.approx(0.6, abs=0.06)
    rows, cols = np.nonzero(occupied)
    centres = np.column_stack([(cols - 151 // 2 + 0.5) * 0.4 - 0.2,
                               (rows - 151 // 2 + 0.5) * 0.4 - 0.2, np.zeros(len(rows))])
    as_points = thinned_scan(Scan(2, 0.0, pose, points=centres), 0.4).points
    assert np.array_equal(as_points, centres[kept[rows, cols]])


class _Images(Sequence):
    """Density images along x, every scan a reference and a query."""

    def __init__(self, n):
        self.name = "images"
        self.stamps = np.arange(n, dtype=float)
        self.poses = np.tile(np.eye(4), (n, 1, 1))
        self.poses[:, 0, 3] = np.arange(n) * 2.0
        self._density = np.random.default_rng(1).integers(0, 2, (n, 120, 120)).astype(np.float32)

    def _read(self, indices):
        for index in indices:
            yield self._scan(index, lambda: {"density": self._density[index].copy(),
                                             "density_pixel_m": 0.4})


class _Describer:
    """A method that records what it was asked to describe, and matches nothing."""

    name = "recorder"
    submap_window = None

    def __init__(self):
        self.described = []

    def describe(self, scan, reference):
        self.described.append((scan.index, reference, int(np.count_nonzero(scan.density))))
        return scan.index

    def build(self, descriptors, poses, stamps):
        pass

    def pass_over(self, odometry):
        pass

    def query(self, descriptor, n_active, odometry):
        return Retrieval(-1, np.zeros(3), 0.0, np.zeros(0, dtype=int), 0.0)


def test_a_thinned_protocol_thins_its_queries_and_never_a_reference():
    sequence = _Images(8)
    whole = {index: int(np.count_nonzero(sequence._density[index])) for index in range(8)}
    protocol = Protocol(3.0, exclude_recent_frames=2, query_thinning=0.5)
    method = _Describer()
    run = run_protocol(method, sequence, select(sequence, protocol, 0.0),
                       query_thinning=protocol.query_thinning, progress=False)
    assert isinstance(run, ProtocolRun) and len(run.records) == 5
    references = [(index, cells) for index, reference, cells in method.described if reference]
    queries = [(index, cells) for index, reference, cells in method.described if not reference]
    assert references == [(index, whole[index]) for index in range(8)]
    assert [index for index, _ in queries] == list(range(3, 8))
    for index, cells in queries:
        assert cells / whole[index] == pytest.approx(0.5, abs=0.1)
    with pytest.raises(ValueError, match="query_thinning"):
        Protocol(3.0, query_thinning=1.0)


def test_evaluate_pair_thins_what_its_protocol_says(monkeypatch):
    thinning = []
    monkeypatch.setattr(protocol_module, "make_method", lambda name, config: _Describer())
    monkeypatch.setattr(protocol_module, "run_protocol", lambda *args, query_thinning, **kw:
                        thinning.append(query_thinning) or ProtocolRun([], []))
    for fraction in (0.0, 0.5):
        evaluate_pair(Line(10), preset("kitti"), Protocol(3.0, exclude_recent_frames=2,
                                                          query_thinning=fraction))
    assert thinning == [0.0, 0.5]
    thinned = [rule for rule in SUITES["tuning"].rules if rule.protocol.query_thinning > 0]
    assert [(rule.references, rule.label) for rule in thinned] == [
        (("kitti_bev/00",), "thinned queries")]


class _LateVoucher(_Describer):
    """Matches every query to the first reference 5 m off its truth; the third query's
    verdict publishes the first late, at the first query's true pose (a vouch that moves a
    weak match)."""

    name = "late voucher"

    def __init__(self):
        super().__init__()
        self.odometry = []

    def query(self, descriptor, n_active, odometry):
        self.odometry.append(np.asarray(odometry, dtype=float))
        confirms = ({0: ("accepted: vouched", self.odometry[0], np.diag([0.25, 0.04]))}
                    if len(self.odometry) == 3 else {})
        return Retrieval(0, self.odometry[-1] + [5.0, 0.0, 0.0], 0.3, np.zeros(1, dtype=int),
                         0.0, confirms=confirms, position_covariance=np.eye(2) * 0.01)


def test_a_match_published_late_is_recorded_at_the_pose_it_is_published_at():
    sequence = _Images(8)
    run = run_protocol(_LateVoucher(), sequence,
                       select(sequence, Protocol(3.0, exclude_recent_frames=2), 0.0),
                       progress=False)
    first, second = run.records[:2]
    assert first.published and first.reason == "accepted: vouched"
    assert first.estimate == pytest.approx(first.truth) and first.rte_m == pytest.approx(0.0)
    assert first.position_covariance == pytest.approx([0.25, 0.0, 0.04])
    assert second.position_covariance == pytest.approx([0.01, 0.0, 0.01])
    assert not second.published and second.rte_m == pytest.approx(5.0)
