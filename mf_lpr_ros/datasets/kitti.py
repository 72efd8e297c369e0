"""KITTI odometry layout: velodyne/NNNNNN.bin (float32 x y z intensity), poses.txt, times.txt."""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np

from mf_lpr_ros.datasets.base import (
    Scan,
    Sequence,
    read_kitti_poses,
    read_xyzi_bin,
    register_loader,
)
from mf_lpr_ros.errors import DatasetError


@register_loader
class KittiSequence(Sequence):
    layout = "a KITTI folder (velodyne/*.bin, poses.txt)"
    notes = "optional `times.txt` (else scans 0.1 s apart); `poses.txt` optional for localising"
    priority = 20

    @classmethod
    def recognises(cls, path: Path) -> bool:
        return path.is_dir() and (path / "velodyne").is_dir()

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        self.name = self.root.name
        files = sorted((self.root / "velodyne").glob("*.bin"), key=lambda p: _frame_number(p))
        if not files:
            raise DatasetError(f"{self.root}: no velodyne/*.bin scans")
        times_file = self.root / "times.txt"
        if times_file.exists():
            stamps = np.loadtxt(times_file, ndmin=1, dtype=np.float64)
            if len(stamps) != len(files):
                raise DatasetError(f"{times_file}: {len(stamps)} times for {len(files)} scans")
        else:
            stamps = np.arange(len(files)) * 0.1
        poses_file = self.root / "poses.txt"
        poses = read_kitti_poses(poses_file, len(files)) if poses_file.exists() else None
        order = np.argsort(stamps, kind="stable")
        self._files = [files[i] for i in order]
        self.stamps = stamps[order]
        self.poses = None if poses is None else poses[order]

    def _read(self, indices: np.ndarray) -> Iterator[Scan]:
        for index in indices:
            yield self._scan(index, lambda: {"points": read_xyzi_bin(self._files[index])})


def _frame_number(path: Path) -> float:
    try:
        return float(path.stem)
    except ValueError as error:
        raise DatasetError(f"{path}: scan file names must be frame numbers") from error
