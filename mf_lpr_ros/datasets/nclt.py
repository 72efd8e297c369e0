"""NCLT session: velodyne_sync/<utime>.bin and groundtruth_<date>.csv.

Scans are 8-byte records: x, y, z as little-endian uint16 (0.005 m per unit, offset -100 m),
intensity and laser id as uint8. Ground truth rows are utime, x, y, z, roll, pitch, yaw of the
body in a z-down frame (NaN rows are gaps). Everything is turned z-up on load (x, -y, -z, which
keeps the frames right-handed), and poses are the Velodyne's: body pose times the extrinsic.
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
    register_loader,
)
from mf_lpr_ros.errors import DatasetError

# body_T_velodyne from the NCLT development kit (x, y, z m; roll, pitch, yaw deg).
BODY_T_VELODYNE = (0.002, -0.004, -0.957, 0.807, 0.166, -90.703)
_Z_UP = np.diag([1.0, -1.0, -1.0, 1.0])
_RECORD = np.dtype([("xyz", "<u2", 3), ("intensity", "u1"), ("laser", "u1")])
MAX_POSE_GAP_S = 0.5


@register_loader
class NcltSequence(Sequence):
    layout = "an NCLT session (velodyne_sync/*.bin, groundtruth_*.csv)"
    notes = ("uint16 records (0.005 m, -100 m); made z-up, Velodyne extrinsic applied, ground "
             "truth interpolated at scan stamps, gaps dropped")
    priority = 30

    @classmethod
    def recognises(cls, path: Path) -> bool:
        return path.is_dir() and (path / "velodyne_sync").is_dir()

    def __init__(self, root: str | Path, groundtruth: str | Path | None = None,
                 body_t_velodyne: tuple[float, ...] = BODY_T_VELODYNE) -> None:
        self.root = Path(root)
        self.name = self.root.name
        self._files, self.stamps = numbered_files(self.root / "velodyne_sync", "*.bin", 1e6)
        if groundtruth is None:
            candidates = sorted(self.root.glob("groundtruth_*.csv"))
            groundtruth = candidates[0] if candidates else None
        self.poses = None
        if groundtruth is not None:
            values = _read_csv(Path(groundtruth), 7)
            values = values[np.isfinite(values).all(axis=1)]
            body = euler_pose(values[:, 1:4], values[:, 4:7])
            extrinsic = euler_pose(np.array(body_t_velodyne[:3]),
                                   np.radians(np.array(body_t_velodyne[3:])))
            sensor = _Z_UP @ body @ extrinsic @ _Z_UP
            self.poses = poses_at_stamps(values[:, 0] / 1e6, sensor, self.stamps, MAX_POSE_GAP_S)

    def _read(self, indices: np.ndarray) -> Iterator[Scan]:
        for index in indices:
            yield self._scan(index, lambda: {"points": _read_velodyne_sync(self._files[index])})


def _read_velodyne_sync(path: Path) -> np.ndarray:
    """x, y, z (N, 3) of an NCLT velodyne_sync .bin scan, in the package's z-up frame."""
    raw = path.read_bytes()
    if len(raw) % _RECORD.itemsize:
        raise DatasetError(f"{path}: size is not a multiple of 8 bytes (NCLT records)")
    xyz = np.frombuffer(raw, dtype=_RECORD)["xyz"].astype(np.float32) * 0.005 - 100.0
    xyz[:, 1:] *= -1.0
    return xyz


def _read_csv(path: Path, columns: int) -> np.ndarray:
    try:
        values = np.genfromtxt(path, delimiter=",", dtype=np.float64, ndmin=2)
    except (OSError, ValueError) as error:
        raise DatasetError(f"cannot read {path}: {error}") from error
    if values.shape[1] < columns:
        raise DatasetError(f"{path}: expected {columns} columns, got {values.shape[1]}")
    return values[:, :columns]
