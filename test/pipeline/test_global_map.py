"""Global point-cloud maps: accumulate, render references on a grid, relocalise off the path."""

import csv
import gc
import json
import os
import re
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import cKDTree

from mf_lpr_ros.cli import main
from mf_lpr_ros.config import preset
from mf_lpr_ros.core.descriptor import describe_points
from mf_lpr_ros.core.map_store import GLOBAL_MAP_KIND, ReferenceMap
from mf_lpr_ros.core.pose import pose_matrix, quaternion_from_yaw, wrap_angle
from mf_lpr_ros.core.refine import refine_match
from mf_lpr_ros.core.search import MatchedFilterIndex
from mf_lpr_ros.datasets import open_source
from mf_lpr_ros.errors import DatasetError, InvalidCloudError
from mf_lpr_ros.live.map_builder import MapBuilder
from mf_lpr_ros.live.pose_buffer import PairedScan
from mf_lpr_ros.pipeline import global_map
from mf_lpr_ros.pipeline.global_cloud import TiledCloud, accumulate, read_global_cloud, write_pcd
from mf_lpr_ros.pipeline.global_map import (
    RenderParams,
    build_global_map,
    ground_grid,
    reference_positions,
    render_view,
)
from mf_lpr_ros.sim.lidar import cast
from mf_lpr_ros.sim.scenes import scene_cloud
from mf_lpr_ros.sim.simulator import drive, urban_traversals

CONFIG = preset("kitti")
SIM_RENDER = RenderParams(elevation_deg=(-15.0, 15.0))


@pytest.fixture(scope="module")
def town():
    """The simulator's town, its cloud cropped to the bottom street, and scans along it."""
    traversals = urban_traversals()
    cloud = scene_cloud(traversals.scene)
    crop = cloud[(np.abs(cloud[:, 1]) < 35) & (cloud[:, 0] > -25) & (cloud[:, 0] < 125)]
    return traversals, crop


def _pose(x, y, yaw, height=1.8):
    return pose_matrix(np.array([x, y, height]), quaternion_from_yaw(yaw))


def _scan(traversals, x, y, yaw, seed=0):
    return cast(traversals.scene, traversals.sensor, _pose(x, y, yaw), np.random.default_rng(seed))


def test_a_rendered_view_correlates_with_the_scan_as_well_as_a_neighbouring_keyframe(town):
    traversals, _ = town
    # A mapping run every 2 m along the street, accumulated into a global map.
    stations = np.arange(-10.0, 112.0, 2.0)
    clouds = [_scan(traversals, x, 0.0, 0.0, seed=k) for k, x in enumerate(stations)]
    accumulated = np.concatenate([cloud + np.array([x, 0.0, 1.8], dtype=np.float32)
                                  for cloud, x in zip(clouds, stations)])
    tiled = TiledCloud(accumulated, 32.0)
    params = CONFIG.descriptor
    try:
        rendered_scores, keyframe_scores = [], []
        for k in (20, 32, 45):
            query = describe_points(clouds[k], params)
            rendered = describe_points(render_view(tiled, np.array([stations[k], 0.0]), 0.0,
                                                   params, SIM_RENDER, 1.8), params,
                                       reference=True)
            keyframe = describe_points(clouds[k + 1], params, reference=True)
            for reference, pose, scores in ((rendered, _pose(stations[k], 0.0, 0.0),
                                             rendered_scores),
                                            (keyframe, _pose(stations[k + 1], 0.0, 0.0),
                                             keyframe_scores)):
                reference_map = ReferenceMap(params)
                reference_map.append(reference, pose, 0.0)
                scores.append(MatchedFilterIndex(reference_map, CONFIG.search).query(query)
                              .confidence)
        assert np.mean(rendered_scores) >= np.mean(keyframe_scores)
    finally:
        tiled.close()


