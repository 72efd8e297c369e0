"""Faults and hostile inputs: damaged map files, kills while saving, a full disk, bad poses,
and memory under repeated searches."""

from __future__ import annotations

import os
import random
import re
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from helpers import make_map

from mf_lpr_ros.config import preset
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.errors import MapFileError
from mf_lpr_ros.live.localiser import Localiser
from mf_lpr_ros.sim.synthetic import scan_world

BIN = os.path.dirname(sys.executable)


SAVER = textwrap.dedent("""
    import sys
    import numpy as np
    from mf_lpr_ros.config import preset
    from mf_lpr_ros.live.map_builder import MapBuilder
    from mf_lpr_ros.live.pose_buffer import PairedScan
    from mf_lpr_ros.core.map_store import ReferenceMap
    from pathlib import Path

    path = Path(sys.argv[1])
    config = preset("kitti")
    existing = ReferenceMap.load(path) if path.exists() else None
    builder = MapBuilder(config, path, reference_map=existing, keep_clouds=True)
    rng = np.random.default_rng(len(builder.map))
    stamp = 1000.0 * len(builder.map)
    while True:
        stamp += 1.0
        pose = np.eye(4)
        pose[0, 3] = stamp * 3.0
        builder.offer(PairedScan(0, stamp, rng.uniform(-20, 20, (20000, 3)).astype(np.float32),
                                 pose))
        print("saved", builder.save(), flush=True)
""")


def test_any_truncation_or_flipped_byte_fails_loudly_at_load(tmp_path, rng):
    path = tmp_path / "a.mfmap"
    original = make_map(rng, n=3, clouds=True)
    original.save(path)
    data = path.read_bytes()
    damaged = tmp_path / "damaged.mfmap"
    for keep in sorted(set(np.linspace(0, len(data) - 1, 150).astype(int))):
        damaged.write_bytes(data[:keep])
        with pytest.raises(MapFileError):
            ReferenceMap.load(damaged)
    for position in sorted(set(np.linspace(0, len(data) - 1, 150).astype(int))):
        flipped = bytearray(data)
        flipped[position] ^= 0x5A
        damaged.write_bytes(bytes(flipped))
        try:
            loaded = ReferenceMap.load(damaged)
        except MapFileError:
            continue
        # Only alignment padding is outside the checksums: the content must be intact.
        assert np.array_equal(loaded.occupancy_bits, original.occupancy_bits)
        assert np.array_equal(loaded.poses, original.poses)
        assert np.array_equal(loaded.cloud(2), original.cloud(2))


def test_empty_and_single_reference_maps(tmp_path, rng, world):
    config = preset("kitti")
    empty = ReferenceMap(config.descriptor)
    empty.save(tmp_path / "empty.mfmap")
    points, _ = scan_world(world, 0.0, 0.0, 0.0, rng)
    result = Localiser(ReferenceMap.load(tmp_path / "empty.mfmap"), config).localise(1.0, points)
    assert result.match is None and not result.accepted

    single = make_map(rng, n=1)
    single.params = config.descriptor
    single.save(tmp_path / "one.mfmap")
    result = Localiser(ReferenceMap.load(tmp_path / "one.mfmap"), config).localise(1.0, points)
    assert result.match is not None and result.match.reference_index == 0


@pytest.mark.slow
def test_sigkill_while_saving_30_times_never_loses_an_acknowledged_reference(tmp_path):
    """The map builder's save path (MapBuilder.save, used by the node) killed at random
    moments; most of its time goes to writing a growing multi-megabyte file."""
    path = tmp_path / "killed.mfmap"
    chooser = random.Random(7)
    acknowledged = 0
    for attempt in range(30):
        process = subprocess.Popen([sys.executable, "-c", SAVER, str(path)],
                                   stdout=subprocess.PIPE, text=True)
        first = process.stdout.readline()              # started and saved at least once
        assert first.startswith("saved"), first
        time.sleep(chooser.uniform(0.0, 0.15))
        process.send_signal(signal.SIGKILL)
        output = first + process.communicate()[0]
        acknowledged = int(re.findall(r"saved (\d+)", output)[-1])
        loaded = ReferenceMap.load(path)
        assert len(loaded) >= acknowledged, f"attempt {attempt}"
        assert loaded.has_clouds and len(loaded.cloud(len(loaded) - 1)) == 20000
    assert acknowledged >= 30
    leftovers = [p.name for p in tmp_path.iterdir() if p.name != "killed.mfmap"]
    assert len(leftovers) <= 1                          # at most the temp file of the last kill


def _rss_mb() -> float:
    with open("/proc/self/statm") as handle:
        return int(handle.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def test_repeated_searches_of_a_large_map_do_not_grow_memory(rng):
    config = preset("kitti")
    reference_map = ReferenceMap(config.descriptor)
    occupancy = rng.random((1000, 120, 120)) < 0.1
    for index in range(1000):
        reference_map.append(occupancy[index], np.eye(4), float(index))
    del occupancy
    localiser = Localiser(reference_map, config)
    query = np.random.default_rng(2).uniform(-20, 20, (30000, 3)).astype(np.float32)
    for _ in range(3):
        localiser.localise(0.0, query)
    before = _rss_mb()
    for _ in range(12):
        localiser.localise(0.0, query)
    assert _rss_mb() - before < 10.0


@pytest.mark.slow
@pytest.mark.realtime
def test_a_20_hz_stream_into_a_slow_localiser_stays_flat_and_fresh():
    """A short run of benchmarks/bench_soak.py (the 10-minute run is in the closing note)."""
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "benchmarks"))
    from bench_soak import soak

    samples = soak(seconds=15.0, references=1500, hz=20.0, sample_every_s=3.0, trace=True,
                   minimum_search_ms=150.0)
    idle = samples.pop()
    retained_mb = idle["traced_mb"]
    last = samples[-1]
    assert last["received"] >= 0.9 * 20 * 15
    assert idle["dropped"] > idle["searched"]     # a 150 ms search drops 2 of every 3 scans...
    assert idle["searched"] + idle["dropped"] == idle["received"]   # ...and drops are counted
    # A backlog or a leak per scan would retain ~3.6 MB/s (20 Hz x 180 kB scans); what Python and
    # numpy objects still hold once idle is measured (RSS swings by ~50 MB with the allocator).
    assert retained_mb < 10.0
    # Fresh: at no sample does a backlog build up. One scan in search, one pending and one being
    # counted in are in flight; a backlog would add ~60 scans per 3 s sample. (Latency, a
    # wall-clock figure, is reported by the benchmark rather than asserted here.)
    assert all(s["received"] - s["searched"] - s["dropped"] <= 4 for s in samples)
