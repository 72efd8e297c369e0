"""A folder of BEV height-density PNGs (imgs/NNNNNN.png) with KITTI poses.txt.

The layout of BEVPlace's KITTI images: 0.4 m per pixel, sensor at the centre pixel, the row
index decreasing as x (forward) grows and the column index decreasing as y (left) grows,
value / 25.5 = occupied voxels in the column. Images are turned into the package's axis
convention (rows = y, columns = x, both increasing) on load; the sensor stays half a pixel off
the package's sensor corner (Scan.sensor_offset_m), at the centre of its pixel.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np
from PIL import Image

from mf_lpr_ros.datasets.base import Scan, Sequence, read_kitti_poses, register_loader
from mf_lpr_ros.errors import DatasetError

PIXEL_SIZE_M = 0.4
COUNT_SCALE = 25.5
FRAME_PERIOD_S = 0.1


@register_loader
class BevPngSequence(Sequence):
    layout = "a BEV PNG folder (imgs/*.png, poses.txt)"
    notes = ("BEVPlace's layout; each image is the column density the descriptor thresholds, "
             "and its sensor sits at a pixel centre (`Scan.sensor_offset_m`, corrected in the "
             "pose)")
    priority = 70

    @classmethod
    def recognises(cls, path: Path) -> bool:
        return path.is_dir() and (path / "imgs").is_dir()

    def __init__(self, root: str | Path, pixel_size_m: float = PIXEL_SIZE_M) -> None:
        self.root = Path(root)
        self.name = self.root.name
        self.pixel_size_m = pixel_size_m
        files = sorted((self.root / "imgs").glob("*.png"), key=lambda p: p.stem)
        if not files:
            raise DatasetError(f"{self.root}: no imgs/*.png density images")
        self._files = files
        self.stamps = np.arange(len(files)) * FRAME_PERIOD_S
        poses_file = self.root / "poses.txt"
        self.poses = read_kitti_poses(poses_file, len(files)) if poses_file.exists() else None

    def _read(self, indices: np.ndarray) -> Iterator[Scan]:
        for index in indices:
            yield self._scan(index, lambda: {
                "density": load_bev_density(self._files[index]),
                "density_pixel_m": self.pixel_size_m, "sensor_offset_m": self.pixel_size_m / 2})


def load_bev_density(path: Path) -> np.ndarray:
    """Occupied voxels per column, in the package's axis convention."""
    try:
        image = np.asarray(Image.open(path).convert("L"), dtype=np.float32)
    except OSError as error:
        raise DatasetError(f"cannot read BEV image {path}: {error}") from error
    return image[::-1, ::-1].T / COUNT_SCALE