@pytest.mark.slow
def test_global_grid_relocalises_lanes_the_mapping_run_never_drove(town):
    traversals, cloud = town
    mapping = np.stack([_pose(x, 0.0, 0.0) for x in np.arange(-10.0, 110.0, 2.0)])
    global_map = build_global_map("town.pcd", CONFIG, trajectory=mapping, points=cloud,
                                  render=SIM_RENDER, progress=False)
    assert global_map.metadata["kind"] == GLOBAL_MAP_KIND
    assert global_map.metadata["sensor_height_m"] == pytest.approx(1.8, abs=0.05)
    index = MatchedFilterIndex(global_map, CONFIG.search)
    lanes = np.vstack([drive(np.array([[20.0, 0.0], [90.0, 0.0]]), 10.0, lateral_offset_m=off)
                       for off in (5.5, -6.5)])
    good = 0
    for k, (x, y, yaw) in enumerate(lanes):
        match = index.query(describe_points(_scan(traversals, x, y, yaw, seed=k),
                                            CONFIG.descriptor))
        error = np.hypot(match.pose[0] - x, match.pose[1] - y)
        good += error < 0.5 and abs(np.degrees(wrap_angle(match.pose[2] - yaw))) < 2.0
    assert good >= 0.8 * len(lanes)


def test_the_area_grows_from_the_trajectory_through_free_space_only():
    rng = np.random.default_rng(0)
    ground = np.c_[rng.uniform(0, 60, (40000, 2)), np.zeros(40000)]
    # A wall across x = 30 splits the ground in two.
    wall = np.c_[np.full(3000, 30.0), rng.uniform(0, 60, 3000), rng.uniform(0, 3, 3000)]
    grid = ground_grid(np.vstack([ground, wall]).astype(np.float32), 1.0, (0.4, 2.0))
    seeded = reference_positions(grid, 2.0, np.array([[5.0, 5.0], [10.0, 30.0]]))
    assert len(seeded) and seeded[:, 0].max() < 30.0 and seeded[:, 0].min() < 3.0
    everywhere = reference_positions(grid, 2.0)
    assert everywhere[:, 0].max() > 50.0


def test_accumulate_writes_a_map_the_renderer_reads(tmp_path, world):
    from mf_lpr_ros.sim.synthetic import route, write_kitti_sequence

    write_kitti_sequence(tmp_path / "seq", world, route(12), seed=1)
    assert main(["accumulate", str(tmp_path / "seq"), "--out", str(tmp_path / "map.pcd"),
                 "--voxel", "0.3", "--quiet"]) == 0
    cloud = read_global_cloud(tmp_path / "map.pcd")
    direct = accumulate(open_source(tmp_path / "seq"), 0.3, progress=False)
    assert len(cloud) == len(direct) > 1000
    keys = np.unique(np.floor(cloud / 0.3).astype(np.int64), axis=0)
    assert len(keys) == len(cloud)                       # one point per voxel
    assert main(["build-map", "--global-map", str(tmp_path / "map.pcd"), "--trajectory",
                 str(tmp_path / "seq" / "poses.txt"), "--out", str(tmp_path / "g.mfmap"),
                 "--preset", "kitti", "--quiet"]) == 0
    reference_map = ReferenceMap.load(tmp_path / "g.mfmap")
    assert reference_map.metadata["kind"] == GLOBAL_MAP_KIND and len(reference_map) > 50


def test_bad_global_clouds_are_refused_by_name(tmp_path):
    write_pcd(tmp_path / "nan.pcd", np.full((10, 3), np.nan, dtype=np.float32))
    with pytest.raises(InvalidCloudError, match="no finite point"):
        read_global_cloud(tmp_path / "nan.pcd")
    (tmp_path / "cut.pcd").write_bytes((tmp_path / "nan.pcd").read_bytes()[:-20])
    with pytest.raises(DatasetError, match="truncated"):
        read_global_cloud(tmp_path / "cut.pcd")
    (tmp_path / "map.xyz").write_text("1 2 3\n")
    with pytest.raises(DatasetError, match=".pcd or .ply"):
        read_global_cloud(tmp_path / "map.xyz")
    assert main(["build-map", "--global-map", str(tmp_path / "nan.pcd"), "--out",
                 str(tmp_path / "m.mfmap")]) == 2
    assert not (tmp_path / "m.mfmap").exists()
    flat = np.c_[np.random.default_rng(0).uniform(0, 5, (200, 2)), np.zeros(200)]
    with pytest.raises(ValueError, match="auto"):
        build_global_map("x.pcd", preset("auto"), points=flat.astype(np.float32),
                         progress=False)


