"""MulRan sequence: Ouster/<ns>.bin (float32 x, y, z, intensity) and global_pose.csv.

global_pose.csv rows are a nanosecond stamp and the base's 3x4 pose, row-major, at the
ground truth's own rate; poses are interpolated at each scan's stamp and composed with the
base-to-Ouster extrinsic.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np

from mf_lpr_ros.core.pose import euler_pose
from mf_lpr_ros.datasets.base import (
    Scan,
    Sequence,
    numbered_files,
    poses_at_stamps,
    read_xyzi_bin,
    register_loader,
)
from mf_lpr_ros.errors import DatasetError

# base_T_ouster from the MulRan calibration (x, y, z m; roll, pitch, yaw deg).
BASE_T_OUSTER = (1.7042, -0.021, 1.8047, 0.0001, 0.0003, 179.6654)
MAX_POSE_GAP_S = 1.0


@register_loader
class MulranSequence(Sequence):
    layout = "a MulRan sequence (Ouster/*.bin, global_pose.csv)"
    notes = ("Ouster extrinsic, poses interpolated")
    priority = 40

    @classmethod
    def recognises(cls, path: Path) -> bool:
        return path.is_dir() and (path / "Ouster").is_dir()

    def __init__(self, root: str | Path,
                 base_t_ouster: tuple[float, ...] = BASE_T_OUSTER) -> None:
        self.root = Path(root)
        self.name = self.root.name
        self._files, self.stamps = numbered_files(self.root / "Ouster", "*.bin", 1e9)
        path = self.root / "global_pose.csv"
        self.poses = None
        if path.exists():
            try:
                values = np.loadtxt(path, delimiter=",", dtype=np.float64, ndmin=2)
            except (OSError, ValueError) as error:
                raise DatasetError(f"cannot read {path}: {error}") from error
            if values.shape[1] != 13:
                raise DatasetError(f"{path}: expected 13 columns (stamp + 3x4 pose), "
                                   f"got {values.shape[1]}")
            base = np.tile(np.eye(4), (len(values), 1, 1))
            base[:, :3, :4] = values[:, 1:].reshape(-1, 3, 4)
            extrinsic = euler_pose(np.array(base_t_ouster[:3]),
                                   np.radians(np.array(base_t_ouster[3:])))
            self.poses = poses_at_stamps(values[:, 0] / 1e9, base @ extrinsic, self.stamps,
                                         MAX_POSE_GAP_S)

    def _read(self, indices: np.ndarray) -> Iterator[Scan]:
        for index in indices:
            yield self._scan(index, lambda: {"points": read_xyzi_bin(self._files[index])})
