"""Scans with nothing to describe in offline work (an empty cloud at a driver's start, a file
cut short, a sensor facing an open field): `build-map` (serial and bulk) and `evaluate` pass
over them as the live nodes and `localise` do, say which, and stop only when nothing at all can
be described."""

from __future__ import annotations

import numpy as np
import pytest

from mf_lpr_ros.cli import main
from mf_lpr_ros.config import preset
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.pose import planar
from mf_lpr_ros.core.references import PASSED_OVER_KEY
from mf_lpr_ros.datasets import RosbagSequence, open_source
from mf_lpr_ros.errors import InvalidCloudError
from mf_lpr_ros.evaluation.methods import MatchedFilterMethod
from mf_lpr_ros.evaluation.protocol import Protocol, evaluate_pair, run_protocol, select
from mf_lpr_ros.pipeline import localise
from mf_lpr_ros.pipeline.bulk import SourceSpec, build_maps
from mf_lpr_ros.pipeline.mapping import (
    NOT_DESCRIBED,
    build_map,
    describe_scan,
    plan_references,
)
from mf_lpr_ros.sim import simulator
from mf_lpr_ros.sim.synthetic import route, write_kitti_sequence


def _blank(folder, index: int) -> None:
    """Scan index of a KITTI folder made one with nothing to describe: every return far beyond
    the descriptor's window."""
    far = np.zeros((50, 4), dtype="<f4")
    far[:, 0] = 500.0
    far.tofile(folder / "velodyne" / f"{index:06d}.bin")


def test_a_bag_message_with_an_empty_cloud_is_a_scan_naming_its_problem(tmp_path, monkeypatch):
    """The scans after it are read on; describing it raises the problem with the scan's name."""
    urban = simulator.WORLDS["urban"]()
    cast, calls = simulator.cast, []

    def empty_third(*args):
        calls.append(1)
        points = cast(*args)
        return points[:0] if len(calls) == 3 else points

    monkeypatch.setattr(simulator, "cast", empty_third)
    simulator.write_bag(tmp_path / "day", urban.scene, urban.sensor, urban.first[:6], seed=3,
                        progress=False)
    scans = list(RosbagSequence(tmp_path / "day").iter_scans())
    assert [scan.points is None for scan in scans] == [False, False, True, False, False, False]
    assert scans[2].problem == "/points message 2: PointCloud2 is empty (width * height = 0)"
    assert all(scan.problem == "" for k, scan in enumerate(scans) if k != 2)
    with pytest.raises(InvalidCloudError, match=rf"^scan 2 \(stamp {scans[2].stamp:.3f} s\): "
                                                r"/points message 2: PointCloud2 is empty"):
        describe_scan(scans[2], preset("default").descriptor, reference=True)

    # The whole bag still makes a map (reference 2 from scan 3) and is localised around it.
    planned = plan_references(RosbagSequence(tmp_path / "day"), preset("default")).indices
    reference_map = build_map(RosbagSequence(tmp_path / "day"), preset("default"),
                              progress=False)
    assert planned.tolist() == [0, 2, 4] and reference_map.source_indices.tolist() == [0, 3, 4]
    outcomes = localise.localise_sequence(reference_map, RosbagSequence(tmp_path / "day"),
                                          preset("default").search, progress=False)
    assert [outcome.match is None for outcome in outcomes] == [False, False, True] + [False] * 3
    assert outcomes[2].verdict.reason.startswith(f"{NOT_DESCRIBED}scan 2 ")
    assert np.nanmax([outcome.translation_error_m for outcome in outcomes]) < 0.5


@pytest.fixture
def blanked(world, tmp_path):
    """A KITTI sequence of ~1.1 m steps (references every other scan at 2 m) with planned
    references 3 and 5 blanked, and 5's next scan a truncated file: (folder, planned indices,
    3's, 5's)."""
    folder = tmp_path / "first"
    write_kitti_sequence(folder, world, route(200), seed=1)
    planned = plan_references(open_source(folder), preset("kitti")).indices
    third, fifth = int(planned[3]), int(planned[5])
    assert planned[4] > third + 1 and planned[6] == fifth + 2      # the layout the test needs
    for index in (third, fifth):
        _blank(folder, index)
    (folder / "velodyne" / f"{fifth + 1:06d}.bin").write_bytes(b"\0" * 10)
    return folder, planned, third, fifth


def test_a_reference_with_nothing_to_describe_is_taken_from_the_next_scan(blanked):
    """As the live map builder takes the next scan; where no scan before the next reference
    can be described, the map has none there. The map's metadata names the scans passed over,
    and the bulk build (chunks of the plan) gives the same map."""
    folder, planned, third, fifth = blanked
    reference_map = build_map(open_source(folder), preset("kitti"), progress=False)
    expected = [index for index in planned.tolist() if index != fifth]
    expected[3] = third + 1
    assert reference_map.source_indices.tolist() == expected
    noted = reference_map.metadata[PASSED_OVER_KEY]
    assert noted["count"] == 3
    assert [scan["scan"] for scan in noted["scans"]] == [third, fifth, fifth + 1]
    assert noted["scans"][0]["why"].startswith(f"scan {third} (stamp ")
    assert "no finite point" in noted["scans"][0]["why"]
    assert noted["scans"][2]["why"].endswith(f"{fifth + 1:06d}.bin: size is not a multiple of 16 "
                                             f"bytes (x y z intensity)")

    [bulk] = build_maps([SourceSpec(str(folder))], preset("kitti"), progress=False)
    assert bulk.source_indices.tolist() == expected
    assert np.array_equal(bulk.occupancy_bits, reference_map.occupancy_bits)
    assert bulk.metadata[PASSED_OVER_KEY]["count"] == 3


