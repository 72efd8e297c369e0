"""Reference spectra computed on demand and the prefilter cache beside a map file."""

import dataclasses

import numpy as np
import pytest

from mf_lpr_ros.core import search as search_module
from mf_lpr_ros.core.descriptor import describe_points
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.prefilter_cache import cache_path, save_features
from mf_lpr_ros.core.search import MatchedFilterIndex, cache_prefilter
from mf_lpr_ros.errors import ConfigError
from mf_lpr_ros.params import DescriptorParams, SearchParams
from mf_lpr_ros.sim.synthetic import route, scan_world

PARAMS = DescriptorParams(voxel_size=0.4, z_min=-1.2)
# 8 of 36 references: the prefilter, its expansion by map neighbours and the exact stage
# all take part.
SEARCH = SearchParams(prefilter_top_k=8, backend="numpy")


def _path_map(world, poses) -> ReferenceMap:
    rng = np.random.default_rng(5)
    reference_map = ReferenceMap(PARAMS)
    for i, (x, y, yaw) in enumerate(poses):
        points, pose = scan_world(world, x, y, yaw, rng)
        reference_map.append(describe_points(points, PARAMS, reference=True, seed_key=i), pose,
                             float(i), i)
    return reference_map


@pytest.fixture(scope="module")
def loop_map(world):
    return _path_map(world, route(36))


@pytest.fixture(scope="module")
def queries(world):
    rng = np.random.default_rng(6)
    return [describe_points(scan_world(world, x + 1.1, y - 0.7, yaw + 0.4, rng)[0], PARAMS)
            for x, y, yaw in route(36)[::5]]


def _same_result(a, b):
    assert a.reference_index == b.reference_index
    np.testing.assert_array_equal(a.candidates, b.candidates)
    np.testing.assert_allclose(a.pose, b.pose, atol=1e-9)
    assert a.score == pytest.approx(b.score, rel=1e-5)
    assert a.confidence == pytest.approx(b.confidence, rel=1e-5)
    assert a.distinctiveness == pytest.approx(b.distinctiveness, rel=1e-5, abs=1e-6)


@pytest.mark.parametrize("rescore_k", [0, 16])
@pytest.mark.parametrize("n_active", [None, 20, 6])
def test_on_demand_spectra_give_the_matches_of_spectra_in_memory(loop_map, queries, n_active,
                                                                 rescore_k):
    # n_active 6 is under prefilter_top_k: the exhaustive path, on demand too. rescore_k 16:
    # the coarse re-ranking's references are pooled on demand too.
    search = dataclasses.replace(SEARCH, prefilter_rescore_k=rescore_k)
    memory = MatchedFilterIndex(loop_map, dataclasses.replace(search, reference_spectra="memory"))
    on_demand = MatchedFilterIndex(loop_map, dataclasses.replace(search,
                                                                 reference_spectra="on_demand"))
    assert not memory.spectra_on_demand and on_demand.spectra_on_demand
    for query in queries:
        _same_result(memory.query(query, n_active), on_demand.query(query, n_active))
    # Only a query's candidates are held: the spectra bank is sized for them, not the map.
    assert len(on_demand.bank) <= len(loop_map)
    assert on_demand.nbytes < memory.nbytes
    if rescore_k:
        assert len(on_demand.coarse_bank) <= rescore_k < len(memory.coarse_bank)


def test_auto_keeps_spectra_in_memory_up_to_its_limit(loop_map, monkeypatch):
    assert not MatchedFilterIndex(loop_map, SEARCH).spectra_on_demand
    monkeypatch.setattr(search_module, "ON_DEMAND_ABOVE", len(loop_map) - 1)
    assert MatchedFilterIndex(loop_map, SEARCH).spectra_on_demand
    exhaustive = dataclasses.replace(SEARCH, prefilter_top_k=0)
    assert not MatchedFilterIndex(loop_map, exhaustive).spectra_on_demand