def test_a_narrow_field_of_view_renders_wedges_facing_round_the_circle(town):
    traversals, cloud = town
    render = RenderParams(spacing_m=6.0, horizontal_fov_deg=70.0)
    headings = render.headings()
    assert len(headings) == 11 and np.diff(headings).max() <= np.radians(35.0) + 1e-9
    mapping = np.stack([_pose(x, 0.0, 0.0) for x in np.arange(20.0, 60.0, 2.0)])
    wide = build_global_map("town.pcd", CONFIG, trajectory=mapping, points=cloud,
                            render=RenderParams(spacing_m=6.0), progress=False)
    narrow = build_global_map("town.pcd", CONFIG, trajectory=mapping, points=cloud,
                              render=render, progress=False)
    assert len(narrow) > 5 * len(wide)
    yaws = np.arctan2(narrow.poses[:, 1, 0], narrow.poses[:, 0, 0]) % (2 * np.pi)
    assert np.allclose(np.unique(np.round(yaws, 6)), np.round(headings, 6))
    # A wedge holds fewer cells than the full view, all within the field of view.
    first = narrow.occupancy(0)
    rows, cols = np.nonzero(first)
    off_axis = np.degrees(np.abs(np.arctan2(rows - 59.5, cols - 59.5)))
    assert first.sum() < wide.occupancy(0).sum() and off_axis.max() <= 35.0 + 3.0


def test_a_compressed_global_map_builds_as_its_binary_twin(town, tmp_path):
    o3d = pytest.importorskip("open3d")
    pytest.importorskip("lzf", reason="python-neo-lzf (make setup installs it)")
    _, cloud = town
    crop = cloud[(cloud[:, 0] > 28) & (cloud[:, 0] < 52) & (np.abs(cloud[:, 1]) < 15)]
    write_pcd(tmp_path / "binary.pcd", crop)
    twin = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(
        read_global_cloud(tmp_path / "binary.pcd").astype(np.float64)))
    assert o3d.io.write_point_cloud(str(tmp_path / "compressed.pcd"), twin, compressed=True)
    mapping = np.stack([_pose(x, 0.0, 0.0) for x in np.arange(32.0, 48.0, 2.0)])
    maps = [build_global_map(tmp_path / name, CONFIG, trajectory=mapping, render=SIM_RENDER,
                             progress=False) for name in ("binary.pcd", "compressed.pcd")]
    assert len(maps[0]) == len(maps[1]) > 5
    np.testing.assert_array_equal(maps[0].occupancy_bits, maps[1].occupancy_bits)
    np.testing.assert_allclose(maps[0].poses, maps[1].poses)


def test_rendering_workers_build_the_map_one_process_builds(town):
    _, cloud = town
    crop = cloud[(cloud[:, 0] > 20) & (cloud[:, 0] < 70)]
    mapping = np.stack([_pose(x, 0.0, 0.0) for x in np.arange(30.0, 60.0, 2.0)])
    lines = []
    alone = build_global_map("town.pcd", CONFIG, trajectory=mapping, points=crop,
                             render=SIM_RENDER, progress=False, workers=1)
    shared = build_global_map("town.pcd", CONFIG, trajectory=mapping, points=crop,
                              render=SIM_RENDER, progress=False, workers=2, report=lines.append)
    assert len(alone) > 20
    np.testing.assert_array_equal(alone.occupancy_bits, shared.occupancy_bits)
    np.testing.assert_array_equal(alone.poses, shared.poses)
    np.testing.assert_array_equal(alone.source_indices, shared.source_indices)
    # The estimate made before rendering names the positions and the references to come.
    assert len(lines) == 1
    assert f"rendering {len(alone)} positions x 1 headings: ~{len(alone)} references" in lines[0]
    assert "on 2 workers" in lines[0]


