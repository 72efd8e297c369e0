import numpy as np
import pytest

from mf_lpr_ros.datasets import (BevPngSequence, DatasetError, KittiSequence, PcdFolderSequence,
                                 RosbagSequence, open_source)
from mf_lpr_ros.datasets.pcd import read_pcd
from mf_lpr_ros.pose import interpolate_poses, pose_matrix, quaternion_from_yaw


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
    with pytest.raises(DatasetError, match="not supported"):
        read_pcd(tmp_path / "d.pcd")


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
                                             ("hku_mb_livox", PcdFolderSequence, 457),
                                             ("kitti07_keyframes", PcdFolderSequence, 5),
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
    from mf_lpr_ros.map_store import ReferenceMap
    from mf_lpr_ros.pipeline import describe_scan
    from mf_lpr_ros.pose import planar, wrap_angle
    from mf_lpr_ros.search import MatchedFilterIndex

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