def test_on_demand_needs_the_prefilter():
    with pytest.raises(ConfigError, match="reference_spectra"):
        SearchParams(prefilter_top_k=0, reference_spectra="on_demand")


def test_on_demand_index_follows_a_growing_map(world, loop_map, queries):
    growing = ReferenceMap(PARAMS)
    on_demand = dataclasses.replace(SEARCH, reference_spectra="on_demand")
    index = MatchedFilterIndex(growing, on_demand)
    assert index.query(queries[0]) is None
    for i in range(len(loop_map)):
        growing.append(loop_map.occupancy(i), loop_map.poses[i], float(i), i)
    assert index.sync() == len(loop_map)
    reference = MatchedFilterIndex(loop_map, on_demand)
    for query in queries:
        _same_result(index.query(query), reference.query(query))


def test_prefilter_cache_is_written_reused_and_rebuilt_when_stale(tmp_path, loop_map, queries):
    path = tmp_path / "loop.mfmap"
    loop_map.save(path)
    on_demand = dataclasses.replace(SEARCH, reference_spectra="on_demand")
    expected = [MatchedFilterIndex(loop_map, on_demand).query(query) for query in queries]

    def results_and_status():
        index = MatchedFilterIndex(ReferenceMap.load(path), on_demand)
        return [index.query(query) for query in queries], index.prefilter_cache_status

    first, status = results_and_status()
    assert status.startswith("no cache at") and "; cached at" in status
    assert cache_path(path).exists()
    second, status = results_and_status()
    assert status.startswith("loaded from")
    for a, b, c in zip(expected, first, second):
        _same_result(a, b)
        _same_result(a, c)

    cached = bytearray(cache_path(path).read_bytes())
    cached[-5] ^= 0xFF
    cache_path(path).write_bytes(bytes(cached))
    repaired, status = results_and_status()
    assert "checksum mismatch" in status and "; cached at" in status
    for a, b in zip(expected, repaired):
        _same_result(a, b)
    assert results_and_status()[1].startswith("loaded from")

    # The map changes (a reference more): the old cache belongs to another version of it.
    grown = ReferenceMap.load(path)
    grown.append(loop_map.occupancy(0), loop_map.poses[0], 99.0, 99)
    grown.save(path)
    index = MatchedFilterIndex(ReferenceMap.load(path), on_demand)
    assert index.prefilter_cache_status.startswith("prefilter cache")
    assert "another version of the map; cached at" in index.prefilter_cache_status
    assert len(index) == len(loop_map) + 1

    cache_path(path).write_bytes(b"this is not a cache, only some text")
    assert "not a prefilter cache" in results_and_status()[1]


def test_a_map_saved_offline_has_its_cache_written_before_any_search(tmp_path, loop_map,
                                                                     queries):
    """cache_prefilter, as build-map runs it after saving: the first index of the map then
    loads the features instead of computing them, and matches as one in memory does. A map
    whose search keeps its spectra in memory (the defaults, at this size) gets no cache."""
    path = tmp_path / "loop.mfmap"
    loop_map.save(path)
    on_demand = dataclasses.replace(SEARCH, reference_spectra="on_demand")
    assert cache_prefilter(path, SEARCH) is None
    assert not cache_path(path).exists()
    # Told the map's size, it decides without opening the file.
    assert cache_prefilter(tmp_path / "not_written.mfmap", SEARCH, len(loop_map)) is None
    assert cache_prefilter(path, on_demand, len(loop_map)).startswith("no cache at")
    cache_path(path).unlink()
    status = cache_prefilter(path, on_demand)
    assert status.startswith("no cache at") and "; cached at" in status
    index = MatchedFilterIndex(ReferenceMap.load(path), on_demand)
    assert index.prefilter_cache_status.startswith("loaded from")
    in_memory = MatchedFilterIndex(loop_map, SEARCH)
    for query in queries:
        _same_result(index.query(query), in_memory.query(query))
    assert cache_prefilter(path, on_demand).startswith("loaded from")