class _FinalisedWhere:
    """Appends the pid of the process that finalises it to a file: an object bound to the
    state of the process that made it (a ROS context, a device handle) must not be finalised
    in a forked copy of that process."""

    def __init__(self, log_path):
        self.log_path = log_path
        self.cycle = self

    def __del__(self):
        with open(self.log_path, "a") as log:
            log.write(f"{os.getpid()}\n")


_RENDER_POSITIONS = global_map._render_positions


def _collect_then_render(indices, renderer=None):
    """A worker's task that runs a full garbage collection first, as a worker's collector may
    at any allocation."""
    gc.collect()
    return _RENDER_POSITIONS(indices, renderer)


def test_rendering_workers_never_finalise_what_the_building_process_left(town, tmp_path,
                                                                         monkeypatch):
    """The workers are forked: garbage the building process had not collected yet (cycles)
    is finalised in that process before the fork, and a worker's collector never touches the
    objects it inherits. Before, a worker's collector finalised such garbage in its copy of the
    process, and in a test process that had run ROS and torch tests a worker crashed so."""
    _, cloud = town
    crop = cloud[(cloud[:, 0] > 20) & (cloud[:, 0] < 40)]
    mapping = np.stack([_pose(x, 0.0, 0.0) for x in np.arange(24.0, 36.0, 2.0)])
    log_path = tmp_path / "finalised.txt"
    monkeypatch.setattr(global_map, "_render_positions", _collect_then_render)
    # The collector paused, so that the garbage is still there when the workers fork.
    gc.disable()
    try:
        for _ in range(20):
            _FinalisedWhere(log_path)
        build_global_map("town.pcd", CONFIG, trajectory=mapping, points=crop, render=SIM_RENDER,
                         progress=False, workers=2)
    finally:
        gc.enable()
    gc.collect()
    assert log_path.read_text().split() == [str(os.getpid())] * 20


def test_a_pickled_tiled_cloud_opens_the_same_file_and_names_it_when_it_is_gone(tmp_path):
    import pickle

    points = np.random.default_rng(1).uniform(-40, 40, (5000, 3)).astype(np.float32)
    tiled = TiledCloud(points, 8.0, tmp_path)
    handle = pickle.dumps(tiled)
    assert len(handle) < 2000                           # a handle, not the points
    reopened = pickle.loads(handle)
    np.testing.assert_array_equal(reopened.near(3.0, -5.0, 12.0), tiled.near(3.0, -5.0, 12.0))
    reopened.close()                                    # a handle never removes the file
    assert tiled.near(0.0, 0.0, 50.0).shape == (3, 5000)
    (path,) = tmp_path.glob("mf_lpr_tiles_*/columns.f32")
    with open(path, "r+b") as handle_file:
        handle_file.truncate(1000)
    with pytest.raises(InvalidCloudError, match="holds 1000 bytes, 60000 expected"):
        pickle.loads(handle)
    tiled.close()
    assert not path.exists()
    with pytest.raises(InvalidCloudError, match=r"not on this machine.*--tiles-dir"):
        pickle.loads(handle)


