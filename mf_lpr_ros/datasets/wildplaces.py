"""Wild-Places sequence (e.g. Venman/V-03): Clouds/ or Clouds_downsampled/ and poses_aligned.csv.

Clouds are named by their time (<sec>.<nsec>.pcd, or .bin float32 x y z intensity in the newer
release). The CSV has a header naming timestamp, x, y, z, qx, qy, qz, qw: one pose per cloud,
keyed by the same time. The release's evaluation pickles (<Forest>_evaluation_query.pickle and
<Forest>_evaluation_database.pickle) list each sequence's test-split queries; read_query_split
reads them without running arbitrary pickled code.
"""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Iterator

import numpy as np

from mf_lpr_ros.core.pose import pose_matrix
from mf_lpr_ros.datasets.base import Scan, Sequence, nearest_keys, read_xyzi_bin, register_loader
from mf_lpr_ros.errors import DatasetError
from mf_lpr_ros.io.pcd import read_pcd

CLOUD_FOLDERS = ("Clouds_downsampled", "Clouds")
POSE_FILES = ("poses_aligned.csv", "poses.csv")
_POSE_COLUMNS = ("x", "y", "z", "qx", "qy", "qz", "qw")
_STAMP_TOLERANCE_S = 1e-4


@register_loader
class WildPlacesSequence(Sequence):
    layout = "a Wild-Places sequence (Clouds_downsampled/ or Clouds/, poses_aligned.csv)"
    notes = ("PCD or float32 `.bin` clouds; the release's `<Forest>_evaluation_query.pickle` is "
             "read by a loader that refuses any pickled code")
    priority = 60

    @classmethod
    def recognises(cls, path: Path) -> bool:
        return path.is_dir() and any((path / folder).is_dir() for folder in CLOUD_FOLDERS)

    def __init__(self, root: str | Path, cloud_folder: str | None = None) -> None:
        self.root = Path(root)
        self.name = self.root.name
        folders = [cloud_folder] if cloud_folder else list(CLOUD_FOLDERS)
        folder = next((self.root / f for f in folders if (self.root / f).is_dir()), None)
        if folder is None:
            raise DatasetError(f"{self.root}: no cloud folder (expected one of {folders})")
        files = [p for p in folder.iterdir() if p.suffix in (".pcd", ".bin")]
        if not files:
            raise DatasetError(f"{folder}: no .pcd or .bin clouds")
        try:
            stamps = np.array([float(p.stem) for p in files])
        except ValueError as error:
            raise DatasetError(f"{folder}: cloud file names must be times ({error})") from error
        order = np.argsort(stamps, kind="stable")
        self._files = [files[i] for i in order]
        self.stamps = stamps[order]
        pose_file = next((self.root / f for f in POSE_FILES if (self.root / f).exists()), None)
        self.poses = None if pose_file is None else self._poses_for_clouds(pose_file)

    def _poses_for_clouds(self, path: Path) -> np.ndarray:
        pose_stamps, poses = read_pose_csv(path)
        order = np.argsort(pose_stamps, kind="stable")
        pose_stamps, poses = pose_stamps[order], poses[order]
        nearest, gap = nearest_keys(pose_stamps, self.stamps)
        matched = gap <= _STAMP_TOLERANCE_S
        result = np.full((len(self.stamps), 4, 4), np.nan)
        result[matched] = poses[nearest[matched]]
        return result

    def _read(self, indices: np.ndarray) -> Iterator[Scan]:
        for index in indices:
            path = self._files[index]
            yield self._scan(index, lambda: {
                "points": read_pcd(path) if path.suffix == ".pcd" else read_xyzi_bin(path)})


def read_pose_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Stamps and world_T_sensor poses from a Wild-Places pose CSV (columns found by name)."""
    try:
        with open(path) as handle:
            header = [name.strip().lstrip("%") for name in handle.readline().split(",")]
        values = np.genfromtxt(path, delimiter=",", skip_header=1, dtype=np.float64, ndmin=2)
    except (OSError, ValueError) as error:
        raise DatasetError(f"cannot read {path}: {error}") from error
    stamp_column = next((n for n in ("timestamp", "time") if n in header), None)
    missing = [n for n in _POSE_COLUMNS if n not in header]
    if stamp_column is None or missing:
        raise DatasetError(f"{path}: expected columns timestamp, x, y, z, qx, qy, qz, qw "
                           f"(header: {header})")
    values = values[np.isfinite(values).all(axis=1)]
    columns = values[:, [header.index(n) for n in _POSE_COLUMNS]]
    try:
        poses = pose_matrix(columns[:, :3], columns[:, 3:])
    except ValueError as error:
        raise DatasetError(f"{path}: {error}") from error
    return values[:, header.index(stamp_column)], poses


class _PlainDataUnpickler(pickle.Unpickler):
    """Loads dicts, lists, numbers, strings and numpy arrays; refuses any other class."""

    _ALLOWED = {("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray",
                                                            "_reconstruct"),
                ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
                ("numpy", "ndarray"), ("numpy", "dtype")}

    def find_class(self, module: str, name: str):
        if (module, name) in self._ALLOWED:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"refusing to load {module}.{name}")


def read_query_split(query_pickle: str | Path) -> list[np.ndarray]:
    """Per sequence of a forest (in the pickle's order), the times of its evaluation queries."""
    path = Path(query_pickle)
    try:
        with open(path, "rb") as handle:
            sets = _PlainDataUnpickler(handle).load()
    except (OSError, pickle.UnpicklingError, EOFError, AttributeError) as error:
        raise DatasetError(f"cannot read Wild-Places query split {path}: {error}") from error
    if not isinstance(sets, list) or not all(isinstance(s, dict) for s in sets):
        raise DatasetError(f"{path}: expected a list of per-sequence dicts (the Wild-Places "
                           "evaluation query pickle)")
    stamps = []
    for sequence in sets:
        try:
            stamps.append(np.array(sorted(float(Path(entry["query"]).name.rsplit(".", 1)[0])
                                          for entry in sequence.values())))
        except (KeyError, TypeError, ValueError) as error:
            raise DatasetError(f"{path}: an entry has no usable 'query' file name ({error})") \
                from error
    return stamps
