"""Submaps in the live logic: a sparse sensor relocalised from submaps where single scans fail,
the window recorded in the map, a localiser that names a differing window, the loop-closure
localiser and its map sharing one window."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mf_lpr_ros.config import Config, preset
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.pose import planar, planar_error
from mf_lpr_ros.core.references import describe_observation
from mf_lpr_ros.core.submap import Submap, SubmapWindow
from mf_lpr_ros.errors import MapParameterMismatch
from mf_lpr_ros.live.localiser import Localiser
from mf_lpr_ros.live.map_builder import MapBuilder
from mf_lpr_ros.live.pose_buffer import PairedScan
from mf_lpr_ros.sim.synthetic import route, scan_world

# 97 % of the returns dropped: ~800 points a scan, as sparse as a downsampled Mid-360 keyframe.
SPARSE_DROPOUT = 0.97


def with_window(window_m: float) -> Config:
    base = preset("default")
    return dataclasses.replace(base, descriptor=dataclasses.replace(base.descriptor,
                                                                    submap_m=window_m))


@pytest.fixture(scope="module")
def sparse_maps(world) -> dict[float, ReferenceMap]:
    """Maps of one sparse traversal, built with single scans (0) and with 4 m submaps."""
    maps = {}
    for window_m in (0.0, 4.0):
        rng = np.random.default_rng(1)
        builder = MapBuilder(with_window(window_m), None)
        for index, (x, y, yaw) in enumerate(route(300)):
            points, pose = scan_world(world, x, y, yaw, rng, dropout=SPARSE_DROPOUT)
            builder.offer(PairedScan(index, 10.0 + 0.1 * index, points, pose))
        maps[window_m] = builder.map
    return maps


def relocalised(world, localiser: Localiser) -> tuple[int, list]:
    """Scans of a second, reversed traversal 1.5 m aside: every scan observed, every 10th
    searched; how many land within 2 m and 5 degrees, and the results."""
    rng = np.random.default_rng(2)
    correct, results = 0, []
    for index, (x, y, yaw) in enumerate(route(300, lateral_offset_m=1.5, reverse=True)):
        points, pose = scan_world(world, x, y, yaw, rng, dropout=SPARSE_DROPOUT)
        stamp = 100.0 + 0.1 * index
        localiser.observe(stamp, points, pose)
        if index % 10 == 9:
            result = localiser.localise(stamp, points, pose)
            results.append(result)
            error_m, error_deg = planar_error(result.match.pose, planar(pose))
            correct += error_m < 2.0 and error_deg < 5.0
    return correct, results


def test_a_sparse_sensor_is_relocalised_from_submaps_where_single_scans_fail(world,
                                                                               sparse_maps):
    single_correct, _ = relocalised(world, Localiser(sparse_maps[0.0], with_window(0.0)))
    assert sparse_maps[4.0].params.submap_m == 4.0, "the map records its window"
    correct, results = relocalised(world, Localiser(sparse_maps[4.0], with_window(4.0)))
    assert correct >= 27 > 10 >= single_correct
    assert results[-1].described_from.startswith("complete submap of")
    assert results[-1].window_complete


def test_scans_without_odometry_are_described_alone(world, sparse_maps):
    localiser = Localiser(sparse_maps[4.0], with_window(4.0))
    points, _ = scan_world(world, 0.0, 0.0, 0.0, np.random.default_rng(0))
    result = localiser.localise(5.0, points, None)
    assert result.described_from == "single scan"


def test_a_localiser_asking_for_another_window_is_refused_by_name(sparse_maps):
    with pytest.raises(MapParameterMismatch, match="submap_m"):
        Localiser(sparse_maps[4.0], with_window(2.0))


def test_map_references_are_described_from_their_submap(world):
    config = with_window(3.0)
    rng = np.random.default_rng(5)
    builder = MapBuilder(config, None)
    mirror = Submap(SubmapWindow.for_descriptor(config.descriptor))
    scans = []
    for index, (x, y, yaw) in enumerate(route(60)):
        points, pose = scan_world(world, x, y, yaw, rng, dropout=SPARSE_DROPOUT)
        stamp = 1.0 + index
        added = builder.offer(PairedScan(index, stamp, points, pose))
        mirror.add(stamp, points, pose)
        if added is not None:
            scans.append((stamp, mirror.points_at(stamp).points))
    assert len(scans) == len(builder.map) > 10
    for reference, (stamp, submap_points) in enumerate(scans):
        expected = describe_observation(config.descriptor, reference=True, stamp=stamp,
                                        points=submap_points)
        np.testing.assert_array_equal(builder.map.occupancy(reference), expected)


def test_loop_closure_localiser_and_its_map_share_one_window():
    config = with_window(3.0)
    localiser = Localiser(ReferenceMap(config.descriptor), config, mode="loop_closure")
    assert localiser._builder.submap is localiser.submap
