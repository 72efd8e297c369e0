"""The ROS-free logic of the live nodes: pose buffering, pairing, map building, acceptance."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from mf_lpr_ros.config import preset
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.pose import euler_pose, planar, planar_error, pose_matrix, quaternion_from_yaw
from mf_lpr_ros.core.references import PASSED_OVER_KEY
from mf_lpr_ros.core.verification import VOUCHED, VOUCHED_WHERE_PREDICTED
from mf_lpr_ros.errors import InvalidCloudError, InvalidPoseError, MapParameterMismatch
from mf_lpr_ros.live.localiser import UNLEVELLED, Localiser, relocalised_pose
from mf_lpr_ros.live.map_builder import MapBuilder
from mf_lpr_ros.live.pose_buffer import PairedScan, PoseBuffer, ScanPoseSynchroniser
from mf_lpr_ros.sim.synthetic import route, scan_world

CONFIG = preset("kitti")


def pose_at(x: float, y: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    return pose_matrix(np.array([x, y, 0.0]), quaternion_from_yaw(yaw))


def test_pose_buffer_interpolates_waits_and_refuses():
    buffer = PoseBuffer(max_gap_s=1.0)
    assert buffer.lookup(0.5)[0] == "wait"
    buffer.add(0.0, pose_at(0.0))
    buffer.add(1.0, pose_at(2.0, yaw=0.2))
    status, pose = buffer.lookup(0.25)
    assert status == "ok" and pose[0, 3] == pytest.approx(0.5)
    assert math.atan2(pose[1, 0], pose[0, 0]) == pytest.approx(0.05)
    assert buffer.lookup(1.5) == ("wait", None)           # a later sample may still come
    assert buffer.lookup(3.0)[0] == "none"                # too far past the newest sample
    # End of stream: the last sample, only while it is still the nearest (half an interval).
    assert buffer.lookup(1.4, final=True)[0] == "ok"
    assert buffer.lookup(1.6, final=True)[0] == "none"
    assert buffer.lookup(-5.0)[0] == "none"
    with pytest.raises(InvalidPoseError, match="not after"):
        buffer.add(0.5, pose_at(1.0))
    nan_pose = pose_at(1.0)
    nan_pose[0, 3] = np.nan
    with pytest.raises(InvalidPoseError, match="NaN"):
        buffer.add(2.0, nan_pose)
    sheared = pose_at(1.0)
    sheared[0, 1] = 0.5
    with pytest.raises(InvalidPoseError, match="orthonormal"):
        buffer.add(2.0, sheared)


def test_a_scan_before_the_first_pose_is_not_given_a_pose_a_whole_interval_later():
    # Odometry at 1 Hz from t = 7 s (the samples before lost): the scan at 6 s was taken ~2 m
    # from where the sample at 7 s puts it, and must not become a reference there.
    buffer = PoseBuffer(max_gap_s=1.0)
    for stamp in (7.0, 8.0, 9.0):
        buffer.add(stamp, pose_at(2.0 * stamp))
    assert buffer.lookup(6.0)[0] == "none"
    status, pose = buffer.lookup(6.9)
    assert status == "ok" and pose[0, 3] == pytest.approx(14.0)


def test_a_pose_jump_restarts_the_buffer():
    buffer = PoseBuffer(max_gap_s=1.0, max_speed_mps=30.0)
    buffer.add(0.0, pose_at(0.0))
    buffer.add(0.1, pose_at(1.0))
    buffer.add(0.2, pose_at(500.0))                       # 5 km/s: a relocalisation jump
    assert buffer.jumps == 1 and len(buffer) == 1
    assert buffer.lookup(0.15, final=True)[0] == "none"   # never interpolated across the jump


def test_synchroniser_pairs_in_order_and_counts_drops():
    buffer = PoseBuffer(max_gap_s=1.0)
    extrinsic = pose_at(0.5)
    synchroniser = ScanPoseSynchroniser(buffer, extrinsic, max_pending=3)
    points = np.zeros((1, 3), np.float32)
    for index, stamp in enumerate([0.2, 0.4, 0.6]):
        synchroniser.add_scan(index, stamp, points, extra=f"scan{index}")
    assert synchroniser.ready() == []                      # no pose yet: all wait
    buffer.add(0.0, pose_at(0.0))
    buffer.add(0.5, pose_at(1.0))
    paired = synchroniser.ready()
    assert [p.index for p in paired] == [0, 1] and paired[1].extra == "scan1"
    assert paired[0].pose[0, 3] == pytest.approx(0.4 + 0.5)   # interpolated, then extrinsic
    for index in range(3, 7):
        synchroniser.add_scan(index, 0.7 + index, points)
    assert synchroniser.dropped_without_pose == 2 and synchroniser.pending == 3  # oldest go
    assert synchroniser.ready(final=True) == []
    assert synchroniser.dropped_without_pose == 5


def test_map_builder_keeps_one_reference_per_spacing_and_survives_a_failed_save(world, tmp_path):
    rng = np.random.default_rng(1)
    builder = MapBuilder(CONFIG, tmp_path / "m.mfmap")
    kept = []
    for index, x in enumerate(np.arange(0.0, 10.0, 0.5)):
        points, pose = scan_world(world, x, 0.0, 0.0, rng)
        kept.append(builder.offer(PairedScan(index, float(index), points, pose)))
    assert [k is not None for k in kept].count(True) == 5   # x = 0, 2, 4, 6, 8
    assert builder.save() == 5 and builder.unsaved == 0
    points, pose = scan_world(world, 20.0, 0.0, 0.0, rng)
    builder.offer(PairedScan(99, 99.0, points, pose))
    (tmp_path / "a-file").write_text("")
    builder.map_path = tmp_path / "a-file" / "m.mfmap"          # its folder cannot exist
    with pytest.raises(OSError):
        builder.save()
    assert builder.unsaved == 1 and len(builder.map) == 6
    assert len(ReferenceMap.load(tmp_path / "m.mfmap")) == 5


def test_a_scan_the_map_builder_refuses_is_noted_and_saved_with_the_map(world, tmp_path):
    """A scan with nothing inside the window raises, and is noted in the map's metadata; a note
    alone is saved when the map has references (none is lost at shutdown), not before."""
    rng = np.random.default_rng(2)
    builder = MapBuilder(CONFIG, tmp_path / "m.mfmap")
    points, pose = scan_world(world, 0.0, 0.0, 0.0, rng)
    with pytest.raises(InvalidCloudError):
        builder.offer(PairedScan(0, 0.0, points + 900.0, pose))
    assert builder.map.metadata[PASSED_OVER_KEY]["count"] == 1 and not builder.needs_save
    assert builder.offer(PairedScan(1, 1.0, points, pose)) == 0    # the next scan instead
    assert builder.save() == 1 and not builder.needs_save
    builder.pass_over(2, 2.0, "frame 'lidar' is not the configured sensor_frame_id 'velodyne'")
    assert builder.needs_save and builder.unsaved == 0
    builder.save()
    noted = ReferenceMap.load(tmp_path / "m.mfmap").metadata[PASSED_OVER_KEY]
    assert noted["count"] == 2 and [scan["scan"] for scan in noted["scans"]] == [0, 2]
    assert "sensor_frame_id" in noted["scans"][1]["why"]


def test_a_map_keeps_the_clouds_its_verification_needs(world, tmp_path):
    """handheld verifies by ICP against the reference's cloud: its maps keep clouds unasked,
    and a relocalising localiser then takes them (it refuses a map without clouds)."""
    from mf_lpr_ros.datasets import open_source
    from mf_lpr_ros.pipeline.mapping import build_map
    from mf_lpr_ros.sim.synthetic import write_kitti_sequence

    rng = np.random.default_rng(4)
    builders = {name: MapBuilder(preset(name), None) for name in ("handheld", "kitti")}
    for index, x in enumerate(np.arange(0.0, 4.0, 1.0)):
        points, pose = scan_world(world, x, 0.0, 0.0, rng)
        for builder in builders.values():
            builder.offer(PairedScan(index, float(index), points, pose))
    assert builders["handheld"].map.has_clouds and not builders["kitti"].map.has_clouds
    Localiser(builders["handheld"].map, preset("handheld"))
    verifying = dataclasses.replace(preset("kitti"), search=preset("handheld").search)
    with pytest.raises(ValueError, match="keeps reference clouds"):
        Localiser(builders["kitti"].map, verifying)
    write_kitti_sequence(tmp_path / "seq", world, route(6), seed=5)
    sequence = open_source(tmp_path / "seq")
    assert build_map(sequence, preset("handheld"), progress=False).has_clouds
    assert not build_map(sequence, preset("kitti"), progress=False).has_clouds
    assert build_map(sequence, preset("kitti"), keep_clouds=True, progress=False).has_clouds


def _loop_closure_run(world, trajectory: np.ndarray, revisited: int, extra_reference=None):
    """A loop_closure localiser (references 10 s old or more) fed the trajectory and then its
    first `revisited` places again, each scan added as a reference after its search;
    extra_reference(index, points, pose, rng) may return one more PairedScan to add after it.
    Returns the results and whether each was accepted when it came."""
    rng = np.random.default_rng(5)
    localiser = Localiser(ReferenceMap(CONFIG.descriptor), CONFIG, mode="loop_closure",
                          exclude_recent_s=10.0)
    results, accepted_on_arrival = [], []
    for index, (x, y, yaw) in enumerate(np.vstack([trajectory, trajectory[:revisited]])):
        points, pose = scan_world(world, x, y, yaw, rng)
        results.append(localiser.localise(float(index), points, pose))
        accepted_on_arrival.append(results[-1].accepted)
        localiser.add_reference(PairedScan(index, float(index), points, pose))
        extra = extra_reference(index, points, pose, rng) if extra_reference else None
        if extra is not None:
            localiser.add_reference(extra)
    return results, accepted_on_arrival


def test_loop_closure_localiser_only_searches_old_enough_references(world):
    trajectory = route(20)
    results, accepted_on_arrival = _loop_closure_run(world, trajectory, 3)
    assert results[0].match is None and results[0].reason == "no reference to search yet"
    assert all(r.references_searched == max(0, i - 10 + 1) for i, r in enumerate(results))
    # The revisit's first two matches are right but wait for odometry support (two agreeing
    # earlier matches); the third has it, and its agreement confirms the first two.
    for index in (20, 21, 22):
        revisit = results[index]
        assert revisit.match.reference_index == index - 20
        assert np.hypot(*(revisit.match.pose[:2] - trajectory[index - 20][:2])) < 0.5
        assert revisit.support == index - 20
    assert accepted_on_arrival[20:] == [False, False, True]
    assert results[22].confirms == [results[20], results[21]]
    assert all(r.accepted and "confirmed by later" in r.reason for r in results[20:22])
    assert not any(r.confirms for r in results[:22])


def test_a_revisit_that_starts_at_a_look_alike_place_is_published_once_a_closure_vouches(world):
    """The loop's first place is stored twice, the second time 85 m away with 5 % of its points
    gone: the revisit's first match there is right but not distinct. It waits, and is
    published late, when the revisit's next matches confirm a closure that agrees with it. The
    scan before it, which matched the look-alike copy, is never published."""
    def look_alike_of_the_first_place(index, points, pose, rng):
        if index != 0:
            return None
        elsewhere = pose.copy()
        elsewhere[:2, 3] += [60.0, 60.0]
        return PairedScan(index, 0.5, points[rng.random(len(points)) > 0.05], elsewhere)

    results, accepted_on_arrival = _loop_closure_run(world, route(40), 5,
                                                     look_alike_of_the_first_place)
    first = results[40]
    assert first.match.reference_index == 0 and first.match.distinctiveness < 0.15
    assert not accepted_on_arrival[40] and first.accepted and first.reason == VOUCHED
    assert any(first in later.confirms for later in results[41:])
    look_alike = results[39]
    assert look_alike.match.reference_index == 1 and not look_alike.accepted
    assert not any(look_alike in later.confirms for later in results)


@pytest.mark.parametrize("retry, revisit_check, answer", [
    ("revisits", False, "retried"), ("requests", False, "weak"),
    ("requests", True, "predicted")])
def test_a_stream_searches_again_where_a_weak_match_contradicts_its_revisit(
        world, retry, revisit_check, answer):
    """The revisit's first three matches confirm a closure; then the candidate stage leaves
    the true place out (three candidates, all over 40 m away). Under "revisits"
    the weak match, which the confirmed closure carried along the odometry contradicts, is
    searched again over the wider list and the true place found; a stream under "requests"
    keeps the weak match, unless the revisit check aligns the scan where the revisit puts
    it: then that place is reported, and published on the closure's vouch."""
    config = dataclasses.replace(CONFIG, search=dataclasses.replace(
        CONFIG.search, prefilter_top_k=3, prefilter_retry_top_k=64, prefilter_expand_m=0.0,
        prefilter_retry=retry, revisit_check=revisit_check))
    localiser = Localiser(ReferenceMap(config.descriptor), config, mode="loop_closure",
                          exclude_recent_s=10.0)
    ranking = localiser.index.prefilter.top
    current = [0]

    def top(image, k, stop=None):
        place = current[0] - 20
        if k > 3 or place < 0:
            return ranking(image, k, stop)
        return np.array([place, 10, 11] if place < 3 else [10, 11, 12])

    localiser.index.prefilter.top = top
    rng = np.random.default_rng(5)
    trajectory = route(20)
    results = []
    for index, (x, y, yaw) in enumerate(np.vstack([trajectory, trajectory[:6]])):
        current[0] = index
        points, pose = scan_world(world, x, y, yaw, rng)
        results.append(localiser.localise(float(index), points, pose))
        localiser.add_reference(PairedScan(index, float(index), points, pose))
    assert all(r.accepted and r.match.reference_index == i for i, r in enumerate(results[20:23]))
    for index in (23, 24, 25):
        match = results[index].match
        if answer == "weak":
            assert match.reference_index == 10 and not results[index].accepted
            continue
        assert match.reference_index == index - 20
        assert np.hypot(*(match.pose[:2] - trajectory[index - 20][:2])) < 0.5
        assert match.revisit_predicted == (answer == "predicted")
        if answer == "predicted":
            assert results[index].accepted and results[index].reason == VOUCHED_WHERE_PREDICTED


