"""The one interface every dataset loader implements."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, ClassVar, Iterable, Iterator

import numpy as np

from mf_lpr_ros.errors import DatasetError, InvalidCloudError


@dataclass
class Scan:
    """One scan: either points (N, 3+) in the sensor frame or a ready height-density image.

    density is in the package's axis convention (rows = y, columns = x, sensor at the centre
    corner) with density_pixel_m metres per pixel. pose is world_T_sensor (4x4) or None.
    sensor_offset_m: where the sensor truly sits, along x and y, from that centre corner: half a
    pixel for images that centre the sensor on a pixel (BEVPlace's), which no resampling onto
    the package's grid can undo; the search corrects poses for it (MatchedFilterIndex.query).
    problem: why the source gave nothing to read for this scan (an empty or malformed message
    among good ones), with neither points nor density; "" when it gave them. Describing such a
    scan raises InvalidCloudError with it, so the tools pass over it as over any scan with
    nothing to describe.
    """

    index: int
    stamp: float
    pose: np.ndarray | None
    points: np.ndarray | None = None
    density: np.ndarray | None = None
    density_pixel_m: float = 0.0
    sensor_offset_m: float = 0.0
    problem: str = ""


class Sequence:
    """Scans in time order with stamps and (optional) poses, readable in one pass.

    Subclasses set name, stamps (n,), poses ((n, 4, 4) or None) and implement _read(indices),
    yielding Scans for increasing indices. A loader that open_source should find declares its
    layout (one phrase for the error that lists them), what it does beyond reading (notes:
    docs/DATASETS.md is generated from both) and recognises(path), and is registered with
    @register_loader; loaders are tried by ascending priority.
    """

    name: str = ""
    stamps: np.ndarray
    poses: np.ndarray | None
    layout: ClassVar[str] = ""
    notes: ClassVar[str] = ""
    priority: ClassVar[int] = 50

    @classmethod
    def recognises(cls, path: Path) -> bool:
        """Whether path (a file or folder that exists) is in this loader's layout."""
        return False

    @classmethod
    def from_source(cls, path: Path, cloud_topic: str | None = None,
                    pose_topic: str | None = None) -> "Sequence":
        """The sequence at a recognised path (topics matter to bags only)."""
        return cls(path)

    def __len__(self) -> int:
        return len(self.stamps)

    def iter_scans(self, indices: Iterable[int] | None = None) -> Iterator[Scan]:
        """Scans at the given indices (all by default), in increasing index order."""
        wanted = np.arange(len(self)) if indices is None else np.unique(np.asarray(list(indices),
                                                                                   dtype=np.int64))
        if len(wanted) and (wanted[0] < 0 or wanted[-1] >= len(self)):
            raise IndexError(f"scan index out of range for {self.name} ({len(self)} scans)")
        return self._read(wanted)

    def _read(self, indices: np.ndarray) -> Iterator[Scan]:
        raise NotImplementedError

    def _scan(self, index: int, read: Callable[[], dict], where: str = "") -> Scan:
        """The scan at index with what read() gives (its Scan fields: points, or a density image
        and its layout). A file or message that cannot be read (DatasetError or
        InvalidCloudError naming the problem, OSError) gives a scan with that problem instead
        (Scan.problem, prefixed with where when given): one bad file among thousands is passed
        over by name, not the end of the read."""
        index = int(index)
        stamp, pose = float(self.stamps[index]), self.pose(index)
        try:
            fields = read()
        except (DatasetError, InvalidCloudError, OSError) as error:
            return Scan(index, stamp, pose, problem=f"{where}: {error}" if where else str(error))
        return Scan(index, stamp, pose, **fields)

    def pose(self, index: int) -> np.ndarray | None:
        return None if self.poses is None else self.poses[index]

    def valid_poses(self, needed_for: str) -> np.ndarray:
        """(n,) bool: the scans with a finite pose; DatasetError naming needed_for when the
        source has no poses at all."""
        if self.poses is None:
            raise DatasetError(f"{self.name}: this source has no poses; {needed_for} needs them")
        return np.isfinite(self.poses).all(axis=(1, 2))

    @property
    def fully_posed(self) -> bool:
        """Every scan has a finite pose (the poses can then serve as odometry)."""
        return self.poses is not None and bool(np.isfinite(self.poses).all())


def read_kitti_poses(path, expected: int | None = None) -> np.ndarray:
    """KITTI poses file: 12 numbers per line (3x4 row-major) -> (n, 4, 4)."""
    try:
        values = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except (OSError, ValueError) as error:
        raise DatasetError(f"cannot read KITTI poses {path}: {error}") from error
    if values.shape[1] != 12:
        raise DatasetError(f"{path}: expected 12 numbers per line, got {values.shape[1]}")
    if expected is not None and len(values) != expected:
        raise DatasetError(f"{path}: {len(values)} poses for {expected} scans")
    if not np.isfinite(values).all():
        raise DatasetError(f"{path}: non-finite pose values")
    poses = np.tile(np.eye(4), (len(values), 1, 1))
    poses[:, :3, :4] = values.reshape(-1, 3, 4)
    return poses


def read_tum_poses(path) -> tuple[np.ndarray, np.ndarray]:
    """TUM file 'key x y z qx qy qz qw' -> (keys (n,), poses (n, 4, 4)); '#' lines skipped."""
    from mf_lpr_ros.core.pose import pose_matrix

    try:
        values = np.loadtxt(path, dtype=np.float64, ndmin=2, comments="#")
    except (OSError, ValueError) as error:
        raise DatasetError(f"cannot read TUM poses {path}: {error}") from error
    if values.shape[1] != 8:
        raise DatasetError(f"{path}: expected 8 columns (key x y z qx qy qz qw), "
                           f"got {values.shape[1]}")
    if not np.isfinite(values).all():
        raise DatasetError(f"{path}: non-finite pose values")
    try:
        poses = pose_matrix(values[:, 1:4], values[:, 4:8])
    except ValueError as error:
        raise DatasetError(f"{path}: {error}") from error
    return values[:, 0], poses


def poses_at_stamps(pose_stamps: np.ndarray, poses: np.ndarray, scan_stamps: np.ndarray,
                    max_gap_s: float) -> np.ndarray:
    """Poses interpolated at the scans' stamps; NaN where the ground truth has a gap (a scan
    with a NaN pose is neither a reference nor a query)."""
    from mf_lpr_ros.core.pose import interpolate_poses

    order = np.argsort(pose_stamps, kind="stable")
    interpolated, valid = interpolate_poses(pose_stamps[order], poses[order], scan_stamps,
                                            max_gap_s)
    interpolated[~valid] = np.nan
    return interpolated


def nearest_keys(sorted_keys: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each value, the index of the nearest of sorted_keys and the absolute gap to it."""
    position = np.searchsorted(sorted_keys, values).clip(0, len(sorted_keys) - 1)
    before = (position - 1).clip(0)
    closer_before = np.abs(sorted_keys[before] - values) < np.abs(sorted_keys[position] - values)
    nearest = np.where(closer_before, before, position)
    return nearest, np.abs(sorted_keys[nearest] - values)


def numbered_files(folder, pattern: str, divisor: float) -> tuple[list, np.ndarray]:
    """Files named by an integer time (e.g. microseconds), in time order, and their stamps in
    seconds (name / divisor). Never the directory listing's order."""
    from pathlib import Path

    files = list(Path(folder).glob(pattern))
    if not files:
        raise DatasetError(f"{folder}: no {pattern} files")
    try:
        keys = np.array([int(p.stem) for p in files], dtype=np.int64)
    except ValueError as error:
        raise DatasetError(f"{folder}: file names must be integer times ({error})") from error
    order = np.argsort(keys, kind="stable")
    return [files[i] for i in order], keys[order] / divisor


def read_xyzi_bin(path) -> np.ndarray:
    """x, y, z (N, 3) of a float32 x y z intensity .bin scan (KITTI, MulRan, BALM)."""
    raw = np.fromfile(path, dtype="<f4")
    if raw.size % 4:
        raise DatasetError(f"{path}: size is not a multiple of 16 bytes (x y z intensity)")
    return raw.reshape(-1, 4)[:, :3]


class PoseOverride(Sequence):
    """Another sequence's scans with other poses (e.g. drifted odometry instead of the ground
    truth): the scans it yields carry the new poses."""

    def __init__(self, base: Sequence, poses: np.ndarray, name: str = "") -> None:
        if poses.shape != (len(base), 4, 4):
            raise ValueError(f"{len(base)} scans need ({len(base)}, 4, 4) poses, "
                             f"got {poses.shape}")
        self.base = base
        self.name = name or base.name
        self.stamps = base.stamps
        self.poses = poses
        self.frame_id = getattr(base, "frame_id", "")

    def _read(self, indices: np.ndarray) -> Iterator[Scan]:
        for scan in self.base.iter_scans(indices):
            scan.pose = self.poses[scan.index]
            yield scan


LOADERS: list[type[Sequence]] = []


def register_loader(loader: type[Sequence]) -> type[Sequence]:
    """Class decorator: make open_source try this loader."""
    if not loader.layout:
        raise TypeError(f"{loader.__name__} must declare its layout")
    LOADERS.append(loader)
    LOADERS.sort(key=lambda registered: registered.priority)
    return loader
