"""Submaps (core.submap): scans moved into the newest scan's frame, the window's bounds, and the
offline reading (pipeline.submaps) equal to what a live node accumulates."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mf_lpr_ros.config import Config
from mf_lpr_ros.core.auto_params import (
    SensorProfile,
    auto_descriptor,
    measure_sensor,
    needs_submaps,
)
from mf_lpr_ros.core.descriptor import one_point_per_voxel
from mf_lpr_ros.core.pose import pose_matrix, quaternion_from_yaw
from mf_lpr_ros.core.submap import Submap, SubmapWindow
from mf_lpr_ros.datasets import Scan, Sequence
from mf_lpr_ros.errors import ConfigError
from mf_lpr_ros.params import DescriptorParams
from mf_lpr_ros.pipeline.submaps import SubmapSequence, with_submaps
from mf_lpr_ros.sim.lidar import MID360, VLP16, cast
from mf_lpr_ros.sim.simulator import urban_traversals


def planar_pose(x: float, y: float, yaw: float, z: float = 0.0) -> np.ndarray:
    return pose_matrix(np.array([x, y, z]), quaternion_from_yaw(yaw))


def window(metres: float, scans: int = 100, age_s: float = 60.0) -> SubmapWindow:
    return SubmapWindow(metres, scans, age_s, voxel_m=0.01, reach_m=1000.0)


def seen_from(pose: np.ndarray, world_points: np.ndarray) -> np.ndarray:
    """World points in the sensor frame of pose."""
    inverse = np.linalg.inv(pose)
    return world_points @ inverse[:3, :3].T + inverse[:3, 3]


def test_earlier_scans_land_where_the_current_sensor_sees_them():
    landmarks = np.array([[5.0, 2.0, 1.0], [-3.0, 4.0, 0.5], [10.0, -6.0, 2.0]])
    submap = Submap(window(10.0))
    poses = [planar_pose(0.0, 0.0, 0.0), planar_pose(1.5, 0.5, 0.4),
             planar_pose(3.0, 2.0, 1.3)]
    # Each scan sees one landmark only: the submap of the last must hold all three.
    for stamp, (pose, landmark) in enumerate(zip(poses, landmarks)):
        submap.add(float(stamp), seen_from(pose, landmark[None]), pose)
    built = submap.points_at(2.0)
    expected = seen_from(poses[-1], landmarks)
    assert built.scans == 3
    assert built.span_m == pytest.approx(np.hypot(1.5, 0.5) + np.hypot(1.5, 1.5))
    for point in expected:
        assert np.min(np.linalg.norm(built.points - point, axis=1)) < 1e-6


def test_window_is_bounded_by_travel_count_and_age():
    point = np.array([[1.0, 0.0, 0.0]])
    by_travel = Submap(window(2.5))
    by_count = Submap(window(100.0, scans=3))
    by_age = Submap(window(100.0, age_s=1.5))
    for k in range(10):
        pose = planar_pose(float(k), 0.0, 0.0)
        for submap in (by_travel, by_count, by_age):
            submap.add(float(k), point, pose)
    travel = by_travel.points_at(9.0)
    assert (travel.scans, travel.span_m, travel.complete) == (3, 2.0, True)
    assert by_count.points_at(9.0).scans == 3
    assert by_age.points_at(9.0).scans == 2
    assert len(by_travel) == 3, "scans beyond the window are not kept"


def test_partial_window_is_reported_until_the_robot_has_moved_far_enough():
    submap = Submap(window(3.0))
    point = np.array([[1.0, 0.0, 0.0]])
    for k in range(3):
        submap.add(float(k), point, planar_pose(float(k), 0.0, 0.0))
    assert not submap.points_at(2.0).complete
    assert "partial submap of 3 scans over 2.0 m" == submap.points_at(2.0).describe()
    for k in range(3, 6):
        submap.add(float(k), point, planar_pose(float(k), 0.0, 0.0))
    assert submap.points_at(5.0).complete


def test_lost_odometry_and_time_going_back_start_afresh_and_repeats_are_kept_once():
    submap = Submap(window(10.0))
    point = np.array([[1.0, 0.0, 0.0]])
    for k in range(4):
        submap.add(float(k), point, planar_pose(0.1 * k, 0.0, 0.0))
    submap.add(3.0, point, planar_pose(0.3, 0.0, 0.0))
    assert len(submap) == 4
    submap.add(2.0, point, planar_pose(0.2, 0.0, 0.0))
    assert len(submap) == 4, "a scan already kept (searched after newer ones came) is not re-added"
    submap.add(4.0, point, None)
    assert len(submap) == 0
    for k in (10, 11):
        submap.add(float(k), point, planar_pose(0.0, 0.0, 0.0))
    submap.add(5.0, point, planar_pose(0.0, 0.0, 0.0))
    assert len(submap) == 1, "a bag played again starts a new window"
    with pytest.raises(KeyError):
        submap.points_at(10.0)


def test_stored_scans_are_thinned_and_cropped_to_what_can_reach_the_window():
    params = DescriptorParams(voxel_size=0.5, submap_m=4.0)
    settings = SubmapWindow.for_descriptor(params)
    assert settings.voxel_m == 0.25
    assert settings.reach_m == pytest.approx(30.0 * math.sqrt(2.0) + 4.0)
    dense = np.random.default_rng(0).uniform(-1.0, 1.0, (20000, 3))
    far = np.array([[100.0, 0.0, 0.0]])
    submap = Submap(settings)
    submap.add(0.0, np.vstack([dense, far]), planar_pose(0.0, 0.0, 0.0))
    kept = submap.points_at(0.0).points
    assert len(kept) <= 8 ** 3
    assert np.hypot(kept[:, 0], kept[:, 1]).max() < 2.0


def test_submap_parameters_are_validated_by_name():
    for field, value in (("submap_m", -1.0), ("submap_max_scans", 0),
                         ("submap_max_age_s", 0.0)):
        with pytest.raises(ConfigError, match=field):
            DescriptorParams(**{field: value})


class _Line(Sequence):
    """Scans along a bending line, each seeing a few world landmarks, one pose missing."""

    def __init__(self, count: int = 40) -> None:
        rng = np.random.default_rng(4)
        self.name = "line"
        self.stamps = np.arange(count) * 0.5
        self.poses = np.stack([planar_pose(0.7 * k, 0.02 * k * k, 0.03 * k)
                               for k in range(count)])
        self.poses[17] = np.nan
        self.world = rng.uniform(-20.0, 40.0, (count, 5, 3))

    def _read(self, indices):
        for index in indices:
            pose = self.poses[index]
            local = self.world[index] if not np.isfinite(pose).all() \
                else seen_from(pose, self.world[index])
            yield Scan(int(index), float(self.stamps[index]), pose, points=local)


def test_offline_submaps_equal_what_a_live_node_accumulates():
    sequence = _Line()
    settings = window(3.0, scans=6)
    live = Submap(settings)
    expected = {}
    for scan in sequence.iter_scans():
        live.add(scan.stamp, scan.points, scan.pose)
        expected[scan.index] = live.points_at(scan.stamp).points if len(live) else scan.points
    offline = with_submaps(sequence, settings)
    assert isinstance(offline, SubmapSequence)
    wanted = [3, 9, 16, 17, 18, 20, 39]
    for scan in offline.iter_scans(wanted):
        np.testing.assert_allclose(np.sort(scan.points, axis=0),
                                   np.sort(expected[scan.index], axis=0), atol=1e-9)
    assert len(next(offline.iter_scans([17])).points) == 5, "no pose: the scan alone"
    assert len(next(offline.iter_scans([18])).points) == 5, "nothing reaches back across it"
    assert len(next(offline.iter_scans([20])).points) > 5


def test_single_scans_when_the_window_is_off_or_there_is_no_odometry():
    sequence = _Line()
    assert with_submaps(sequence, window(0.0)) is sequence
    assert with_submaps(sequence, None) is sequence
    sequence.poses = None
    assert with_submaps(sequence, window(3.0)) is sequence


def _profile(fov: float, occupied_voxels: float) -> SensorProfile:
    return SensorProfile(n_scans=12, occupied_voxels=occupied_voxels, ground_below_sensor_m=1.0,
                         horizontal_fov_deg=fov, heading_deg=0.0, tilt_spread_deg=0.5,
                         range_p95_m=40.0, range_held_m=20.0)


def test_auto_gives_narrow_and_sparse_sensors_submaps_and_dense_ones_single_scans():
    base = Config().descriptor
    assert not needs_submaps(_profile(360.0, 1600.0))
    assert auto_descriptor(_profile(360.0, 1600.0), base).submap_m == 0.0
    assert auto_descriptor(_profile(70.0, 1600.0), base).submap_m > 0
    assert auto_descriptor(_profile(360.0, 850.0), base).submap_m > 0


def _sweeps(sensor, n: int = 4) -> list[np.ndarray]:
    traversals = urban_traversals(seed=5)
    rng = np.random.default_rng(0)
    poses = [pose_matrix(np.array([x, y, sensor.mount_height_m]), quaternion_from_yaw(yaw))
             for x, y, yaw in traversals.first[:: len(traversals.first) // n][:n]]
    return [cast(traversals.scene, sensor, pose, rng) for pose in poses]


def test_auto_reads_sparseness_from_what_a_scan_covers_not_from_returns_per_surface():
    """A longer integration (every return four times, 5 mm apart) leaves a sparse sensor sparse,
    and downsampling a dense one to 0.3 m leaves it dense: real sensors differ in both (BALM's
    scans give 8.4 returns per occupied voxel as .bin files, 5.0 as the bag)."""
    rng = np.random.default_rng(1)
    mid360 = _sweeps(MID360)
    integrated = [np.concatenate([c + rng.normal(0.0, 0.005, c.shape).astype(np.float32)
                                  for _ in range(4)]) for c in mid360]
    assert needs_submaps(measure_sensor(mid360))
    assert needs_submaps(measure_sensor(integrated))
    vlp16 = _sweeps(VLP16)
    assert not needs_submaps(measure_sensor(vlp16))
    assert not needs_submaps(measure_sensor([one_point_per_voxel(c, 0.3) for c in vlp16]))
