"""Suites and bulk map building on a Dask LocalCluster give the serial results."""

import json
import math
import os
import signal
import threading
import time

import numpy as np
import pytest

pytest.importorskip("distributed", reason="Dask distributed is not installed (make setup)")

from mf_lpr_ros.cli import main  # noqa: E402
from mf_lpr_ros.config import preset  # noqa: E402
from mf_lpr_ros.core.map_store import ReferenceMap  # noqa: E402
from mf_lpr_ros.datasets import open_source  # noqa: E402
from mf_lpr_ros.errors import UnitFailure
from mf_lpr_ros.evaluation.protocol import Protocol  # noqa: E402
from mf_lpr_ros.evaluation.suite import Rule, Suite, run_suite  # noqa: E402
from mf_lpr_ros.pipeline.bulk import SourceSpec, build_maps  # noqa: E402
from mf_lpr_ros.pipeline.distributed import dask_client, run_units  # noqa: E402
from mf_lpr_ros.pipeline.mapping import build_map  # noqa: E402
from mf_lpr_ros.sim.synthetic import route, write_kitti_sequence  # noqa: E402


@pytest.fixture(scope="module")
def cluster():
    with dask_client("local", 2) as client:
        yield client


def _deterministic(results: dict) -> dict:
    """A suite's results without the timings (they differ run to run)."""
    def strip(value):
        if isinstance(value, dict):
            return {k: strip(v) for k, v in value.items() if not k.startswith("ms_")}
        if isinstance(value, list):
            return [strip(v) for v in value]
        return value
    return strip(results)


