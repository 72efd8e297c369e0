import json
import struct

import numpy as np
import pytest
from helpers import PARAMS, make_map

from mf_lpr_ros.core.map_store import FORMAT_VERSION, ReferenceMap
from mf_lpr_ros.errors import MapFileError, MapParameterMismatch
from mf_lpr_ros.params import DescriptorParams


def test_round_trip_keeps_everything(tmp_path, rng):
    original = make_map(rng, clouds=True)
    path = tmp_path / "a.mfmap"
    original.save(path)
    loaded = ReferenceMap.load(path)
    assert len(loaded) == 5 and loaded.params == PARAMS
    assert loaded.frame_id == "map" and loaded.sensor_frame_id == "velodyne"
    assert loaded.metadata == {"source": "test"}
    np.testing.assert_array_equal(loaded.occupancy(slice(None)), original.occupancy(slice(None)))
    np.testing.assert_allclose(loaded.poses, original.poses)
    np.testing.assert_allclose(loaded.stamps, original.stamps)
    np.testing.assert_array_equal(loaded.source_indices, [0, 3, 6, 9, 12])
    np.testing.assert_allclose(loaded.cloud(3), original.cloud(3))
    assert isinstance(loaded.occupancy_bits, np.memmap)


def test_append_after_load_and_resave(tmp_path, rng):
    path = tmp_path / "a.mfmap"
    make_map(rng).save(path)
    loaded = ReferenceMap.load(path)
    loaded.append(np.ones((120, 120), dtype=bool), np.eye(4), 200.0, 99)
    loaded.save(path)
    again = ReferenceMap.load(path)
    assert len(again) == 6 and again.occupancy(5).all() and again.stamps[-1] == 200.0


def test_empty_map_round_trips(tmp_path):
    path = tmp_path / "empty.mfmap"
    ReferenceMap(PARAMS).save(path)
    assert len(ReferenceMap.load(path)) == 0


@pytest.mark.parametrize("position,mask,message", [(-100, 0xFF, "checksum in 'poses'|checksum"),
                                                   (30, 0x01, "corrupt map header")])
def test_flipped_bits_are_detected(tmp_path, rng, position, mask, message):
    path = tmp_path / "a.mfmap"
    make_map(rng).save(path)
    data = bytearray(path.read_bytes())
    data[position] ^= mask
    path.write_bytes(bytes(data))
    with pytest.raises(MapFileError, match=message):
        ReferenceMap.load(path)


@pytest.mark.parametrize("keep", [0, 10, 23, 200, -1])
def test_truncation_is_detected(tmp_path, rng, keep):
    path = tmp_path / "a.mfmap"
    make_map(rng).save(path)
    data = path.read_bytes()
    path.write_bytes(data[:keep] if keep >= 0 else data[:-1])
    with pytest.raises(MapFileError, match="truncated|magic"):
        ReferenceMap.load(path)


def test_newer_and_unknown_versions_are_refused(tmp_path, rng):
    path = tmp_path / "a.mfmap"
    make_map(rng).save(path)
    data = bytearray(path.read_bytes())
    struct.pack_into("<I", data, 8, FORMAT_VERSION + 1)
    path.write_bytes(bytes(data))
    with pytest.raises(MapFileError, match="newer"):
        ReferenceMap.load(path)
    struct.pack_into("<I", data, 8, 0)
    path.write_bytes(bytes(data))
    with pytest.raises(MapFileError, match="version 0"):
        ReferenceMap.load(path)


def test_not_a_map_and_missing_file(tmp_path):
    path = tmp_path / "b.mfmap"
    path.write_bytes(b"PK\x03\x04" + b"\0" * 100)
    with pytest.raises(MapFileError, match="not an mf_lpr_ros map"):
        ReferenceMap.load(path)
    with pytest.raises(MapFileError, match="cannot read"):
        ReferenceMap.load(tmp_path / "missing.mfmap")


