"""Crafted map headers (property-based): a header rewritten with a valid checksum either loads
the original arrays or is refused with MapFileError naming the problem, never another
exception. The slow variant runs many more examples."""

from __future__ import annotations

import copy
import json
import struct
import zlib

import numpy as np
import pytest
from helpers import make_map
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.site_cloud import SiteCloud
from mf_lpr_ros.errors import MapFileError

_PREAMBLE = struct.Struct("<8sIII")

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-2 ** 70, 2 ** 70) | st.floats()
    | st.text(max_size=12) | st.sampled_from(["<f8", "<i8", "|u1", "<f4", "<c16", "O", "V8"]),
    lambda children: st.lists(children, max_size=4)
    | st.dictionaries(st.text(max_size=8), children, max_size=4),
    max_leaves=12)


@st.composite
def header_edits(draw):
    """A list of edits: (path into the header, new value or None to delete the key)."""
    return draw(st.lists(st.tuples(st.lists(st.sampled_from(
        ["arrays", "occupancy_bits", "poses", "stamps", "source_indices", "cloud_points",
         "cloud_offsets", "offset", "dtype", "shape", "crc32", "descriptor", "size",
         "voxel_size", "n_references", "metadata", "frame_id", "site_points", "site_tile_keys",
         "site_tile_offsets", "site_cloud", "tile_m", "half_m", "format_version", 0, 1, 2]),
        min_size=1,
        max_size=4), st.one_of(st.none(), json_values, st.integers(-10 ** 6, 10 ** 6),
                               st.just([[[[[[[[[[[]]]]]]]]]]] * 3))),
        min_size=1, max_size=3))


def apply_edit(header, path, value) -> None:
    node = header
    for key in path[:-1]:
        if isinstance(node, dict) and key in node:
            node = node[key]
        elif isinstance(node, list) and isinstance(key, int) and key < len(node):
            node = node[key]
        else:
            return
    last = path[-1]
    if isinstance(node, dict) and isinstance(last, str):
        if value is None:
            node.pop(last, None)
        else:
            # A copy: hypothesis may hand one value object to two edits, and inserting it
            # into itself would make the header circular.
            node[last] = copy.deepcopy(value)
    elif isinstance(node, list) and isinstance(last, int) and last < len(node):
        node[last] = copy.deepcopy(value)


def rewritten(original: bytes, header: dict | bytes) -> bytes:
    """The file with its header replaced and the preamble's length and checksum made valid;
    the arrays stay where they were (a longer header overwrites their first bytes)."""
    _, version, length, _ = _PREAMBLE.unpack(original[:_PREAMBLE.size])
    encoded = header if isinstance(header, bytes) else json.dumps(header).encode()
    preamble = _PREAMBLE.pack(b"MFLPRMAP", version, len(encoded), zlib.crc32(encoded))
    body = preamble + encoded
    start = _PREAMBLE.size + length
    return body + original[len(body):] if len(body) >= start else \
        body + b"\0" * (start - len(body)) + original[start:]


@pytest.fixture(scope="module", params=["reference clouds", "site cloud"])
def saved_map(tmp_path_factory, request):
    path = tmp_path_factory.mktemp("fuzz") / "map.mfmap"
    rng = np.random.default_rng(0)
    original = make_map(rng, clouds=request.param == "reference clouds")
    if request.param == "site cloud":
        original.set_site_cloud(SiteCloud.from_points(rng.uniform(-40, 40, (500, 3)), 10.0))
    original.save(path)
    data = path.read_bytes()
    _, _, length, _ = _PREAMBLE.unpack(data[:_PREAMBLE.size])
    header = json.loads(data[_PREAMBLE.size:_PREAMBLE.size + length])
    return data, header, ReferenceMap.load(path)


def assert_loads_original_or_refuses(path, data: bytes, original: ReferenceMap) -> None:
    path.write_bytes(data)
    try:
        loaded = ReferenceMap.load(path)
    except MapFileError as error:
        assert str(error).startswith(str(path)), "the message names the file"
        return
    np.testing.assert_array_equal(loaded.occupancy_bits, original.occupancy_bits)
    np.testing.assert_array_equal(loaded.poses, original.poses)
    np.testing.assert_array_equal(loaded.stamps, original.stamps)
    np.testing.assert_array_equal(loaded.source_indices, original.source_indices)
    np.testing.assert_array_equal(loaded.cloud_points, original.cloud_points)
    np.testing.assert_array_equal(loaded.cloud_offsets, original.cloud_offsets)
    assert (loaded.site_cloud is None) == (original.site_cloud is None)
    if original.site_cloud is not None:
        np.testing.assert_array_equal(loaded.site_cloud.points, original.site_cloud.points)
        np.testing.assert_array_equal(loaded.site_cloud.tile_offsets,
                                      original.site_cloud.tile_offsets)


def run_crafted_headers(saved_map, tmp_path, edits) -> None:
    data, header, original = saved_map
    crafted = json.loads(json.dumps(header))
    for path, value in edits:
        apply_edit(crafted, path, value)
    assert_loads_original_or_refuses(tmp_path / "crafted.mfmap", rewritten(data, crafted),
                                     original)


@settings(max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(edits=header_edits())
def test_crafted_headers_load_the_original_or_are_refused(saved_map, tmp_path, edits):
    run_crafted_headers(saved_map, tmp_path, edits)


@pytest.mark.slow
@settings(max_examples=1000, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(edits=header_edits())
def test_crafted_headers_many_more(saved_map, tmp_path, edits):
    run_crafted_headers(saved_map, tmp_path, edits)


@pytest.mark.parametrize("case, expected", [
    ("arrays as a list", "arrays must be a JSON object"),
    ("deep nesting", "nested deeper"),
    ("negative shape", "shape must be"),
    ("negative offset", "offset must be"),
    ("poses read as integers", "poses.dtype"),
    ("overlapping arrays", "offset must be >="),
    ("n_references a string", "n_references must be"),
    ("not JSON", "not UTF-8 JSON"),
    ("unknown descriptor field", "descriptor"),
])
def test_the_known_crafted_headers_are_refused_by_name(saved_map, tmp_path, case, expected):
    data, header, original = saved_map
    crafted = json.loads(json.dumps(header))
    arrays = crafted["arrays"]
    if case == "arrays as a list":
        crafted["arrays"] = list(arrays.values())
    elif case == "deep nesting":
        crafted = b'{"metadata": ' + b"[" * 100_000 + b"]" * 100_000 + b"}"
    elif case == "negative shape":
        arrays["stamps"]["shape"] = [-5]
    elif case == "negative offset":
        arrays["poses"]["offset"] = -64
    elif case == "poses read as integers":
        arrays["poses"]["dtype"] = "<i8"
    elif case == "overlapping arrays":
        arrays["stamps"]["offset"] = arrays["poses"]["offset"]
    elif case == "n_references a string":
        crafted["n_references"] = "5"
    elif case == "not JSON":
        crafted = b"\xff\xfe not json"
    elif case == "unknown descriptor field":
        crafted["descriptor"]["voxel_sizes"] = 0.5
    path = tmp_path / "crafted.mfmap"
    path.write_bytes(rewritten(data, crafted))
    with pytest.raises(MapFileError, match=expected):
        ReferenceMap.load(path)