def _same(a, b) -> bool:
    """Equal, but for floats: NaN (a figure not taken) equals NaN, and the rest agree to
    float32 precision (a worker process may sum the global scores in another order, which
    moves a distinctiveness, 1 minus a ratio of float32 scores, by a few 1e-7)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, float) and isinstance(b, float):
        return (math.isnan(a) and math.isnan(b)) or math.isclose(a, b, rel_tol=1e-5,
                                                                 abs_tol=1e-6)
    return a == b


def _pairs(out):
    return {path.name: _deterministic(json.loads(path.read_text()))
            for path in sorted((out / "pairs").glob("*.json"))}


@pytest.mark.slow
def test_suite_on_a_cluster_equals_the_serial_run_even_when_a_worker_dies(cluster, world,
                                                                          tmp_path):
    # Three units spread over two workers with one of them killed is what this checks, not any
    # dataset: two short simulated sequences of two laps each (revisits, so closures are
    # published too) take well under half the time of the two small real sets.
    data_dir = tmp_path / "data"
    for seed, name in enumerate(("loop_a", "loop_b")):
        laps = np.concatenate([route(40), route(40, lateral_offset_m=1.0 + seed)])
        write_kitti_sequence(data_dir / name, world, laps, seed=seed)
    second_lap = Protocol(5.0, exclude_recent_frames=30)
    suite = Suite("cluster-check", "two simulated sequences of two laps, three units",
                  (Rule("single", "kitti", second_lap, ("loop_a",)),
                   Rule("single", "default", second_lap, ("loop_b",)),
                   Rule("single", "livox", second_lap, ("loop_b",), label="livox")))
    serial, parallel = tmp_path / "serial", tmp_path / "cluster"
    run_suite(suite, data_dir, serial, methods=["mf-lpr"], progress=False, figures=False)

    pids = list(cluster.run(os.getpid).values())

    def kill_one_worker():
        # Once the first unit has written its result, a worker dies mid-run.
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not list((parallel / "pairs").glob("*.json")):
            time.sleep(0.05)
        os.kill(pids[0], signal.SIGKILL)

    killer = threading.Thread(target=kill_one_worker)
    killer.start()
    try:
        run_suite(suite, data_dir, parallel, methods=["mf-lpr"], progress=False, figures=False,
                  client=cluster)
    except UnitFailure:
        pass                                  # the unit on the killed worker may be lost ...
    killer.join()
    # ... and a resumed run redoes only what is missing.
    run_suite(suite, data_dir, parallel, methods=["mf-lpr"], progress=False, figures=False,
              client=cluster)
    assert _same(_pairs(parallel), _pairs(serial))
    assert len(_pairs(serial)) == 3
    assert all(pair["summary"]["closures_published"] > 0 for pair in _pairs(serial).values())


def test_bulk_build_of_three_sources_equals_three_serial_builds(cluster, world, tmp_path):
    specs = []
    for k in range(3):
        write_kitti_sequence(tmp_path / f"run{k}", world, route(70 + 10 * k, lateral_offset_m=k),
                             seed=k)
        specs.append(SourceSpec(str(tmp_path / f"run{k}")))
    config = preset("kitti")
    on_cluster = build_maps(specs, config, client=cluster, progress=False)
    serial = [build_map(open_source(spec.path), config, progress=False) for spec in specs]
    assert len(on_cluster) == 3
    for bulk, single in zip(on_cluster, serial):
        assert np.array_equal(bulk.occupancy_bits, single.occupancy_bits)
        assert np.array_equal(bulk.poses, single.poses)
        assert np.array_equal(bulk.stamps, single.stamps)
        assert np.array_equal(bulk.source_indices, single.source_indices)
        assert bulk.metadata == single.metadata
    combined = build_maps(specs, config, combine=True, client=cluster, progress=False)[0]
    assert np.array_equal(combined.occupancy_bits,
                          np.concatenate([m.occupancy_bits for m in serial]))
    assert combined.metadata["sources"] == [m.metadata["source"] for m in serial]
    # The CLI: one map each, written like build-map writes one.
    out = tmp_path / "maps"
    assert main(["build-map", "--sources", *[s.path for s in specs], "--one-map-each", "--out",
                 str(out), "--preset", "kitti", "--scheduler", "local", "--quiet"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["run0.mfmap", "run1.mfmap", "run2.mfmap"]


def test_failed_units_are_reported_by_name(cluster):
    def fragile(value):
        if value == 2:
            raise ValueError("no good")
        return value * 10

    with pytest.raises(UnitFailure, match="unit-2: ValueError: no good"):
        run_units(cluster, fragile, [(f"unit-{k}", (k,)) for k in range(4)], progress=False)


def test_global_map_rendered_on_a_cluster_equals_the_one_process_build(cluster, tmp_path):
    from mf_lpr_ros.core.pose import pose_matrix, quaternion_from_yaw
    from mf_lpr_ros.pipeline.global_cloud import write_pcd
    from mf_lpr_ros.pipeline.global_map import RenderParams, build_global_map
    from mf_lpr_ros.sim.scenes import scene_cloud
    from mf_lpr_ros.sim.simulator import urban_traversals

    cloud = scene_cloud(urban_traversals().scene)
    street = cloud[(np.abs(cloud[:, 1]) < 30) & (cloud[:, 0] > 20) & (cloud[:, 0] < 70)]
    mapping = np.stack([pose_matrix(np.array([x, 0.0, 1.8]), quaternion_from_yaw(0.0))
                        for x in np.arange(30.0, 60.0, 2.0)])
    config, render = preset("kitti"), RenderParams(elevation_deg=(-15.0, 15.0))
    alone = build_global_map("town.pcd", config, trajectory=mapping, points=street,
                             render=render, progress=False, workers=1)
    tiles = tmp_path / "tiles"
    tiles.mkdir()
    lines = []
    on_cluster = build_global_map("town.pcd", config, trajectory=mapping, points=street,
                                  render=render, progress=False, client=cluster,
                                  tiles_folder=tiles, report=lines.append)
    assert len(alone) > 20
    np.testing.assert_array_equal(alone.occupancy_bits, on_cluster.occupancy_bits)
    np.testing.assert_array_equal(alone.poses, on_cluster.poses)
    np.testing.assert_array_equal(alone.source_indices, on_cluster.source_indices)
    assert "on 2 workers" in lines[0]
    assert list(tiles.iterdir()) == []                  # the tiles are removed after the build
    # The CLI renders on a cluster of its own with --scheduler local.
    write_pcd(tmp_path / "town.pcd", street)
    np.savetxt(tmp_path / "poses.txt", mapping[:, :3, :].reshape(len(mapping), 12))
    assert main(["build-map", "--global-map", str(tmp_path / "town.pcd"), "--trajectory",
                 str(tmp_path / "poses.txt"), "--preset", "kitti", "--scheduler", "local",
                 "--workers", "2", "--tiles-dir", str(tiles), "--out",
                 str(tmp_path / "grid.mfmap"), "--quiet"]) == 0
    assert len(ReferenceMap.load(tmp_path / "grid.mfmap")) > 20
