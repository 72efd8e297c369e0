import numpy as np
import pytest

from mf_lpr_ros.config import preset
from mf_lpr_ros.core.pose import interpolate_poses, pose_matrix, quaternion_from_yaw
from mf_lpr_ros.datasets import (
    BevPngSequence,
    KittiSequence,
    PointFolderSequence,
    RosbagSequence,
    open_source,
)
from mf_lpr_ros.errors import DatasetError, InvalidCloudError
from mf_lpr_ros.io.pcd import read_pcd
from mf_lpr_ros.pipeline.mapping import describe_scan


def write_kitti(folder, n=3, times=None):
    (folder / "velodyne").mkdir(parents=True)
    for i in range(n):
        np.full((5, 4), i, dtype="<f4").tofile(folder / "velodyne" / f"{i:06d}.bin")
    poses = np.tile(np.eye(4)[:3].ravel(), (n, 1))
    poses[:, 3] = np.arange(n)
    np.savetxt(folder / "poses.txt", poses)
    if times is not None:
        np.savetxt(folder / "times.txt", times)


def test_kitti_orders_by_time_not_by_name(tmp_path):
    write_kitti(tmp_path, times=[0.2, 0.0, 0.1])
    sequence = open_source(tmp_path)
    assert isinstance(sequence, KittiSequence)
    np.testing.assert_allclose(sequence.stamps, [0.0, 0.1, 0.2])
    scans = list(sequence.iter_scans())
    assert [s.points[0, 0] for s in scans] == [1.0, 2.0, 0.0]
    assert [s.pose[0, 3] for s in scans] == [1.0, 2.0, 0.0]


def test_kitti_pose_count_mismatch_is_named(tmp_path):
    write_kitti(tmp_path)
    np.savetxt(tmp_path / "poses.txt", np.tile(np.eye(4)[:3].ravel(), (2, 1)))
    with pytest.raises(DatasetError, match="2 poses for 3 scans"):
        open_source(tmp_path)


def test_unknown_layout_and_missing_path(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(DatasetError, match="unknown dataset layout"):
        open_source(tmp_path)
    with pytest.raises(DatasetError, match="no such file"):
        open_source(tmp_path / "absent")


def test_pcd_ascii_and_binary(tmp_path):
    header = ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\n"
              "COUNT 1 1 1 1\nWIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA {}\n")
    points = np.array([[1, 2, 3, 9], [4, 5, 6, 9]], dtype="<f4")
    (tmp_path / "a.pcd").write_bytes(header.format("binary").encode() + points.tobytes())
    (tmp_path / "b.pcd").write_text(header.format("ascii") + "1 2 3 9\n4 5 6 9\n")
    np.testing.assert_allclose(read_pcd(tmp_path / "a.pcd"), points[:, :3])
    np.testing.assert_allclose(read_pcd(tmp_path / "b.pcd"), points[:, :3])
    (tmp_path / "c.pcd").write_bytes(header.format("binary").encode() + points.tobytes()[:-3])
    with pytest.raises(DatasetError, match="truncated"):
        read_pcd(tmp_path / "c.pcd")
    (tmp_path / "d.pcd").write_bytes(header.format("binary_compressed").encode())
    with pytest.raises(DatasetError, match="no sizes after DATA"):
        read_pcd(tmp_path / "d.pcd")
    (tmp_path / "e.pcd").write_bytes(header.format("lzma").encode())
    with pytest.raises(DatasetError, match="encoding 'lzma' is not one of"):
        read_pcd(tmp_path / "e.pcd")


def test_pose_interpolation_and_gaps():
    stamps = np.array([0.0, 1.0, 5.0])
    poses = pose_matrix(np.array([[0, 0, 0], [2, 0, 0], [2, 8, 0]], dtype=float),
                        np.stack([quaternion_from_yaw(0.0), quaternion_from_yaw(np.pi / 2),
                                  quaternion_from_yaw(np.pi / 2)]))
    result, valid = interpolate_poses(stamps, poses, np.array([0.5, 3.0, 5.0, 9.0]), max_gap_s=1.5)
    np.testing.assert_array_equal(valid, [True, False, True, False])
    np.testing.assert_allclose(result[0, :3, 3], [1, 0, 0])
    np.testing.assert_allclose(np.arctan2(result[0, 1, 0], result[0, 0, 0]), np.pi / 4)


