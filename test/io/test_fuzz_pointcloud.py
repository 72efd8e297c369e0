"""Property-based tests of PointCloud2 decoding: any layout either decodes to finite points or
is refused with InvalidCloudError naming the problem; valid layouts decode exactly."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mf_lpr_ros.errors import InvalidCloudError
from mf_lpr_ros.io.pointcloud import pointcloud2_to_xyz

FIELD = st.builds(SimpleNamespace,
                  name=st.sampled_from(["x", "y", "z", "intensity", "ring", "t"]),
                  offset=st.integers(-4, 48), datatype=st.integers(0, 10), count=st.integers(0, 3))


@st.composite
def valid_cloud(draw):
    """A well-formed cloud: shuffled field order, padding, either byte order, f4 or f8, NaN
    holes."""
    coordinate = draw(st.sampled_from(["f4", "f8"]))
    size = np.dtype(coordinate).itemsize
    order = draw(st.permutations(["x", "y", "z", "intensity"]))
    padding = draw(st.lists(st.integers(0, 5), min_size=4, max_size=4))
    offsets, cursor = {}, 0
    for name, pad in zip(order, padding):
        cursor += pad
        offsets[name] = cursor
        cursor += size if name != "intensity" else 4
    point_step = cursor + draw(st.integers(0, 6))
    height, width = draw(st.integers(1, 3)), draw(st.integers(1, 20))
    row_step = width * point_step + draw(st.integers(0, 9))
    big = draw(st.booleans())
    values = draw(st.lists(st.floats(-1e4, 1e4, allow_nan=False, width=32),
                           min_size=3 * height * width, max_size=3 * height * width))
    xyz = np.array(values, dtype=np.float64).reshape(-1, 3)
    holes = draw(st.lists(st.integers(0, len(xyz) - 1), max_size=3))
    xyz[holes] = np.nan
    data = bytearray(height * row_step)
    dtype = (">" if big else "<") + coordinate
    for index, point in enumerate(xyz):
        base = (index // width) * row_step + (index % width) * point_step
        for axis, value in zip("xyz", point):
            data[base + offsets[axis]: base + offsets[axis] + size] = np.array(
                value, dtype=dtype).tobytes()
    datatype = 8 if size == 8 else 7
    fields = [SimpleNamespace(name=n, offset=offsets[n], datatype=datatype if n != "intensity"
                              else 7, count=1) for n in order]
    cloud = SimpleNamespace(fields=fields, height=height, width=width, point_step=point_step,
                            row_step=row_step, is_bigendian=big, data=bytes(data))
    return cloud, xyz


FAULTS = ["none", "drop_field", "move_field", "retype_field", "negative_size", "short_data",
          "point_step", "row_step", "huge", "stray_field", "arbitrary"]


@st.composite
def any_cloud(draw):
    """A well-formed cloud with one fault injected (or none), so that every check is reached."""
    cloud, _ = draw(valid_cloud())
    fault = draw(st.sampled_from(FAULTS))
    fields = {f.name: f for f in cloud.fields}
    axis = fields[draw(st.sampled_from("xyz"))]
    if fault == "drop_field":
        cloud.fields = [f for f in cloud.fields if f is not axis]
    elif fault == "move_field":
        axis.offset = draw(st.integers(-8, cloud.point_step + 8))
    elif fault == "retype_field":
        axis.datatype = draw(st.integers(-1, 12))
    elif fault == "negative_size":
        setattr(cloud, draw(st.sampled_from(["height", "width", "row_step"])),
                draw(st.integers(-3, -1)))
    elif fault == "short_data":
        cloud.data = cloud.data[: draw(st.integers(0, max(len(cloud.data) - 1, 0)))]
    elif fault == "point_step":
        cloud.point_step = draw(st.integers(-2, cloud.point_step - 1))
    elif fault == "row_step":
        cloud.row_step = draw(st.integers(0, cloud.row_step))
        cloud.height = max(cloud.height, 2)
    elif fault == "huge":
        cloud.width, cloud.height = 5_000_000, 1
    elif fault == "stray_field":
        cloud.fields = [*cloud.fields, draw(FIELD)]
    elif fault == "arbitrary":
        cloud.data = draw(st.binary(max_size=2000))
        cloud.width, cloud.point_step = draw(st.integers(0, 50)), draw(st.integers(0, 40))
    return cloud


@settings(max_examples=800, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(any_cloud())
def test_any_layout_decodes_or_is_refused_by_name(cloud):
    try:
        points = pointcloud2_to_xyz(cloud, max_points=10_000)
    except InvalidCloudError as error:
        assert str(error).startswith("PointCloud2")
        return
    assert points.dtype == np.float32 and points.ndim == 2 and points.shape[1] == 3
    assert np.isfinite(points).all()


@settings(max_examples=300, deadline=None)
@given(valid_cloud())
def test_valid_layouts_decode_exactly(case):
    cloud, xyz = case
    expected = xyz[np.isfinite(xyz).all(axis=1)].astype(np.float32)
    np.testing.assert_array_equal(pointcloud2_to_xyz(cloud), expected)
