"""PointCloud2 decoding and encoding without ROS.

Works on any object with PointCloud2's attributes (an rclpy message, a rosbags message or a
stand-in), so the nodes, the bag readers and the tests share one implementation.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from mf_lpr_ros.core.descriptor import finite_rows, rows_where
from mf_lpr_ros.errors import InvalidCloudError

# sensor_msgs/PointField datatypes.
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)
_DATATYPE_SIZES = {INT8: 1, UINT8: 1, INT16: 2, UINT16: 2, INT32: 4, UINT32: 4, FLOAT32: 4,
                   FLOAT64: 8}
_COORDINATE_TYPES = {FLOAT32: "f4", FLOAT64: "f8"}


@dataclass(frozen=True)
class FieldSpec:
    name: str
    offset: int
    datatype: int
    count: int = 1


def pointcloud2_to_xyz(cloud: Any, max_points: int | None = None) -> np.ndarray:
    """The finite x, y, z of a PointCloud2 as (N, 3) float32.

    Honours fields, offsets, point_step, row_step, is_bigendian, float32/float64 coordinates and
    organised clouds; other fields are ignored. Raises InvalidCloudError naming the problem.
    """
    height, width, point_step, row_step = _checked_shape(cloud, max_points)
    dtype = _coordinate_dtype(cloud, point_step)
    if height > 1 and row_step < width * point_step:
        raise InvalidCloudError(f"PointCloud2 row_step {row_step} is smaller than width * "
                                f"point_step = {width * point_step}")
    row_stride = row_step if height > 1 else width * point_step
    data = np.frombuffer(_buffer(cloud.data), dtype=np.uint8)
    needed = (height - 1) * row_stride + width * point_step
    if len(data) < needed:
        raise InvalidCloudError(f"PointCloud2 data holds {len(data)} bytes; its layout "
                                f"(height {height}, width {width}, point_step {point_step}, "
                                f"row_step {row_step}) needs {needed}")
    records = np.ndarray(shape=(height, width), dtype=dtype, buffer=data,
                         strides=(row_stride, point_step))
    xyz = np.empty((height * width, 3), dtype=np.float32)
    # A float64 coordinate beyond float32's range becomes inf, and is dropped with the other
    # non-finite points below.
    with np.errstate(over="ignore"):
        for column, axis in enumerate("xyz"):
            xyz[:, column] = records[axis].ravel()
    return rows_where(xyz, finite_rows(xyz))


def _checked_shape(cloud: Any, max_points: int | None) -> tuple[int, int, int, int]:
    """(height, width, point_step, row_step), refusing empty, oversized or negative layouts."""
    height, width = int(cloud.height), int(cloud.width)
    point_step, row_step = int(cloud.point_step), int(cloud.row_step)
    if height < 0 or width < 0 or row_step < 0:
        raise InvalidCloudError(f"PointCloud2 height {height}, width {width} and row_step "
                                f"{row_step} must not be negative")
    n_points = height * width
    if n_points == 0:
        raise InvalidCloudError("PointCloud2 is empty (width * height = 0)")
    if max_points is not None and n_points > max_points:
        raise InvalidCloudError(f"PointCloud2 has {n_points} points, more than the limit "
                                f"{max_points}")
    if point_step <= 0:
        raise InvalidCloudError(f"PointCloud2 point_step must be > 0, got {point_step}")
    return height, width, point_step, row_step


def _coordinate_dtype(cloud: Any, point_step: int) -> np.dtype:
    """The structured dtype of one point's x, y, z, refusing missing, non-float, misplaced or
    overlapping fields."""
    fields = {f.name: f for f in cloud.fields}
    missing = [axis for axis in "xyz" if axis not in fields]
    if missing:
        raise InvalidCloudError(f"PointCloud2 has no {', '.join(missing)} field "
                                f"(fields: {sorted(fields)})")
    byte_order = ">" if cloud.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for axis in "xyz":
        field = fields[axis]
        if field.datatype not in _COORDINATE_TYPES:
            raise InvalidCloudError(f"PointCloud2 field {axis!r} has datatype {field.datatype}; "
                                    "only FLOAT32 (7) and FLOAT64 (8) coordinates are supported")
        size = _DATATYPE_SIZES[field.datatype]
        if field.offset < 0 or field.offset + size > point_step:
            raise InvalidCloudError(f"PointCloud2 field {axis!r} at offset {field.offset} "
                                    f"({size} bytes) does not fit in point_step {point_step}")
        names.append(axis)
        formats.append(byte_order + _COORDINATE_TYPES[field.datatype])
        offsets.append(int(field.offset))
    spans = sorted((offset, offset + np.dtype(fmt).itemsize, name)
                   for offset, fmt, name in zip(offsets, formats, names))
    for (_, end, first), (start, _, second) in zip(spans, spans[1:]):
        if start < end:
            raise InvalidCloudError(f"PointCloud2 fields {first!r} and {second!r} overlap "
                                    f"(offsets {dict(zip(names, offsets))})")
    return np.dtype({"names": names, "formats": formats, "offsets": offsets,
                     "itemsize": point_step})


def _buffer(data: Any) -> Any:
    if isinstance(data, (bytes, bytearray, memoryview, np.ndarray)):
        return data
    try:
        return memoryview(data)
    except TypeError:
        return bytes(data)


def xyz_to_pointcloud2_layout(points: np.ndarray) -> tuple[list[FieldSpec], int, bytes]:
    """(fields, point_step, data) of a dense float32 x, y, z cloud, little-endian."""
    xyz = np.ascontiguousarray(np.asarray(points, dtype="<f4")[:, :3])
    fields = [FieldSpec("x", 0, FLOAT32), FieldSpec("y", 4, FLOAT32), FieldSpec("z", 8, FLOAT32)]
    return fields, 12, xyz.tobytes()


def decode_points(cloud: Any, max_points: int) -> np.ndarray:
    """A PointCloud2's finite points, refusing clouds with none left."""
    points = pointcloud2_to_xyz(cloud, max_points=max_points)
    if len(points) == 0:
        raise InvalidCloudError("PointCloud2 holds no finite point (all NaN or infinite)")
    return points