def test_open_ground_beyond_reach_of_any_structure_is_not_rendered(town):
    _, cloud = town
    rng = np.random.default_rng(4)
    street = cloud[(cloud[:, 0] > 20) & (cloud[:, 0] < 60) & (np.abs(cloud[:, 1]) < 20)]
    # A bare hillside east of the street, 40-160 m from the nearest building: no obstacle,
    # but the slope ahead rises into the descriptor's height band, so every view of it holds
    # something, and nothing to tell one position from the next.
    xy = rng.uniform(100, 220, (60000, 2)) + [0, -60]
    field = np.c_[xy, 0.1 * (xy[:, 0] - 100)]
    points = np.concatenate([street, field.astype(np.float32)])
    reach = CONFIG.descriptor.extent_m / 2
    limited = build_global_map("town.pcd", CONFIG, points=points, progress=False, workers=1,
                               render=RenderParams(spacing_m=6.0, elevation_deg=(-15.0, 15.0)))
    unlimited = build_global_map("town.pcd", CONFIG, points=points, progress=False, workers=1,
                                 render=RenderParams(spacing_m=6.0, elevation_deg=(-15.0, 15.0),
                                                     reach_m=np.inf))
    far = limited.poses[:, 0, 3] > 60 + reach + 6.0
    assert not far.any()
    assert (unlimited.poses[:, 0, 3] > 60 + reach + 6.0).sum() > 100
    with pytest.raises(ValueError, match="reach_m"):
        RenderParams(reach_m=0.0)


@pytest.mark.slow
def test_a_narrow_sensor_relocalises_on_a_grid_recording_a_long_query_window(town, tmp_path):
    """docs/CLI.md's recipe for a narrow sensor: the grid records a query window, and `localise`
    describes each 70-degree scan together with the last 20 m of them, as a rendered view sees
    all round. Alone, the scans of a lane beside the mapping drive rarely find their place."""
    traversals, cloud = town
    write_pcd(tmp_path / "town.pcd", cloud)
    mapping = np.stack([_pose(x, 0.0, 0.0) for x in np.arange(-10.0, 110.0, 2.0)])
    np.savetxt(tmp_path / "mapping.txt", mapping[:, :3, :4].reshape(-1, 12))
    lane = drive(np.array([[10.0, 0.0], [100.0, 0.0]]), 1.0, lateral_offset_m=5.5)
    (tmp_path / "lane" / "velodyne").mkdir(parents=True)
    for k, (x, y, yaw) in enumerate(lane):
        points = _scan(traversals, x, y, yaw, seed=k)
        forward = np.abs(np.degrees(np.arctan2(points[:, 1], points[:, 0]))) < 35.0
        records = np.zeros((forward.sum(), 4), dtype="<f4")
        records[:, :3] = points[forward]
        records.tofile(tmp_path / "lane" / "velodyne" / f"{k:06d}.bin")
    np.savetxt(tmp_path / "lane" / "poses.txt",
               np.stack([_pose(x, y, yaw)[:3, :4].ravel() for x, y, yaw in lane]))
    np.savetxt(tmp_path / "lane" / "times.txt", np.arange(len(lane)) * 0.5)
    within_1m = {}
    for window_m in (0.0, 20.0):
        config = tmp_path / f"window_{window_m:g}.yaml"
        config.write_text(
            "/**:\n  ros__parameters:\n    preset: kitti\n    descriptor:\n"
            f"      submap_m: {window_m}\n      submap_max_scans: 400\n"
            "      submap_max_age_s: 300.0\n")
        grid, results = tmp_path / f"grid_{window_m:g}.mfmap", tmp_path / f"{window_m:g}.csv"
        assert main(["build-map", "--global-map", str(tmp_path / "town.pcd"), "--trajectory",
                     str(tmp_path / "mapping.txt"), "--out", str(grid), "--config", str(config),
                     "--sensor-height-m", "1.8", "--quiet"]) == 0
        assert ReferenceMap.load(grid).params.submap_m == window_m
        assert main(["localise", str(grid), str(tmp_path / "lane"), "--out", str(results),
                     "--config", str(config), "--quiet"]) == 0
        with results.open() as table:
            # Scored once the window holds its 20 m (the lane starts at x = 10).
            errors = [float(row["translation_error_m"]) for row in csv.DictReader(table)
                      if float(row["gt_x"]) >= 40.0]
        within_1m[window_m] = np.mean(np.array(errors) <= 1.0)
    assert within_1m[20.0] >= 0.6 and within_1m[20.0] >= within_1m[0.0] + 0.3, within_1m