def test_localiser_refuses_a_map_with_other_parameters(world):
    other = ReferenceMap(preset("default").descriptor)
    with pytest.raises(MapParameterMismatch, match="voxel_size"):
        Localiser(other, CONFIG)
    with pytest.raises(ValueError, match="mode"):
        Localiser(ReferenceMap(CONFIG.descriptor), CONFIG, mode="slam")


def test_relocalised_pose_removes_the_extrinsic():
    from mf_lpr_ros.core.search import MatchResult

    match = MatchResult(0, 1.0, 1.0, np.zeros(2), 0.0, np.array([10.0, 5.0, math.pi / 2]),
                        np.eye(3), np.eye(3), np.array([0]))
    base_T_sensor = pose_at(1.0)                           # sensor 1 m ahead of the base
    world_T_base = relocalised_pose(match, pose_at(0.0), base_T_sensor)
    assert world_T_base[:2, 3] == pytest.approx([10.0, 4.0])   # facing +y: base is 1 m behind


def _tilted(points: np.ndarray, pose: np.ndarray, roll_deg: float, pitch_deg: float
            ) -> tuple[np.ndarray, np.ndarray]:
    """The same scan from a sensor rolled and pitched in place: its points and its pose."""
    tilt = euler_pose(np.zeros(3), np.radians([roll_deg, pitch_deg, 0.0]))[:3, :3]
    tilted_pose = pose.copy()
    tilted_pose[:3, :3] = pose[:3, :3] @ tilt
    return (points @ tilt).astype(np.float32), tilted_pose


