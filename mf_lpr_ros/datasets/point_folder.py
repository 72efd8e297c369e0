"""A folder of PCD or PLY scans (in the folder, or in pcd/ or ply/) with TUM or KITTI poses.

File names are times (e.g. 100.2993.pcd) or frame numbers (e.g. 000003.ply); scans are ordered
by that number, never by the directory listing. Poses come from poses_tum.txt (first column keys
each pose to a scan's name) or poses.txt (KITTI, one line per scan in that order).
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np

from mf_lpr_ros.datasets.base import (
    Scan,
    Sequence,
    nearest_keys,
    read_kitti_poses,
    read_tum_poses,
    register_loader,
)
from mf_lpr_ros.errors import DatasetError
from mf_lpr_ros.io.pcd import read_pcd
from mf_lpr_ros.io.ply import read_ply

_KEY_TOLERANCE = 1e-3
SUFFIXES = (".pcd", ".ply")


def point_folder(root: Path) -> Path | None:
    """The folder holding a point-cloud folder's scans, or None if root is not one."""
    for folder in (root / "pcd", root / "ply", root):
        if folder.is_dir() and any(p.suffix in SUFFIXES for p in folder.iterdir()):
            return folder
    return None


@register_loader
class PointFolderSequence(Sequence):
    layout = ("a PCD/PLY folder (*.pcd, *.ply, or in pcd/ or ply/, with poses_tum.txt or KITTI "
              "poses.txt)")
    notes = ("PCD ascii, binary and binary_compressed (LZF, `python-neo-lzf`); PLY ascii and "
             "binary, either endianness")
    priority = 90

    @classmethod
    def recognises(cls, path: Path) -> bool:
        return path.is_dir() and point_folder(path) is not None

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        self.name = self.root.name
        folder = point_folder(self.root)
        if folder is None:
            raise DatasetError(f"{self.root}: no .pcd or .ply files")
        files = [p for p in folder.iterdir() if p.suffix in SUFFIXES]
        try:
            keys = np.array([float(p.stem) for p in files])
        except ValueError as error:
            raise DatasetError(f"{folder}: scan file names must be times or frame numbers") \
                from error
        order = np.argsort(keys, kind="stable")
        self._files = [files[i] for i in order]
        keys = keys[order]
        self.stamps = keys
        self.poses = None
        if (self.root / "poses_tum.txt").exists():
            self.poses = self._tum_poses(self.root / "poses_tum.txt", keys)
        elif (self.root / "poses.txt").exists():
            self.poses = read_kitti_poses(self.root / "poses.txt", len(keys))

    def _tum_poses(self, path: Path, keys: np.ndarray) -> np.ndarray:
        pose_keys, poses = read_tum_poses(path)
        order = np.argsort(pose_keys, kind="stable")
        pose_keys, poses = pose_keys[order], poses[order]
        nearest, gap = nearest_keys(pose_keys, keys)
        unmatched = gap > _KEY_TOLERANCE
        if unmatched.any():
            raise DatasetError(f"{path}: no pose for {int(unmatched.sum())} scan(s), e.g. "
                               f"{self._files[int(np.argmax(unmatched))].name}")
        return poses[nearest]

    def _read(self, indices: np.ndarray) -> Iterator[Scan]:
        for index in indices:
            path = self._files[index]
            yield self._scan(index, lambda: {
                "points": read_pcd(path) if path.suffix == ".pcd" else read_ply(path)})
