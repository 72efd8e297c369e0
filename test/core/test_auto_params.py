"""preset auto: the descriptor derived from the scans (mf_lpr_ros/core/auto_params.py)."""

import dataclasses
import math

import numpy as np
import pytest

from mf_lpr_ros.config import Config, config_from_dict, preset
from mf_lpr_ros.core.auto_params import (
    SAMPLE_SCANS,
    SensorProfile,
    auto_config,
    auto_descriptor,
    describe_choice,
    measure_sensor,
    single_scan_warning,
)
from mf_lpr_ros.core.descriptor import voxel_size_for_density
from mf_lpr_ros.core.pose import pose_matrix
from mf_lpr_ros.datasets import open_source
from mf_lpr_ros.errors import ConfigError, InvalidCloudError
from mf_lpr_ros.live.map_builder import MapBuilder
from mf_lpr_ros.live.pose_buffer import PairedScan
from mf_lpr_ros.params import DescriptorParams
from mf_lpr_ros.pipeline.mapping import build_map
from mf_lpr_ros.sim.synthetic import route, scan_world, write_kitti_sequence

# 97 % of the returns dropped: ~870 occupied 1 m voxels a scan, a sparse sensor's (the
# generated world's full scans hold ~8,600).
SPARSE_DROPOUT = 0.97


def _scans(world, n=6, lift_m=0.0, seed=0, dropout=0.1):
    """Scans of the generated world (ground 1.7 m below the sensor), the sensor raised by
    lift_m."""
    rng = np.random.default_rng(seed)
    clouds = []
    for x, y, yaw in route(n):
        points, _ = scan_world(world, x, y, yaw, rng, dropout=dropout)
        clouds.append(points[:, :3] - np.array([0.0, 0.0, lift_m], dtype=np.float32))
    return clouds


@pytest.mark.parametrize("lift_m", [0.0, 1.0])
def test_the_height_floor_follows_the_mount_and_nothing_is_cut_above(world, lift_m):
    profile = measure_sensor(_scans(world, lift_m=lift_m, dropout=SPARSE_DROPOUT))
    assert profile.ground_below_sensor_m == pytest.approx(1.7 + lift_m, abs=0.1)
    params = auto_descriptor(profile, DescriptorParams())
    # The floor sits at the same height above the ground whatever the mount.
    assert params.z_min + profile.ground_below_sensor_m == pytest.approx(0.5, abs=0.006)
    assert params.z_max == DescriptorParams().z_max
    assert profile.horizontal_fov_deg == 360.0


def test_a_dense_360_degree_sensor_keeps_the_given_voxel_and_height_band(world):
    """On every dense sensor of the tuning suite the voxel rule and the ground floor lost to
    the defaults; such a sensor gets only its levelling decided, a sparse one everything."""
    dense = measure_sensor(_scans(world))
    assert dense.occupied_voxels > 5000 and math.isfinite(dense.ground_below_sensor_m)
    given = DescriptorParams(voxel_size=0.6, z_min=-1.0)
    assert auto_descriptor(dense, given) == dataclasses.replace(given, level=False)
    assert auto_descriptor(dense, DescriptorParams()) == DescriptorParams(level=False)
    sparse = auto_descriptor(measure_sensor(_scans(world, dropout=SPARSE_DROPOUT)), given)
    assert sparse.submap_m > 0 and sparse.voxel_size != 0.6 and sparse.z_min != -1.0


def test_voxel_size_follows_the_papers_rule_held_between_what_the_sensor_sees(world):
    clouds = _scans(world, dropout=SPARSE_DROPOUT)
    profile = measure_sensor(clouds)
    params = auto_descriptor(profile, DescriptorParams())
    expected = min(max(voxel_size_for_density(profile.occupied_voxels),
                       2 * profile.range_held_m / params.size),
                   2 * profile.range_p95_m / params.size)
    assert params.voxel_size == pytest.approx(expected, abs=0.005)
    # Scans seeing half as far get a window half as wide at most.
    near = measure_sensor([c[np.hypot(c[:, 0], c[:, 1]) < 12.0] for c in clouds])
    assert auto_descriptor(near, DescriptorParams()).extent_m <= 2 * near.range_p95_m + 0.6
    # The paper's three points: denser scans, smaller voxels.
    assert voxel_size_for_density(1360) == pytest.approx(0.3, abs=0.05)
    assert voxel_size_for_density(275) == pytest.approx(1.3, abs=0.05)


