"""A place's similarity (MatchedFilterIndex.place_similarity): how alike the map's own views of
a place are, the yardstick of SearchParams.min_relative_confidence."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers import turned_view_map

from mf_lpr_ros.core.descriptor import _rotation_sources, describe_points
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.search import MatchedFilterIndex
from mf_lpr_ros.params import DescriptorParams, SearchParams
from mf_lpr_ros.sim.synthetic import scan_world

PARAMS = DescriptorParams(voxel_size=0.4, z_min=-1.2)
# Views every 2 m along a route, then one place 25 m from any other (beyond distinct_radius_m).
ROUTE = [(2.0 * step, 0.0, 0.3) for step in range(6)]
LONE = (-25.0, -10.0, 2.5)


def _map(world) -> ReferenceMap:
    """The route's and the lone place's views."""
    rng = np.random.default_rng(0)
    reference_map = ReferenceMap(PARAMS)
    for index, (x, y, yaw) in enumerate(ROUTE + [LONE]):
        points, pose = scan_world(world, x, y, yaw, rng)
        reference_map.append(describe_points(points, PARAMS, reference=True, seed_key=index),
                             pose, float(index), index)
    return reference_map


@pytest.fixture(scope="module")
def route_index(world):
    return MatchedFilterIndex(_map(world), SearchParams())


def test_views_along_a_route_are_alike_and_a_lone_place_has_no_yardstick(route_index):
    similarities = [route_index.place_similarity(view) for view in range(len(ROUTE))]
    assert all(0.3 < similarity <= 1.0 for similarity in similarities), similarities
    assert math.isnan(route_index.place_similarity(len(ROUTE)))
    # Only active references count: the first view's neighbours are not in the map yet.
    assert math.isnan(route_index.place_similarity(0, n_refs=1))
    assert route_index.place_similarity(1, n_refs=2) == pytest.approx(
        route_index.place_similarity(1), abs=0.1)


def test_a_place_measures_as_alike_when_the_maps_headings_are_wrong(world, route_index):
    """The yaw between two views is read off the views too: a map whose headings are off by
    up to half a turn measures its places as the right map does (aligned at the map's headings
    alone, the views would barely overlap). The views are turned only by the search's own
    rotation tables: measuring at arbitrary angles makes no new one."""
    errors = np.random.default_rng(7).uniform(np.radians(30), np.radians(170),
                                              len(ROUTE) + 1)
    wrong = MatchedFilterIndex(turned_view_map(_map(world), [
        (view, turn, 0.0) for view, turn in enumerate(errors)]), SearchParams())
    tables_made = _rotation_sources.cache_info().misses
    for view in range(len(ROUTE)):
        assert wrong.place_similarity(view) == pytest.approx(
            route_index.place_similarity(view), abs=0.03)
    assert _rotation_sources.cache_info().misses == tables_made


def test_a_query_turns_by_the_prepared_tables_and_a_place_by_its_own(world, route_index,
                                                                       monkeypatch):
    """Every set of angles a query turns to has its table from start-up (the global headings
    and each one's local angles); a yaw a place's similarity is measured at that is none of
    them gets a table made for that call alone."""
    from mf_lpr_ros.core import search as search_module

    prepared = {tuple(route_index.global_angles.tolist())} | {
        tuple((heading + route_index.local_offsets).tolist())
        for heading in route_index.global_angles}
    calls = []
    original = search_module.rotate_occupancy

    def recording(image, angles, only=None, *, cached=True):
        calls.append((tuple(np.atleast_1d(angles).tolist()) in prepared, cached))
        return original(image, angles, only, cached=cached)

    monkeypatch.setattr(search_module, "rotate_occupancy", recording)
    points, _ = scan_world(world, 5.1, 0.6, 0.5, np.random.default_rng(3))
    route_index.query(describe_points(points, PARAMS))
    assert calls and all(is_prepared and cached for is_prepared, cached in calls)
    calls.clear()
    route_index._place_similarity.clear()
    route_index.place_similarity(2)
    assert all(is_prepared == cached for is_prepared, cached in calls)
    assert any(not cached for _, cached in calls)


def test_a_weak_match_carries_its_places_similarity_and_nothing_else_changes(world):
    """Measured for a match under min_confidence only (here every match is), inside the query,
    without disturbing it: the match is the same as with the relative test off."""
    points, _ = scan_world(world, 5.1, 0.6, 0.5, np.random.default_rng(3))
    query = describe_points(points, PARAMS)
    results = {relative: MatchedFilterIndex(_map(world), SearchParams(
        min_confidence=0.99, min_relative_confidence=relative)).query(query)
        for relative in (0.0, 0.9)}
    off, on = results[0.0], results[0.9]
    assert math.isnan(off.place_similarity)
    scored = on.reference_index if on.scored_reference is None else on.scored_reference
    assert on.place_similarity == MatchedFilterIndex(
        _map(world), SearchParams()).place_similarity(scored)
    assert on.reference_index == off.reference_index
    assert on.confidence == off.confidence
    np.testing.assert_array_equal(on.pose, off.pose)
    np.testing.assert_array_equal(on.candidates, off.candidates)
    strong = MatchedFilterIndex(_map(world), SearchParams(min_confidence=0.01)).query(query)
    assert math.isnan(strong.place_similarity)