def test_a_grid_that_verifies_by_icp_keeps_the_global_cloud_around_each_reference(town,
                                                                                  tmp_path,
                                                                                  capsys):
    """Each reference's cloud is the global cloud around it in the reference's frame, cut from
    one site cloud the map stores once, so ICP verifies a match against the map: a scan of
    the mapped street passes, a scan of another street, matched to the same grid, does
    not."""
    pytest.importorskip("open3d")
    traversals, cloud = town
    verifying = replace(CONFIG, search=replace(CONFIG.search, verify_fitness=0.68))
    mapping = np.stack([_pose(x, 0.0, 0.0) for x in np.arange(30.0, 70.0, 2.0)])
    render = RenderParams(spacing_m=6.0, elevation_deg=(-15.0, 15.0))
    with_clouds, without = [], []
    grid = build_global_map("town.pcd", verifying, trajectory=mapping, points=cloud,
                            render=render, progress=False, workers=1, report=with_clouds.append)
    assert grid.has_clouds
    assert not build_global_map("town.pcd", CONFIG, trajectory=mapping, points=cloud,
                                render=render, progress=False, workers=1,
                                report=without.append).has_clouds
    # The estimate made before rendering counts the site cloud the map will hold.
    megabytes = [float(re.search(r"~(\d+) MB of map", line).group(1))
                 for line in with_clouds + without]
    assert grid.site_cloud.nbytes > 2e6
    assert abs(megabytes[0] - megabytes[1] - grid.site_cloud.nbytes / 1e6) <= 1.0, megabytes
    # A reference's cloud, moved by the reference's pose, lies on the global cloud.
    pose = grid.poses[len(grid) // 2]
    world = grid.cloud(len(grid) // 2) @ pose[:3, :3].T + pose[:3, 3]
    assert len(world) > 1000
    assert np.percentile(cKDTree(cloud[:, :3]).query(world)[0], 99) < 0.05
    half = verifying.descriptor.extent_m / 2 + verifying.search.max_shift_m
    assert np.abs(world[:, :2] - pose[:2, 3]).max() < half + 1e-3
    # Stored once: the references' clouds together repeat each stored point many times.
    stored = len(grid.site_cloud.points)
    assert sum(len(grid.cloud(k)) for k in range(len(grid))) > 3 * stored
    grid.save(tmp_path / "grid.mfmap")
    loaded = ReferenceMap.load(tmp_path / "grid.mfmap")
    np.testing.assert_array_equal(loaded.cloud(len(grid) // 2), grid.cloud(len(grid) // 2))
    assert main(["info", str(tmp_path / "grid.mfmap")]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["keeps_clouds"] and info["site_cloud_points"] == stored
    # A scan the map builder adds to the grid gets its cloud from the site cloud too.
    extender = MapBuilder(verifying, None, reference_map=loaded)
    added = extender.offer(PairedScan(0, 1.0, _scan(traversals, 41.0, 0.5, 0.2, seed=3),
                                      _pose(41.0, 0.5, 0.2)))
    assert added == len(grid) and len(extender.map.cloud(added)) > 1000

    index = MatchedFilterIndex(grid, verifying.search)

    def fitness(x, y, yaw):
        points = _scan(traversals, x, y, yaw, seed=5)
        match = index.query(describe_points(points, verifying.descriptor))
        return refine_match(match, points, grid).fitness

    assert fitness(47.0, 1.0, 0.3) >= 0.68 and fitness(35.0, -2.0, 1.0) >= 0.68
    assert fitness(50.0, 100.0, 0.0) < 0.68 and fitness(100.0, 70.0, 1.0) < 0.68
