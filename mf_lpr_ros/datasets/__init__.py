"""Dataset loaders, one per layout and file, behind the Sequence interface.

Each loader declares the layout it reads and how it recognises it (Sequence.recognises) and is
registered with @register_loader; open_source asks them in priority order. A new loader is a
new module here with a registered Sequence subclass, imported below.
"""

from __future__ import annotations

from pathlib import Path

from mf_lpr_ros.datasets.base import LOADERS, Scan, Sequence, register_loader
from mf_lpr_ros.datasets.bev_png import BevPngSequence
from mf_lpr_ros.datasets.kitti import KittiSequence
from mf_lpr_ros.datasets.mulran import MulranSequence
from mf_lpr_ros.datasets.nclt import NcltSequence
from mf_lpr_ros.datasets.oxford import OxfordRadarSequence
from mf_lpr_ros.datasets.point_folder import PointFolderSequence
from mf_lpr_ros.datasets.rosbag import RosbagSequence
from mf_lpr_ros.datasets.wildplaces import WildPlacesSequence
from mf_lpr_ros.errors import DatasetError

__all__ = ["Scan", "Sequence", "open_source", "register_loader", "LOADERS", "KittiSequence",
           "PointFolderSequence", "BevPngSequence", "RosbagSequence", "NcltSequence",
           "MulranSequence", "OxfordRadarSequence", "WildPlacesSequence"]


def open_source(path: str | Path, cloud_topic: str | None = None,
                pose_topic: str | None = None) -> Sequence:
    """The Sequence for a dataset folder or bag, by the first registered loader that
    recognises its layout."""
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"{path}: no such file or folder")
    for loader in LOADERS:
        if loader.recognises(path):
            return loader.from_source(path, cloud_topic, pose_topic)
    raise DatasetError(f"{path}: unknown dataset layout. Expected "
                       + ", ".join(loader.layout for loader in LOADERS[:-1])
                       + f" or {LOADERS[-1].layout}")