def test_a_narrow_sensor_seeing_far_keeps_a_window_holding_most_of_its_returns():
    """The paper's rule gives any scan over ~1360 occupied voxels 0.3 m (a 36 m window): a
    narrow sensor in a town seen to 60 m keeps a window holding the nearer 75 % of its
    returns; a forest's short sight lines keep the rule's voxel."""
    def profile(held_m: float, occupied: float = 2700.0, p95_m: float = 60.0) -> SensorProfile:
        return SensorProfile(n_scans=12, occupied_voxels=occupied, ground_below_sensor_m=1.7,
                             horizontal_fov_deg=80.0, heading_deg=0.0, tilt_spread_deg=0.5,
                             range_p95_m=p95_m, range_held_m=held_m)

    town = auto_descriptor(profile(26.4), DescriptorParams())
    assert town.voxel_size == pytest.approx(0.44) and town.extent_m >= 2 * 26.4 - 0.5
    assert auto_descriptor(profile(8.0), DescriptorParams()).voxel_size == pytest.approx(0.3)
    # Never past the sensor's reach, however large the rule's voxel for a sparse scan.
    assert auto_descriptor(profile(15.0, occupied=300.0, p95_m=20.0),
                           DescriptorParams()).voxel_size == pytest.approx(0.33)


def test_field_of_view_and_tilt_are_measured(world):
    clouds = _scans(world)
    azimuth = [np.degrees(np.arctan2(c[:, 1], c[:, 0])) for c in clouds]
    forward = [c[np.abs(a - 30.0) < 35.0] for c, a in zip(clouds, azimuth)]
    profile = measure_sensor(forward)
    assert profile.horizontal_fov_deg == pytest.approx(70.0, abs=10.0)
    assert profile.heading_deg == pytest.approx(30.0, abs=5.0)
    assert math.isnan(profile.tilt_spread_deg)
    rng = np.random.default_rng(1)
    tilted = [pose_matrix(np.zeros(3), _quaternion(rng.normal(0, 0.2), rng.normal(0, 0.2)))[:3, :3]
              for _ in clouds]
    upright = [np.eye(3) for _ in clouds]
    assert auto_descriptor(measure_sensor(clouds, tilted), DescriptorParams()).level
    assert not auto_descriptor(measure_sensor(clouds, upright), DescriptorParams()).level


def _quaternion(roll, pitch):
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    return np.array([sr * cp, cr * sp, -sr * sp, cr * cp])


def test_auto_is_a_preset_that_stays_auto_until_resolved(world):
    assert preset("auto").auto and not preset("kitti").auto
    config = config_from_dict({"preset": "auto", "search": {"top_n": 4}})
    assert config.auto and config.search.top_n == 4
    resolved, _ = auto_config(_scans(world), config)
    assert not resolved.auto and resolved.search.top_n == 4
    with pytest.raises(ConfigError, match="auto"):
        preset("autumn")
    with pytest.raises(InvalidCloudError, match="auto"):
        measure_sensor([np.full((10, 3), np.nan)])


def test_build_map_with_auto_records_its_choice(world, tmp_path):
    write_kitti_sequence(tmp_path / "seq", world, route(20), seed=3)
    reference_map = build_map(open_source(tmp_path / "seq"), preset("auto"), progress=False)
    choice = reference_map.metadata["auto"]
    assert choice["preset"] == "auto"
    assert choice["sensor_profile"]["ground_below_sensor_m"] == pytest.approx(1.7, abs=0.1)
    assert reference_map.params == auto_descriptor(_profile_of(choice), Config().descriptor)
    assert "as given (a dense 360-degree sensor)" in choice["choice"]
    path = tmp_path / "auto.mfmap"
    reference_map.save(path)
    from mf_lpr_ros.core.map_store import ReferenceMap
    assert ReferenceMap.load(path).metadata["auto"]["choice"] == choice["choice"]


def test_a_named_preset_describing_single_scans_of_a_sparse_sensor_says_so(world, tmp_path):
    # Offline: the map records the warning (build-map prints it, the localiser logs it).
    write_kitti_sequence(tmp_path / "sparse", world, route(20), seed=3, dropout=SPARSE_DROPOUT)
    write_kitti_sequence(tmp_path / "dense", world, route(20), seed=3)
    sparse, dense = open_source(tmp_path / "sparse"), open_source(tmp_path / "dense")
    warning = build_map(sparse, preset("default"), progress=False).metadata[
        "single_scan_warning"]
    assert "look sparse" in warning and "preset auto" in warning
    assert "single_scan_warning" not in build_map(sparse, preset("livox"),
                                                  progress=False).metadata
    assert "single_scan_warning" not in build_map(dense, preset("default"),
                                                  progress=False).metadata
    # Live: said once the first SAMPLE_SCANS scans are measured, and kept in the map.
    rng = np.random.default_rng(2)
    for dropout, expected in ((SPARSE_DROPOUT, True), (0.1, False)):
        builder = MapBuilder(preset("default"), None)
        for index, (x, y, yaw) in enumerate(route(SAMPLE_SCANS)):
            assert builder.single_scan_warning is None
            points, pose = scan_world(world, x, y, yaw, rng, dropout=dropout)
            builder.offer(PairedScan(index, float(index), points, pose))
        assert (builder.single_scan_warning is not None) == expected
        assert ("single_scan_warning" in builder.map.metadata) == expected