def test_a_map_indexed_at_once_holds_its_prefilter_features_in_exactly_their_room(loop_map):
    """On demand the bank starts with room for a query's candidates; the prefilter, indexing a
    whole map at its first sync (block by block, as a large map's 1,024 at a time), takes
    room for exactly the map's references, not the next power of two (at a million
    references 4.3 GB instead of 3.8, and the cache written from the spare room copied
    another 3.8). A map growing a reference at a time still doubles: growing by one each
    time would copy every feature at every sync."""
    def indexed(sync_every: int, block: int) -> MatchedFilterIndex:
        index = MatchedFilterIndex(ReferenceMap(PARAMS),
                                   dataclasses.replace(SEARCH, reference_spectra="on_demand"))
        for reference in range(len(loop_map)):
            index.map.append(loop_map.occupancy(reference), loop_map.poses[reference],
                             float(reference), reference)
            if (reference + 1) % sync_every == 0:
                index.sync(block)
        assert len(index) == len(loop_map)
        return index

    at_once = indexed(sync_every=len(loop_map), block=8)
    harmonics, n_references, radii = at_once.prefilter.stored_features.shape
    exact = harmonics * n_references * radii * np.dtype(np.complex64).itemsize
    assert at_once.prefilter.nbytes == exact
    assert indexed(sync_every=1, block=8).prefilter.nbytes > exact


def test_a_cache_of_another_feature_size_is_rebuilt(tmp_path, loop_map, queries):
    """A cache written by a version whose prefilter read other radii and angles (session 18's
    20 and 32) is not read as today's features: the index rebuilds it and matches as before."""
    path = tmp_path / "loop.mfmap"
    loop_map.save(path)
    on_demand = dataclasses.replace(SEARCH, reference_spectra="on_demand")
    expected = [MatchedFilterIndex(loop_map, on_demand).query(query) for query in queries]
    loaded = ReferenceMap.load(path)
    older = np.ones((17, len(loop_map), 20), dtype=np.complex64)
    save_features(cache_path(path), loaded.content_key, older)
    index = MatchedFilterIndex(loaded, on_demand)
    assert "another shape" in index.prefilter_cache_status
    assert "; cached at" in index.prefilter_cache_status
    for a, query in zip(expected, queries):
        _same_result(a, index.query(query))
    assert MatchedFilterIndex(ReferenceMap.load(path),
                              on_demand).prefilter_cache_status.startswith("loaded from")


def test_references_appended_after_loading_are_indexed_but_not_cached(tmp_path, loop_map):
    path = tmp_path / "loop.mfmap"
    loop_map.save(path)
    loaded = ReferenceMap.load(path)
    loaded.append(loop_map.occupancy(3), loop_map.poses[3], 50.0, 50)
    index = MatchedFilterIndex(loaded, dataclasses.replace(SEARCH, reference_spectra="on_demand"))
    assert len(index) == len(loop_map) + 1
    # The cache holds what the file holds, so the next start can use it.
    reloaded = ReferenceMap.load(path)
    again = MatchedFilterIndex(reloaded,
                               dataclasses.replace(SEARCH, reference_spectra="on_demand"))
    assert again.prefilter_cache_status.startswith("loaded from")
    # A map that grows after starting from the (read-only, memory-mapped) cache: the new
    # reference is indexed and found.
    reloaded.append(loop_map.occupancy(3), loop_map.poses[3] @ _shifted(500.0), 50.0, 50)
    assert again.sync() == 1 and len(again) == len(loop_map) + 1
    found = again.query(loop_map.occupancy(3))
    assert {3, len(loop_map)} <= set(found.candidates[:2].tolist())


def _shifted(metres: float) -> np.ndarray:
    shift = np.eye(4)
    shift[0, 3] = metres
    return shift
