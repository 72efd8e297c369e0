"""The site cloud: stored once, each reference's cloud cut from it, in a map file and back."""

import numpy as np
import pytest
from helpers import PARAMS, make_map

from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.site_cloud import SiteCloud
from mf_lpr_ros.errors import MapFileError


def _site(rng, half_m=20.0, tile_m=16.0):
    # Around the origin so tiles of negative index are cut too.
    points = rng.uniform([-150, -150, -2], [150, 150, 10], size=(60_000, 3))
    return points, SiteCloud.from_points(points, half_m=half_m, tile_m=tile_m)


def _pose(x, y, yaw, z=1.5):
    pose = np.eye(4)
    pose[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    pose[:3, 3] = x, y, z
    return pose


@pytest.mark.parametrize("x, y, yaw", [(0.0, 0.0, 0.0), (-47.3, 31.9, 2.1), (16.0, -16.0, -0.7),
                                       (140.0, 140.0, 1.0)])
def test_a_references_cloud_is_every_site_point_in_its_square_in_its_frame(rng, x, y, yaw):
    points, site = _site(rng)
    pose = _pose(x, y, yaw)
    cut = site.around(pose)
    relative = points - pose[:3, 3]
    inside = (np.abs(relative[:, 0]) < 20.0) & (np.abs(relative[:, 1]) < 20.0)
    assert len(cut) == inside.sum() > 0
    expected = relative[inside] @ pose[:3, :3]
    order = np.lexsort(expected.T)
    np.testing.assert_allclose(cut[np.lexsort(cut.T)], expected[order], atol=1e-3)


def test_a_pose_off_the_site_gets_an_empty_cloud(rng):
    _, site = _site(rng)
    assert site.around(_pose(1000.0, -1000.0, 0.3)).shape == (0, 3)


def test_a_map_with_a_site_cloud_round_trips_and_cuts_each_reference(tmp_path, rng):
    points, site = _site(rng)
    original = make_map(rng)
    original.set_site_cloud(site)
    original.append(np.ones((120, 120), bool), _pose(30.0, -60.0, 1.2), 300.0)
    path = tmp_path / "site.mfmap"
    original.save(path)
    assert int.from_bytes(path.read_bytes()[8:12], "little") == 2
    loaded = ReferenceMap.load(path)
    assert loaded.has_clouds and not loaded.has_reference_clouds
    for index in (0, len(loaded) - 1):
        np.testing.assert_array_equal(loaded.cloud(index), original.cloud(index))
    assert len(loaded.cloud(len(loaded) - 1)) > 800
    assert (loaded.site_cloud.tile_m, loaded.site_cloud.half_m) == (16.0, 20.0)


def test_a_map_without_a_site_cloud_is_still_written_as_version_1(tmp_path, rng):
    path = tmp_path / "plain.mfmap"
    make_map(rng, clouds=True).save(path)
    assert int.from_bytes(path.read_bytes()[8:12], "little") == 1


def test_clouds_come_from_one_source(rng):
    _, site = _site(rng)
    with_clouds = make_map(rng, clouds=True)
    with pytest.raises(ValueError, match="per reference"):
        with_clouds.set_site_cloud(site)
    with_site = ReferenceMap(PARAMS)
    with_site.set_site_cloud(site)
    with pytest.raises(ValueError, match="site cloud"):
        with_site.append(np.ones((120, 120), bool), np.eye(4), 0.0, cloud=np.zeros((5, 3)))


def test_inconsistent_site_arrays_are_refused_by_name(tmp_path, rng):
    _, site = _site(rng)
    offsets = site.tile_offsets.copy()
    offsets[3], offsets[4] = offsets[4], offsets[3]
    broken = ReferenceMap(PARAMS)
    broken.set_site_cloud(SiteCloud(site.points, site.tile_keys, offsets, 16.0, 20.0))
    path = tmp_path / "broken.mfmap"
    broken.save(path)
    with pytest.raises(MapFileError, match="site_tile_offsets must run"):
        ReferenceMap.load(path)