def test_the_single_scan_warning_names_what_it_measured():
    def profile(occupied: float, fov_deg: float) -> SensorProfile:
        return SensorProfile(n_scans=12, occupied_voxels=occupied, ground_below_sensor_m=1.7,
                             horizontal_fov_deg=fov_deg, heading_deg=0.0, tilt_spread_deg=0.5,
                             range_p95_m=40.0, range_held_m=20.0)

    single = DescriptorParams()
    assert "field of view of 70 degrees" in single_scan_warning(profile(3000.0, 70.0), single)
    assert "look narrow" in single_scan_warning(profile(3000.0, 70.0), single)
    assert "700 occupied 1 m voxels" in single_scan_warning(profile(700.0, 360.0), single)
    assert single_scan_warning(profile(3000.0, 360.0), single) is None
    assert single_scan_warning(profile(700.0, 360.0),
                               dataclasses.replace(single, submap_m=3.0)) is None


def test_density_images_cannot_be_measured(tmp_path):
    from PIL import Image

    (tmp_path / "imgs").mkdir()
    Image.fromarray(np.zeros((151, 151), np.uint8)).save(tmp_path / "imgs" / "000000.png")
    (tmp_path / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(InvalidCloudError, match="density images"):
        build_map(open_source(tmp_path), preset("auto"), progress=False)


def test_live_map_builder_holds_scans_until_auto_is_derived(world):
    builder = MapBuilder(preset("auto"), None)
    rng = np.random.default_rng(2)
    trajectory = route(SAMPLE_SCANS + 4)
    for index, (x, y, yaw) in enumerate(trajectory[:SAMPLE_SCANS - 1]):
        points, pose = scan_world(world, x, y, yaw, rng)
        assert builder.offer(PairedScan(index, float(index), points, pose)) is None
    assert builder.waiting_for_auto and len(builder.map) == 0
    for index, (x, y, yaw) in enumerate(trajectory[SAMPLE_SCANS - 1:], start=SAMPLE_SCANS - 1):
        points, pose = scan_world(world, x, y, yaw, rng)
        builder.offer(PairedScan(index, float(index), points, pose))
    assert not builder.waiting_for_auto
    assert "preset auto" in builder.auto_choice
    assert builder.map.params == auto_descriptor(_profile_of(builder.map.metadata["auto"]),
                                                 Config().descriptor)
    assert builder.map.params.level is False
    # Every scan moved >= 2 m: the held-back scans became references too, in order.
    assert list(builder.map.source_indices) == list(range(len(trajectory)))


def test_the_logged_choice_names_the_height_floor_and_the_sparseness_it_measured():
    def profile(ground_m: float, occupied: float) -> SensorProfile:
        return SensorProfile(n_scans=12, occupied_voxels=occupied, ground_below_sensor_m=ground_m,
                             horizontal_fov_deg=360.0, heading_deg=0.0, tilt_spread_deg=0.5,
                             range_p95_m=40.0, range_held_m=20.0)

    sparse = profile(math.nan, 700.0)
    line = describe_choice(sparse, auto_descriptor(sparse, DescriptorParams()))
    assert "no ground found" in line and "z unbounded below" in line
    assert "700 occupied 1 m voxels/scan" in line and "sparse" in line
    assert line.endswith("submaps of 3 m")
    floored = profile(1.7, 700.0)
    line = describe_choice(floored, auto_descriptor(floored, DescriptorParams()))
    assert "ground 1.70 m below the sensor" in line and "z from -1.2 m" in line
    dense = profile(1.7, 2000.0)
    line = describe_choice(dense, auto_descriptor(dense, DescriptorParams()))
    assert "dense" in line and "voxel 0.50 m and z unbounded below as given" in line
    assert line.endswith("single scans")


def _profile_of(metadata: dict) -> SensorProfile:
    """The SensorProfile a map's auto metadata records (None stands for NaN there)."""
    return SensorProfile(**{key: math.nan if value is None else value
                            for key, value in metadata["sensor_profile"].items()})