def test_parameter_mismatch_names_the_parameter(rng):
    reference_map = make_map(rng)
    reference_map.check_params(PARAMS)
    with pytest.raises(MapParameterMismatch, match="voxel_size: map has 0.4, requested 0.3"):
        reference_map.check_params(DescriptorParams(voxel_size=0.3))


def test_failed_save_keeps_the_previous_map(tmp_path, rng, monkeypatch):
    path = tmp_path / "a.mfmap"
    first = make_map(rng, n=3)
    first.save(path)
    bigger = make_map(rng, n=8)

    def broken_fsync(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("mf_lpr_ros.core.map_store.os.fsync", broken_fsync)
    with pytest.raises(OSError):
        bigger.save(path)
    monkeypatch.undo()
    assert len(ReferenceMap.load(path)) == 3
    assert [p.name for p in tmp_path.iterdir()] == ["a.mfmap"]


def test_header_is_self_describing(tmp_path, rng):
    path = tmp_path / "a.mfmap"
    make_map(rng).save(path)
    data = path.read_bytes()
    header_len = struct.unpack_from("<I", data, 12)[0]
    header = json.loads(data[20:20 + header_len])
    assert header["descriptor"]["voxel_size"] == 0.4
    assert header["n_references"] == 5
    assert set(header["arrays"]) >= {"occupancy_bits", "poses", "stamps"}


def test_saves_while_another_thread_appends_are_whole_maps(tmp_path, rng):
    """A node's timer saves while its scan callback appends (and counts, which flushes):
    every saved file must load, with one cloud per reference and no reference twice."""
    import sys
    import threading

    reference_map = ReferenceMap(PARAMS)
    occupancy = rng.random((PARAMS.size, PARAMS.size)) < 0.1
    clouds = [rng.random((50 + k % 7, 3)).astype(np.float32) for k in range(400)]
    half_appended, half_saved, done = threading.Event(), threading.Event(), threading.Event()

    def append_and_count():
        for k, cloud in enumerate(clouds):
            if k == len(clouds) // 2:
                # However the threads are scheduled, one save falls between the two halves:
                # the test never passes without a save of a map still growing.
                half_appended.set()
                half_saved.wait(timeout=60)
            reference_map.append(occupancy, np.eye(4), float(k), k, cloud=cloud)
            len(reference_map)
        done.set()

    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)                     # switch threads as often as possible
    saved_lengths = []
    try:
        appender = threading.Thread(target=append_and_count)
        appender.start()
        while not done.is_set() or not saved_lengths:
            after_half = half_appended.is_set()
            path = tmp_path / f"save{len(saved_lengths)}.mfmap"
            reference_map.save(path)
            loaded = ReferenceMap.load(path)
            np.testing.assert_array_equal(loaded.stamps, np.arange(len(loaded)))
            if len(loaded):
                assert len(loaded.cloud_offsets) == len(loaded) + 1
                for k in range(len(loaded)):
                    assert len(loaded.cloud(k)) == len(clouds[k])
            saved_lengths.append(len(loaded))
            if after_half:
                half_saved.set()
        appender.join()
    finally:
        sys.setswitchinterval(interval)
    final = tmp_path / "final.mfmap"
    reference_map.save(final)
    assert len(ReferenceMap.load(final)) == 400
    assert any(0 < length < 400 for length in saved_lengths), saved_lengths


def test_a_map_saved_over_the_one_being_loaded_does_not_mix_into_it(tmp_path, rng,
                                                                    monkeypatch):
    """A localiser loading the map a map builder is saving every few seconds: the save renames a
    new file over the path between the load's reading of the header and of the arrays. The
    load reads the file it opened, whole."""
    import mf_lpr_ros.core.map_store as map_store

    path = tmp_path / "m.mfmap"
    make_map(rng, 5).save(path)
    newer = make_map(rng, 8)
    parse_header = map_store.parse_header

    def saved_over_meanwhile(*args):
        newer.save(path)
        return parse_header(*args)

    monkeypatch.setattr(map_store, "parse_header", saved_over_meanwhile)
    assert len(ReferenceMap.load(path)) == 5
    monkeypatch.undo()
    assert len(ReferenceMap.load(path)) == 8
