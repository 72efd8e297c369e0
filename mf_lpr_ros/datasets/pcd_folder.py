"""A folder of PCD scans (in the folder or in pcd/) with poses_tum.txt.

The TUM file's first column keys each pose to a scan: either the scan's time (file names are
times, e.g. 100.2993.pcd) or its index (file names are frame numbers, e.g. 000003.pcd).
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np

from .base import DatasetError, Scan, Sequence, read_tum_poses
from .pcd import read_pcd

_KEY_TOLERANCE = 1e-3


class PcdFolderSequence(Sequence):
    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        self.name = self.root.name
        folder = self.root / "pcd" if (self.root / "pcd").is_dir() else self.root
        files = list(folder.glob("*.pcd"))
        if not files:
            raise DatasetError(f"{self.root}: no .pcd files")
        try:
            keys = np.array([float(p.stem) for p in files])
        except ValueError as error:
            raise DatasetError(f"{folder}: PCD file names must be times or frame numbers") from error
        order = np.argsort(keys, kind="stable")
        self._files = [files[i] for i in order]
        keys = keys[order]
        self.stamps = keys
        self.poses = None
        poses_file = self.root / "poses_tum.txt"
        if poses_file.exists():
            pose_keys, poses = read_tum_poses(poses_file)
            position = np.searchsorted(pose_keys, keys).clip(0, len(pose_keys) - 1)
            before = (position - 1).clip(0)
            nearest = np.where(np.abs(pose_keys[before] - keys) < np.abs(pose_keys[position] - keys),
                               before, position)
            unmatched = np.abs(pose_keys[nearest] - keys) > _KEY_TOLERANCE
            if unmatched.any():
                raise DatasetError(f"{poses_file}: no pose for {int(unmatched.sum())} scan(s), e.g. "
                                   f"{self._files[int(np.argmax(unmatched))].name}")
            self.poses = poses[nearest]

    def _read(self, indices: np.ndarray) -> Iterator[Scan]:
        for index in indices:
            yield Scan(int(index), float(self.stamps[index]), self.pose(int(index)),
                       points=read_pcd(self._files[index]))
