"""Dataset loaders, one per layout, behind the Sequence interface; open_source auto-detects."""

from __future__ import annotations

from pathlib import Path

from mf_lpr_ros.errors import DatasetError
from mf_lpr_ros.datasets.base import Scan, Sequence
from mf_lpr_ros.datasets.bev_png import BevPngSequence
from mf_lpr_ros.datasets.kitti import KittiSequence
from mf_lpr_ros.datasets.mulran import MulranSequence
from mf_lpr_ros.datasets.nclt import NcltSequence
from mf_lpr_ros.datasets.oxford import OxfordRadarSequence
from mf_lpr_ros.datasets.point_folder import PointFolderSequence, point_folder
from mf_lpr_ros.datasets.rosbag import RosbagSequence
from mf_lpr_ros.datasets.wildplaces import CLOUD_FOLDERS, WildPlacesSequence

BAG_SUFFIXES = (".bag", ".db3", ".mcap")

__all__ = ["DatasetError", "Scan", "Sequence", "open_source", "KittiSequence",
           "PointFolderSequence", "BevPngSequence", "RosbagSequence", "NcltSequence",
           "MulranSequence", "OxfordRadarSequence", "WildPlacesSequence"]


def open_source(path: str | Path, cloud_topic: str | None = None,
                pose_topic: str | None = None) -> Sequence:
    """The Sequence for a dataset folder or bag, recognised by its layout."""
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"{path}: no such file or folder")
    if path.is_file() and path.suffix in BAG_SUFFIXES:
        return RosbagSequence(path, cloud_topic, pose_topic)
    if path.is_dir():
        if (path / "metadata.yaml").exists() or any(path.glob("*.mcap")) or any(path.glob("*.db3")):
            return RosbagSequence(path, cloud_topic, pose_topic)
        if (path / "velodyne").is_dir():
            return KittiSequence(path)
        if (path / "velodyne_sync").is_dir():
            return NcltSequence(path)
        if (path / "Ouster").is_dir():
            return MulranSequence(path)
        if (path / "velodyne_left").is_dir():
            return OxfordRadarSequence(path)
        if any((path / folder).is_dir() for folder in CLOUD_FOLDERS):
            return WildPlacesSequence(path)
        if (path / "imgs").is_dir():
            return BevPngSequence(path)
        if point_folder(path) is not None:
            return PointFolderSequence(path)
    raise DatasetError(
        f"{path}: unknown dataset layout. Expected a KITTI folder (velodyne/*.bin, poses.txt), "
        "an NCLT session (velodyne_sync/*.bin, groundtruth_*.csv), a MulRan sequence "
        "(Ouster/*.bin, global_pose.csv), an Oxford Radar RobotCar session (velodyne_left/, "
        "gps/ins.csv), a Wild-Places sequence (Clouds_downsampled/ or Clouds/, "
        "poses_aligned.csv), a PCD/PLY folder (*.pcd, *.ply, or in pcd/ or ply/, with "
        "poses_tum.txt or KITTI poses.txt), a BEV PNG folder (imgs/*.png, poses.txt) or a ROS "
        "bag (.bag, .db3, .mcap or a ROS 2 bag folder)")