@pytest.mark.parametrize("name,kind,count", [("balm_realworld", KittiSequence, 177),
                                             ("balm_realworld_bag", RosbagSequence, 177),
                                             ("hku_mb_livox", PointFolderSequence, 457),
                                             ("kitti07_keyframes", PointFolderSequence, 5),
                                             ("kitti_bev/00", BevPngSequence, 4541)])
def test_real_layouts_are_recognised(data_dir, name, kind, count):
    sequence = open_source(data_dir / name)
    assert isinstance(sequence, kind) and len(sequence) == count
    assert np.all(np.diff(sequence.stamps) >= 0)
    assert np.isfinite(sequence.poses).all()
    scan = next(sequence.iter_scans([len(sequence) // 2]))
    assert (scan.points is not None and len(scan.points) > 1000) or scan.density is not None


def test_real_bag_matches_kitti_folder(data_dir):
    bag = open_source(data_dir / "balm_realworld_bag")
    folder = open_source(data_dir / "balm_realworld")
    np.testing.assert_allclose(bag.poses, folder.poses, atol=1e-5)
    np.testing.assert_allclose(bag.stamps, folder.stamps, atol=1e-6)
    assert bag.cloud_topic == "/points" and bag.pose_topic == "/odom" and bag.frame_id == "velodyne"


def test_real_bev_axes_agree_with_poses(data_dir):
    """Frames 100 and 4529 of KITTI 00 are 0.14 m apart with ~12.6 deg of yaw difference."""
    from mf_lpr_ros.config import preset
    from mf_lpr_ros.core.map_store import ReferenceMap
    from mf_lpr_ros.core.pose import planar, wrap_angle
    from mf_lpr_ros.core.search import MatchedFilterIndex
    from mf_lpr_ros.pipeline.mapping import describe_scan

    config = preset("kitti")
    scans = {s.index: s for s in open_source(data_dir / "kitti_bev/00").iter_scans([100, 4529])}
    reference_map = ReferenceMap(config.descriptor)
    reference_map.append(describe_scan(scans[100], config.descriptor, reference=True),
                         scans[100].pose, 0.0)
    result = MatchedFilterIndex(reference_map, config.search).query(
        describe_scan(scans[4529], config.descriptor, reference=False))
    truth = planar(scans[4529].pose)
    assert np.hypot(*(result.pose[:2] - truth[:2])) < 0.4
    assert abs(np.degrees(wrap_angle(result.pose[2] - truth[2]))) < 1.0


def test_nclt_records_ground_truth_and_frames(tmp_path):
    from mf_lpr_ros.core.pose import euler_pose, planar
    from mf_lpr_ros.datasets import NcltSequence

    (tmp_path / "velodyne_sync").mkdir()
    # Names are microseconds; listed out of order on purpose.
    utimes = [1_000_300_000, 1_000_100_000, 1_000_200_000]
    for k, utime in enumerate(utimes):
        xyz = np.array([[10.0 + k, 2.0, -1.5]])        # z-down frame: 1.5 m above the sensor
        scaled = np.round((xyz + 100.0) / 0.005).astype("<u2")
        record = np.zeros(1, dtype=[("xyz", "<u2", 3), ("i", "u1"), ("l", "u1")])
        record["xyz"] = scaled
        record.tofile(tmp_path / "velodyne_sync" / f"{utime}.bin")
    # Body moving north (x) at 10 m/s, heading north; a NaN row is a gap and is skipped.
    rows = [[1_000_000_000 + 50_000 * i, 0.5 * i, 0.0, 0.0, 0.0, 0.0, 0.0] for i in range(9)]
    rows.insert(3, [1_000_120_000] + [float("nan")] * 6)
    np.savetxt(tmp_path / "groundtruth_2012-01-08.csv", rows, delimiter=",")
    sequence = open_source(tmp_path)
    assert isinstance(sequence, NcltSequence)
    np.testing.assert_allclose(sequence.stamps, [1000.1, 1000.2, 1000.3])
    scans = list(sequence.iter_scans())
    # Time order, z up, y mirrored with it (a right-handed z-up frame).
    np.testing.assert_allclose(scans[0].points, [[11.0, -2.0, 1.5]], atol=0.003)
    assert [s.points[0, 0] for s in scans] == pytest.approx([11.0, 12.0, 10.0], abs=0.003)
    # Pose of the Velodyne: body interpolated at the stamp, times the extrinsic, made z-up.
    extrinsic = euler_pose(np.array([0.002, -0.004, -0.957]),
                           np.radians([0.807, 0.166, -90.703]))
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    body = np.eye(4)
    body[0, 3] = 1.0                                   # 0.1 s after the first row
    np.testing.assert_allclose(sequence.poses[0], flip @ body @ extrinsic @ flip, atol=1e-9)
    assert planar(sequence.poses[0])[2] == pytest.approx(np.radians(90.703), abs=1e-3)


def test_nclt_bad_record_size_is_named(tmp_path):
    """A file that cannot be read is a scan naming its problem (the tools pass over it by
    name); the files after it are read on."""
    (tmp_path / "velodyne_sync").mkdir()
    (tmp_path / "velodyne_sync" / "100.bin").write_bytes(b"\0" * 12)
    (tmp_path / "velodyne_sync" / "200.bin").write_bytes(b"\0" * 16)
    bad, good = open_source(tmp_path).iter_scans()
    assert bad.points is None and "100.bin: size is not a multiple of 8 bytes" in bad.problem
    assert good.problem == "" and good.points.shape == (2, 3)
    with pytest.raises(InvalidCloudError, match=r"^scan 0 \(stamp .*100.bin: size is not"):
        describe_scan(bad, preset("default").descriptor, reference=True)


def test_mulran_interpolates_ground_truth_at_scan_stamps(tmp_path):
    from mf_lpr_ros.datasets import MulranSequence

    (tmp_path / "Ouster").mkdir()
    for stamp_ns in (2_500_000_000, 1_500_000_000):
        np.array([[1, 2, 3, 7]], dtype="<f4").tofile(tmp_path / "Ouster" / f"{stamp_ns}.bin")
    rows = []
    for i in range(4):                                 # 1 s apart, 4 m apart along x
        pose = np.eye(4)[:3]
        pose[0, 3] = 4.0 * i
        rows.append([1_000_000_000 * (i + 1)] + list(pose.ravel()))
    np.savetxt(tmp_path / "global_pose.csv", rows, delimiter=",")
    sequence = open_source(tmp_path)
    assert isinstance(sequence, MulranSequence)
    np.testing.assert_allclose(sequence.stamps, [1.5, 2.5])
    # Base at 2 m and 6 m; the Ouster sits 1.7042 m ahead, turned ~180 deg.
    assert sequence.poses[0, 0, 3] == pytest.approx(2.0 + 1.7042, abs=1e-3)
    assert sequence.poses[1, 0, 3] == pytest.approx(6.0 + 1.7042, abs=1e-3)
    assert sequence.poses[0, 0, 0] == pytest.approx(-1.0, abs=1e-3)
    assert next(sequence.iter_scans([0])).points.tolist() == [[1.0, 2.0, 3.0]]


def _raw_robotcar_png(path, ranges_m, azimuth_deg):
    """A raw RobotCar Velodyne scan: 32 intensity rows, 32 little-endian uint16 ranges as byte
    pairs, the azimuth as a byte pair, 8 rows of packet time."""
    from PIL import Image

    n = len(azimuth_deg)
    image = np.zeros((106, n), dtype=np.uint8)
    ranges = np.round(np.asarray(ranges_m) / 0.002).astype("<u2")          # (32, n)
    image[32:96:2], image[33:96:2] = ranges & 0xFF, ranges >> 8
    azimuth = np.round(np.asarray(azimuth_deg) * 100).astype("<u2")
    image[96], image[97] = azimuth & 0xFF, azimuth >> 8
    Image.fromarray(image).save(path)


def _write_ins(path, rows):
    header = ("timestamp,ins_status,latitude,longitude,altitude,northing,easting,down,utm_zone,"
              "velocity_north,velocity_east,velocity_down,roll,pitch,yaw")
    lines = [header] + [f"{t},INS_SOLUTION_GOOD,51.7,-1.2,100,{n},{e},{d},30U,0,0,0,0,0,{yaw}"
                        for t, n, e, d, yaw in rows]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


def test_oxford_raw_png_decodes_hdl32e_geometry(tmp_path):
    from mf_lpr_ros.datasets import OxfordRadarSequence

    folder = tmp_path / "2019-01-10-11-46-21" / "velodyne_left"
    folder.mkdir(parents=True)
    ranges = np.zeros((32, 2))
    ranges[8, 0] = 10.0      # the level beam, azimuth 90 deg: straight ahead in the SDK frame
    ranges[0, 1] = 20.0      # the upper-most beam (-0.1862 rad in the z-down frame)
    ranges[31, 0] = 0.5      # under the 1 m minimum: dropped
    _raw_robotcar_png(folder / "1547120000000000.png", ranges, [90.0, 180.0])
    sequence = open_source(folder.parent)
    assert isinstance(sequence, OxfordRadarSequence)
    points = next(sequence.iter_scans()).points
    assert points.shape == (2, 3)
    # Beam by beam, as the SDK orders them. z up: the beam origin is 0.0908 m above the sensor
    # origin and the upward beam rises; azimuth 180 deg is to the right (-y in a z-up frame).
    elevation = 0.1862
    np.testing.assert_allclose(points[0], [0.0, -20 * np.cos(elevation),
                                           20 * np.sin(elevation) + 0.090805], atol=2e-3)
    np.testing.assert_allclose(points[1], [10.0, 0.0, 0.090805], atol=1e-3)


def test_oxford_bin_and_png_agree_and_time_order(tmp_path):
    folder = tmp_path / "session" / "velodyne_left"
    folder.mkdir(parents=True)
    xyz_down = np.array([[5.0, 1.0, 0.5, 7.0], [-3.0, 2.0, -1.0, 7.0]], dtype="<f4").T  # 4 x N
    xyz_down.tofile(folder / "200.bin")
    np.zeros((4, 1), dtype="<f4").tofile(folder / "100.bin")
    sequence = open_source(folder.parent)
    np.testing.assert_allclose(sequence.stamps, [100e-6, 200e-6])
    scans = list(sequence.iter_scans())
    np.testing.assert_allclose(scans[1].points, [[5.0, -1.0, -0.5], [-3.0, -2.0, 1.0]])
    (folder / "bad.bin").write_bytes(b"\0" * 16)
    with pytest.raises(DatasetError, match="integer times"):
        open_source(folder.parent)


def test_oxford_ins_ned_becomes_enu(tmp_path):
    from mf_lpr_ros.core.pose import planar
    from mf_lpr_ros.datasets import OxfordRadarSequence

    session = tmp_path / "s"
    (session / "velodyne_left").mkdir(parents=True)
    for utime in (1_000_000, 1_500_000):
        np.zeros((4, 1), dtype="<f4").tofile(session / "velodyne_left" / f"{utime}.bin")
    # Heading east (NED yaw 90 deg), driving east 2 m/s from northing 5000, easting 600.
    _write_ins(session / "gps" / "ins.csv",
               [(t, 5000.0, 600.0 + 2.0 * (t - 1_000_000) / 1e6, -30.0, np.pi / 2)
                for t in range(900_000, 1_700_000, 100_000)])
    identity = (0.0,) * 6
    sequence = OxfordRadarSequence(session, stereo_t_lidar=identity, stereo_t_ins=identity)
    # ENU: x east, y north, z up; the z-down sensor turned z up keeps x forward (east).
    np.testing.assert_allclose(planar(sequence.poses[1]), [601.0, 5000.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(sequence.poses[1][:3, 3], [601.0, 5000.0, 30.0], atol=1e-9)
    np.testing.assert_allclose(sequence.poses[1][:3, :3], np.eye(3), atol=1e-9)
    # With the SDK's extrinsics the Velodyne faces backwards-ish (yaw -3.1337 from the camera).
    sdk = OxfordRadarSequence(session)
    assert abs(planar(sdk.poses[0])[2]) == pytest.approx(3.1337 - 0.005, abs=0.01)
    (session / "gps" / "ins.csv").write_text("timestamp,northing\n1,2\n")
    with pytest.raises(DatasetError, match="INS columns"):
        OxfordRadarSequence(session)


def test_wildplaces_clouds_poses_and_query_split(tmp_path):
    import pickle

    from mf_lpr_ros.datasets import WildPlacesSequence
    from mf_lpr_ros.datasets.wildplaces import read_query_split

    sequence_dir = tmp_path / "Venman" / "V-03"
    clouds = sequence_dir / "Clouds_downsampled"
    clouds.mkdir(parents=True)
    stamps = ["1623898781.520584106", "1623898780.020584106", "1623898782.999999999"]
    for k, stamp in enumerate(stamps):
        np.array([[k, 0, 0, 1]], dtype="<f4").tofile(clouds / f"{stamp}.bin")
    rows = ["timestamp,x,y,z,qx,qy,qz,qw",
            f"{stamps[0]},1,2,3,0,0,0.7071067811865476,0.7071067811865476",
            f"{stamps[1]},0,0,0,0,0,0,1"]          # no pose for the third cloud
    (sequence_dir / "poses_aligned.csv").write_text("\n".join(rows) + "\n")
    sequence = open_source(sequence_dir)
    assert isinstance(sequence, WildPlacesSequence)
    np.testing.assert_allclose(sequence.stamps, sorted(float(s) for s in stamps))
    assert [s.points[0, 0] for s in sequence.iter_scans()] == [1.0, 0.0, 2.0]
    np.testing.assert_allclose(sequence.poses[1][:3, 3], [1, 2, 3])
    np.testing.assert_allclose(sequence.poses[1][:2, 0], [0, 1], atol=1e-9)  # yaw 90 deg
    assert np.isnan(sequence.poses[2]).all()

    split = [{0: {"query": f"V-03/Clouds_downsampled/{stamps[0]}.pcd", "northing": np.float64(2),
                  "easting": np.float64(1), "pose": np.array([1.0, 2.0], dtype=object),
                  "timestamp": float(stamps[0]), 1: [0, 3]}},
             {}]
    with open(tmp_path / "Venman_evaluation_query.pickle", "wb") as handle:
        pickle.dump(split, handle)
    queries = read_query_split(tmp_path / "Venman_evaluation_query.pickle")
    assert len(queries) == 2 and len(queries[1]) == 0
    np.testing.assert_allclose(queries[0], [float(stamps[0])])

    class Payload:
        def __reduce__(self):
            return (print, ("pickled code ran",))
    with open(tmp_path / "evil.pickle", "wb") as handle:
        pickle.dump([{0: Payload()}], handle)
    with pytest.raises(DatasetError, match="refusing to load builtins.print"):
        read_query_split(tmp_path / "evil.pickle")


def test_ply_folder_with_kitti_poses(tmp_path):
    from mf_lpr_ros.datasets import PointFolderSequence
    from mf_lpr_ros.io.ply import read_ply

    folder = tmp_path / "ply"
    folder.mkdir()
    points = np.array([[1, 2, 3], [4, 5, 6]], dtype="<f4")
    header = ("ply\nformat {}\ncomment written by a test\nelement camera 1\nproperty float a\n"
              "element vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
              "property uchar red\nelement face 0\nproperty list uchar int vertex_indices\n"
              "end_header\n")
    little = np.zeros(2, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1")])
    little["x"], little["y"], little["z"] = points.T
    (folder / "000010.ply").write_bytes(header.format("binary_little_endian 1.0").encode()
                                        + np.float32(9).tobytes() + little.tobytes())
    (folder / "000002.ply").write_bytes(header.format("binary_big_endian 1.0").encode()
                                        + np.float32(9).byteswap().tobytes()
                                        + little.astype(little.dtype.newbyteorder(">")).tobytes())
    (folder / "000005.ply").write_text(header.format("ascii 1.0") + "9\n1 2 3 0\n4 5 6 0\n")
    poses = np.tile(np.eye(4)[:3].ravel(), (3, 1))
    poses[:, 3] = [2, 5, 10]
    np.savetxt(tmp_path / "poses.txt", poses)
    sequence = open_source(tmp_path)
    assert isinstance(sequence, PointFolderSequence)
    np.testing.assert_allclose(sequence.stamps, [2, 5, 10])
    for scan in sequence.iter_scans():
        np.testing.assert_allclose(scan.points, points)
        assert scan.pose[0, 3] == scan.stamp
    (folder / "000011.ply").write_bytes(header.format("binary_little_endian 1.0").encode()
                                        + b"\0" * 8)
    with pytest.raises(DatasetError, match="truncated PLY"):
        read_ply(folder / "000011.ply")
    with pytest.raises(DatasetError, match="4 scans"):
        open_source(tmp_path)


def test_open_source_asks_the_registered_loaders_in_priority_order(tmp_path):
    from mf_lpr_ros.datasets import LOADERS, Sequence, open_source, register_loader

    class MarkerSequence(Sequence):
        layout = "a folder holding MARKER"
        priority = 5

        def __init__(self, path):
            self.name, self.stamps, self.poses = "marker", np.zeros(1), None

        @classmethod
        def recognises(cls, path):
            return (path / "MARKER").exists()

    register_loader(MarkerSequence)
    try:
        (tmp_path / "MARKER").touch()
        (tmp_path / "velodyne").mkdir()        # also a KITTI layout: the higher priority wins
        assert isinstance(open_source(tmp_path), MarkerSequence)
        with pytest.raises(DatasetError) as refused:
            open_source(tmp_path / "velodyne")
        assert "a folder holding MARKER" in str(refused.value)
        assert "a KITTI folder" in str(refused.value) and "a ROS bag" in str(refused.value)
    finally:
        LOADERS.remove(MarkerSequence)