def test_build_map_says_which_scans_it_passed_over(blanked, tmp_path, capsys):
    folder, _, third, _ = blanked
    out = tmp_path / "map.mfmap"
    assert main(["build-map", str(folder), "--preset", "kitti", "--out", str(out),
                 "--quiet"]) == 0
    error = capsys.readouterr().err
    assert "passed over 3 scan(s) with nothing to describe" in error
    assert f"the first: scan {third} (stamp " in error
    assert ReferenceMap.load(out).metadata[PASSED_OVER_KEY]["count"] == 3


def test_a_source_with_nothing_to_describe_is_refused_by_name(world, tmp_path, capsys):
    folder = tmp_path / "first"
    write_kitti_sequence(folder, world, route(6), seed=1)
    for index in range(6):
        _blank(folder, index)
    with pytest.raises(InvalidCloudError, match=r"first: no reference could be described; 6 "
                                                r"scan\(s\) .* the first: scan 0 \(stamp"):
        build_map(open_source(folder), preset("kitti"), progress=False)
    assert main(["evaluate", "--reference", str(folder), "--preset", "kitti", "--tolerance",
                 "5", "--exclude-recent-frames", "2", "--quiet"]) == 2
    error = capsys.readouterr().err
    assert "none of the 6 references could be described; the first: scan 0 (stamp " in error


def test_evaluate_passes_over_scans_with_nothing_to_describe(world, tmp_path, capsys):
    """A reference that cannot be described is left out of the map (its place stays in the
    ground truth); a query that cannot be described is a miss that says why; the rest are
    matched as before."""
    write_kitti_sequence(tmp_path / "first", world, route(40), seed=1)
    write_kitti_sequence(tmp_path / "second", world, route(8, lateral_offset_m=1.0), seed=2)
    _blank(tmp_path / "second", 2)
    _blank(tmp_path / "first", 5)
    protocol = Protocol(tolerance_m=3.0)
    result = evaluate_pair(open_source(tmp_path / "first"), preset("kitti"), protocol,
                           query=open_source(tmp_path / "second"), progress=False)
    records = result.records
    assert len(records) == 8 and result.summary["queries_not_described"] == 1
    assert result.summary["references_not_described"] == 1
    assert records[2].reference_index == -1 and not records[2].published
    assert records[2].reason.startswith(f"{NOT_DESCRIBED}scan 2 (stamp ")
    # Query 1 is at reference 5's place, which the map lacks: a positive that can only miss.
    assert records[1].nearest_reference_m <= 3.0 < records[1].retrieved_distance_m
    assert all(record.reference_index != 5 for record in records)
    assert all(records[k].retrieved_distance_m <= 3.0 for k in (0, 3, 4, 5, 6, 7))
    assert result.summary["recall_at_1"] == pytest.approx(6 / 8)
    # Matches confirmed late are marked on their own records, not shifted by the one skipped.
    assert [record.published for record in records] == [False] * 4 + [True] * 4
    assert records[3].reason.startswith("odometry consistency")

    assert main(["evaluate", "--reference", str(tmp_path / "first"), "--query",
                 str(tmp_path / "second"), "--tolerance", "3", "--preset", "kitti",
                 "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "queries_not_described: 1 (each a miss" in printed
    assert "references_not_described: 1 (left out of the map" in printed
    assert np.isfinite(result.summary["ms_per_query"])


def test_evaluate_moves_the_verifier_over_a_query_it_cannot_search(world, tmp_path):
    """As `localise` does: odometry consistency counts travel step by step, so a query passed
    over is still a step (the route bends: skipping it would shorten the travel)."""
    write_kitti_sequence(tmp_path / "first", world, route(40), seed=1)
    write_kitti_sequence(tmp_path / "second", world, route(8, lateral_offset_m=1.0), seed=2)
    _blank(tmp_path / "second", 2)
    config = preset("kitti")
    reference, query = open_source(tmp_path / "first"), open_source(tmp_path / "second")
    passed = []

    class Recording(MatchedFilterMethod):
        def pass_over(self, odometry):
            passed.append(odometry)
            super().pass_over(odometry)

    method = Recording(config)
    selection = select(reference, Protocol(tolerance_m=3.0), config.spacing_m, query=query)
    run_protocol(method, reference, selection, query=query, progress=False)
    odometry = planar(query.poses)
    assert len(passed) == 1 and np.allclose(passed[0], odometry[2])
    steps = np.hypot(*np.diff(odometry[:, :2], axis=0).T)
    assert method._verifier.consistency.travelled_m == pytest.approx(steps.sum())
    merged = np.hypot(*(odometry[3, :2] - odometry[1, :2])) + steps[[0, 3, 4, 5, 6]].sum()
    assert steps.sum() > merged + 0.5
