"""Oxford Radar RobotCar session: velodyne_left/<utime>.png (raw) or <utime>.bin, gps/ins.csv.

The RobotCar SDK's conventions, decoded here without the SDK:
- .bin: float32, four rows (x, y, z, intensity) of N points, row-major.
- .png: 8-bit image of 32 + 64 + 2 + 8 rows: intensities; ranges as little-endian uint16 byte
  pairs (2 mm per unit); azimuths as uint16 (1/100 degree); packet times. Points follow the
  HDL-32E elevation table, ranges under 1 m are invalid, and the beam origin is 0.090805 m above
  the sensor frame's origin.
- The Velodyne frame is z down (x forward, y right): points are turned z up on load (x, -y, -z).
- gps/ins.csv poses are NED (northing, easting, down, roll, pitch, yaw) at microsecond stamps.
  Poses become ENU (easting, northing, up) so they are right-handed and z up like every other
  loader, composed with the SDK's extrinsics: world_T_velodyne = ins @ inv(stereo_T_ins) @
  stereo_T_velodyne. Positions stay absolute UTM so sessions share one frame.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np
from PIL import Image

from mf_lpr_ros.core.pose import euler_pose
from mf_lpr_ros.datasets.base import (
    Scan,
    Sequence,
    numbered_files,
    poses_at_stamps,
    register_loader,
)
from mf_lpr_ros.errors import DatasetError

# x, y, z (m), roll, pitch, yaw (rad) relative to the stereo camera: the SDK's extrinsics/*.txt.
STEREO_T_VELODYNE_LEFT = (-0.60072, -0.34077, -0.26837, -0.0053948, -0.041998, -3.1337)
STEREO_T_INS = (-1.7132, 0.1181, 1.1948, -0.0125, 0.0400, 0.0050)
HDL32E_ELEVATIONS_RAD = np.array([
    -0.1862, -0.1628, -0.1396, -0.1164, -0.0930, -0.0698, -0.0466, -0.0232, 0.0, 0.0232, 0.0466,
    0.0698, 0.0930, 0.1164, 0.1396, 0.1628, 0.1862, 0.2094, 0.2327, 0.2560, 0.2793, 0.3025,
    0.3259, 0.3491, 0.3723, 0.3957, 0.4189, 0.4421, 0.4655, 0.4887, 0.5119, 0.5353])
RANGE_UNIT_M = 0.002
MIN_RANGE_M = 1.0
BEAM_ORIGIN_HEIGHT_M = 0.090805
RAW_ROWS = 32 + 64 + 2 + 8
MAX_POSE_GAP_S = 0.5
ENU_FROM_NED = np.array([[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0],
                         [0.0, 0.0, 0.0, 1.0]])
_Z_UP = np.diag([1.0, -1.0, -1.0, 1.0])
_INS_COLUMNS = ("timestamp", "northing", "easting", "down", "roll", "pitch", "yaw")


@register_loader
class OxfordRadarSequence(Sequence):
    layout = "an Oxford Radar RobotCar session (velodyne_left/, gps/ins.csv)"
    notes = ("raw `<utime>.png` or `.bin` scans; SDK decoding (HDL-32E table, 2 mm ranges, 1 m "
             "minimum); INS NED turned into ENU, SDK extrinsics (or the session's "
             "`extrinsics/*.txt`)")
    priority = 50

    @classmethod
    def recognises(cls, path: Path) -> bool:
        return path.is_dir() and (path / "velodyne_left").is_dir()

    def __init__(self, root: str | Path, lidar: str = "velodyne_left",
                 stereo_t_lidar: tuple[float, ...] | None = None,
                 stereo_t_ins: tuple[float, ...] | None = None) -> None:
        self.root = Path(root)
        self.name = self.root.name
        folder = self.root / lidar
        suffix = "png" if any(folder.glob("*.png")) else "bin"
        self._files, self.stamps = numbered_files(folder, f"*.{suffix}", 1e6)
        stereo_t_lidar = stereo_t_lidar or _extrinsics(self.root, lidar, STEREO_T_VELODYNE_LEFT)
        stereo_t_ins = stereo_t_ins or _extrinsics(self.root, "ins", STEREO_T_INS)
        ins_path = self.root / "gps" / "ins.csv"
        self.poses = None
        if ins_path.exists():
            stamps, ins_poses = read_ins_poses(ins_path)
            ins_t_lidar = np.linalg.solve(_pose(stereo_t_ins), _pose(stereo_t_lidar))
            sensor = ENU_FROM_NED @ ins_poses @ ins_t_lidar @ _Z_UP
            self.poses = poses_at_stamps(stamps, sensor, self.stamps, MAX_POSE_GAP_S)

    def _read(self, indices: np.ndarray) -> Iterator[Scan]:
        for index in indices:
            yield self._scan(index, lambda: {"points": _read_velodyne(self._files[index])})


def _read_velodyne(path: Path) -> np.ndarray:
    """x, y, z (N, 3) of a raw Velodyne scan (.png or .bin), in the package's z-up frame."""
    xyz = read_velodyne_png(path) if path.suffix == ".png" else read_velodyne_bin(path)
    xyz[:, 1:] *= -1.0
    return xyz