def test_a_levelling_map_levels_scans_by_their_pose_and_describes_one_without_as_held(world):
    """A handheld sensor's map (descriptor.level): a tilted scan with its pose is levelled and
    found; without a pose it is still searched, described as the sensor held it, and said so
    (a node without pose_source runs so instead of refusing to start)."""
    base = preset("default")
    config = dataclasses.replace(base, descriptor=dataclasses.replace(base.descriptor,
                                                                      level=True))
    rng = np.random.default_rng(1)
    builder = MapBuilder(config, None)
    for index, (x, y, yaw) in enumerate(route(120)):
        points, pose = scan_world(world, x, y, yaw, rng)
        builder.offer(PairedScan(index, 10.0 + index, *_tilted(points, pose,
                                                               *rng.uniform(-12.0, 12.0, 2))))
    localiser = Localiser(builder.map, config)
    x, y, yaw = route(120, lateral_offset_m=1.0)[37]
    points, pose = _tilted(*scan_world(world, x, y, yaw, np.random.default_rng(3)), 14.0, -10.0)
    levelled = localiser.localise(500.0, points, pose)
    assert levelled.described_from == "single scan"
    assert planar_error(levelled.match.pose, planar(pose))[0] < 1.0
    held = localiser.localise(501.0, points, None)
    assert held.described_from == "single scan" + UNLEVELLED
    assert held.match.confidence < levelled.match.confidence - 0.05
