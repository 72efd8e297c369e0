from types import SimpleNamespace

import numpy as np
import pytest

from mf_lpr_ros.errors import InvalidCloudError
from mf_lpr_ros.io.pointcloud import FLOAT32, FLOAT64, UINT16, pointcloud2_to_xyz


def field(name, offset, datatype=FLOAT32, count=1):
    return SimpleNamespace(name=name, offset=offset, datatype=datatype, count=count)


def cloud(points, *, dtype="<f4", point_step=None, bigendian=False, height=1, row_pad=0,
          extra=True):
    """A PointCloud2 stand-in laid out like the velodyne driver (x y z intensity ring time)."""
    n = len(points)
    size = np.dtype(dtype).itemsize
    layout = [("x", 0), ("y", size), ("z", 2 * size)]
    step = point_step or 3 * size + (10 if extra else 0)
    width = n // height
    row_step = width * step + row_pad
    data = np.zeros(height * row_step, dtype=np.uint8)
    order = ">" if bigendian else "<"
    for row in range(height):
        for col in range(width):
            base = row * row_step + col * step
            values = np.asarray(points[row * width + col], dtype=order + dtype[1:]).tobytes()
            data[base: base + 3 * size] = np.frombuffer(values, np.uint8)
    datatype = FLOAT64 if size == 8 else FLOAT32
    fields = [field(n_, o, datatype) for n_, o in layout]
    if extra:
        fields += [field("intensity", 3 * size), field("ring", 3 * size + 4, UINT16)]
    return SimpleNamespace(fields=fields, height=height, width=width, point_step=step,
                           row_step=row_step, is_bigendian=bigendian, data=data.tobytes())


POINTS = np.array([[1.0, 2.0, 3.0], [-4.5, 0.25, 7.0], [np.nan, 1.0, 1.0], [8.0, -9.0, 0.5]])


@pytest.mark.parametrize("kwargs", [{}, {"dtype": "<f8"}, {"bigendian": True},
                                    {"point_step": 22, "extra": False}, {"height": 2,
                                                                         "row_pad": 6}])
def test_layouts_decode_to_the_same_points(kwargs):
    xyz = pointcloud2_to_xyz(cloud(POINTS, **kwargs))
    np.testing.assert_allclose(xyz, POINTS[[0, 1, 3]], rtol=1e-6)


def test_missing_field_is_named():
    message = cloud(POINTS)
    message.fields = [f for f in message.fields if f.name != "x"]
    with pytest.raises(InvalidCloudError, match="no x field"):
        pointcloud2_to_xyz(message)


def test_short_data_and_bad_offsets_are_refused():
    message = cloud(POINTS)
    message.data = message.data[:-5]
    with pytest.raises(InvalidCloudError, match="needs"):
        pointcloud2_to_xyz(message)
    message = cloud(POINTS)
    message.point_step = 8
    with pytest.raises(InvalidCloudError, match="does not fit in point_step"):
        pointcloud2_to_xyz(message)


def test_empty_and_integer_coordinates_are_refused():
    message = cloud(POINTS)
    message.width = 0
    with pytest.raises(InvalidCloudError, match="empty"):
        pointcloud2_to_xyz(message)
    message = cloud(POINTS)
    message.fields[0].datatype = UINT16
    with pytest.raises(InvalidCloudError, match="only FLOAT32"):
        pointcloud2_to_xyz(message)


def test_real_velodyne_layout_from_the_bag(data_dir):
    from mf_lpr_ros.datasets import open_source

    bag = open_source(data_dir / "balm_realworld_bag")
    kitti = open_source(data_dir / "balm_realworld")
    from_bag = next(bag.iter_scans([10])).points
    assert from_bag.shape[0] > 1000 and np.isfinite(from_bag).all()
    # The bag holds the same scan as the KITTI folder, downsampled to 0.3 m instead of 0.2 m.
    extent_bag = np.percentile(np.abs(from_bag), 95, axis=0)
    extent_kitti = np.percentile(np.abs(next(kitti.iter_scans([10])).points), 95, axis=0)
    np.testing.assert_allclose(extent_bag, extent_kitti, rtol=0.2)


@pytest.mark.parametrize("change,problem", [
    ({"height": -1, "width": -1}, "negative"),
    ({"fields": [field("x", 0), field("y", 2), field("z", 8)]}, "overlap"),
])
def test_impossible_layouts_are_named(change, problem):
    message = cloud(POINTS, extra=False)
    for key, value in change.items():
        setattr(message, key, value)
    with pytest.raises(InvalidCloudError, match=problem):
        pointcloud2_to_xyz(message)