def read_velodyne_bin(path: Path) -> np.ndarray:
    """x, y, z (N, 3) in the SDK's z-down Velodyne frame from a .bin scan (4 rows of N)."""
    raw = np.fromfile(path, dtype="<f4")
    if raw.size % 4:
        raise DatasetError(f"{path}: size is not a multiple of 16 bytes (4 rows of float32)")
    return np.ascontiguousarray(raw.reshape(4, -1)[:3].T)


def read_velodyne_png(path: Path) -> np.ndarray:
    """x, y, z (N, 3) in the SDK's z-down Velodyne frame from a raw .png scan."""
    try:
        image = np.asarray(Image.open(path))
    except OSError as error:
        raise DatasetError(f"cannot read raw Velodyne scan {path}: {error}") from error
    if image.dtype != np.uint8 or image.ndim != 2 or image.shape[0] != RAW_ROWS:
        raise DatasetError(f"{path}: a raw RobotCar Velodyne scan is an 8-bit grey image of "
                           f"{RAW_ROWS} rows, got {image.dtype} {image.shape}")
    pairs = image[32:98].astype(np.uint16)
    ranges = (pairs[0:64:2] + (pairs[1:64:2] << 8)) * RANGE_UNIT_M
    azimuth = (pairs[64] + (pairs[65] << 8)) * (2.0 * np.pi / 36000.0)
    elevation = HDL32E_ELEVATIONS_RAD[:, None]
    horizontal = np.cos(elevation) * ranges
    x = np.sin(azimuth) * horizontal
    y = -np.cos(azimuth) * horizontal
    z = np.sin(elevation) * ranges - BEAM_ORIGIN_HEIGHT_M
    valid = ranges > MIN_RANGE_M
    return np.stack([x[valid], y[valid], z[valid]], axis=1).astype(np.float32)


def read_ins_poses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """INS stamps (s) and NED world_T_ins poses (n, 4, 4) from gps/ins.csv, by header names."""
    try:
        with open(path) as handle:
            header = [name.strip() for name in handle.readline().split(",")]
        values = np.genfromtxt(path, delimiter=",", skip_header=1, dtype=np.float64, ndmin=2)
    except (OSError, ValueError) as error:
        raise DatasetError(f"cannot read {path}: {error}") from error
    missing = [name for name in _INS_COLUMNS if name not in header]
    if missing:
        raise DatasetError(f"{path}: INS columns {missing} missing (header: {header})")
    columns = values[:, [header.index(name) for name in _INS_COLUMNS]]
    columns = columns[np.isfinite(columns).all(axis=1)]
    if not len(columns):
        raise DatasetError(f"{path}: no valid INS rows")
    return columns[:, 0] / 1e6, euler_pose(columns[:, 1:4], columns[:, 4:7])


def _pose(xyz_rpy: tuple[float, ...]) -> np.ndarray:
    return euler_pose(np.array(xyz_rpy[:3]), np.array(xyz_rpy[3:]))


def _extrinsics(root: Path, name: str, default: tuple[float, ...]) -> tuple[float, ...]:
    """The SDK's extrinsics/<name>.txt beside or above the session, else the SDK's values."""
    for folder in (root / "extrinsics", root.parent / "extrinsics"):
        path = folder / f"{name}.txt"
        if path.exists():
            values = path.read_text().split()
            if len(values) != 6:
                raise DatasetError(f"{path}: expected 6 numbers (x y z roll pitch yaw)")
            return tuple(float(v) for v in values)
    return default
