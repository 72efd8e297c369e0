import numpy as np
import pytest

from mf_lpr_ros.core.descriptor import (
    TurnedPooling,
    auto_voxel_size,
    cap_patches,
    describe_density_image,
    describe_points,
    filter_points,
    finite_rows,
    footprint,
    height_density,
    one_point_per_voxel,
    pool,
    pooled_weights,
    quarter_turn_roots,
    rotate_occupancy,
    rows_where,
    weighted,
)
from mf_lpr_ros.errors import InvalidCloudError
from mf_lpr_ros.params import DescriptorParams

PARAMS = DescriptorParams(voxel_size=0.5, density_threshold=1.0)


def column_at(x, y, heights=(0.0, 0.6, 1.2)):
    return np.array([[x, y, z] for z in heights])


def test_axis_convention_rows_are_y_columns_are_x():
    hdm = height_density(np.concatenate([column_at(10.2, 0.1), column_at(0.1, -5.2)]), PARAMS)
    # x = 10.2 m -> column floor(20.4) + 60 = 80, row of y = 0.1 -> 60.
    assert hdm[60, 80] == 3
    # y = -5.2 m -> row floor(-10.4) + 60 = 49, column of x = 0.1 -> 60.
    assert hdm[49, 60] == 3
    assert hdm.sum() == 6


def test_voxel_mode_counts_occupied_voxels_points_mode_counts_points():
    cloud = np.concatenate([column_at(1.0, 1.0, heights=(0.1, 0.2, 0.3, 0.9))] * 3)
    voxels = height_density(cloud, PARAMS)
    points = height_density(cloud, DescriptorParams(voxel_size=0.5, density_mode="points"))
    assert voxels[62, 62] == 2  # two 0.5 m voxels: z in [0, 0.5) and [0.5, 1.0)
    assert points[62, 62] == 12


def test_threshold_nan_and_height_band():
    cloud = np.concatenate([column_at(3.0, 3.0), column_at(-3.0, 3.0, heights=(0.0,)),
                            [[np.nan, 1.0, 0.0], [np.inf, 0.0, 0.0]],
                            column_at(0.0, -3.0, heights=(5.0, 5.6, 6.2))])
    occupancy = describe_points(cloud, DescriptorParams(voxel_size=0.5, z_max=4.0))
    assert occupancy[66, 66]  # three voxels > threshold 1
    assert not occupancy[66, 54]  # one voxel is not > 1
    assert not occupancy[54, 60]  # above z_max
    assert occupancy.sum() == 1


def test_filter_drops_every_non_finite_coordinate_and_keeps_the_range_and_disc():
    good = [[1.0, 2.0, 0.5], [9.9, 0.0, 100.0]]
    broken = [[np.nan, 1.0, 0.0], [1.0, -np.inf, 0.0], [1.0, 1.0, np.nan], [1.0, 1.0, np.inf],
              [0.0, 0.0, -np.inf]]
    kept = filter_points(np.array(good + broken), DescriptorParams(voxel_size=0.5))
    np.testing.assert_array_equal(kept, good)
    # 10.0 m and the window's half side (30 m) are limits: inside on one side, out on the other.
    cloud = np.array([[6.0, 8.0, 0.0], [6.0, 8.01, 0.0], [29.9, 0.0, 0.0], [21.3, 21.3, 0.0]])
    assert len(filter_points(cloud, DescriptorParams(voxel_size=0.5, max_range=10.0))) == 1
    np.testing.assert_array_equal(filter_points(cloud, DescriptorParams(voxel_size=0.5)),
                                  cloud[:3])
    assert len(filter_points(cloud, DescriptorParams(voxel_size=0.5, crop="square"))) == 4


def test_occupied_voxels_are_counted_per_column_over_every_level(rng):
    # A tall cloud (a submap's ~60 levels of 0.5 m) and a few columns crowded with points: each
    # cell counts the distinct voxels above it, however many points share one.
    cloud = np.concatenate([rng.uniform([-29, -29, -3], [29, 29, 27], (20000, 3)),
                            rng.uniform([2.0, 2.0, 0.0], [2.4, 2.4, 9.9], (3000, 3))])
    params = DescriptorParams(voxel_size=0.5, crop="square")
    voxels = {(int(np.floor(y / 0.5)) + 60, int(np.floor(x / 0.5)) + 60, int(np.floor(z / 0.5)))
              for x, y, z in cloud}
    expected = np.zeros((120, 120))
    for row, col, _ in voxels:
        expected[row, col] += 1
    density = height_density(cloud, params)
    np.testing.assert_array_equal(density, expected)
    assert density[64, 64] == 20


def test_the_rows_kept_are_those_boolean_indexing_keeps(rng):
    points = rng.normal(size=(1000, 4)).astype(np.float32)
    for column, bad in enumerate((np.nan, np.inf, -np.inf)):
        points[rng.choice(1000, 40, replace=False), column] = bad
    # A non-finite intensity does not make a point unusable: only x, y and z are tested.
    points[rng.choice(1000, 40, replace=False), 3] = np.nan
    finite = finite_rows(points)
    np.testing.assert_array_equal(finite, np.isfinite(points[:, :3]).all(axis=1))
    assert 800 < finite.sum() < 900
    np.testing.assert_array_equal(rows_where(points, finite), points[finite])
    with pytest.raises(ValueError, match="999 entries for 1000 rows"):
        rows_where(points, finite[:-1])
    kept = filter_points(points, DescriptorParams(voxel_size=0.5, crop="square"))
    np.testing.assert_array_equal(kept, points[finite][:, :3].astype(np.float64))
    assert kept.dtype == np.float64 and kept.shape == (finite.sum(), 3)


def test_one_point_is_kept_per_voxel_the_first_in_order(rng):
    points = rng.uniform(-5, 5, (5000, 3))
    kept = one_point_per_voxel(points, 0.5)
    first = {}
    for index, point in enumerate(points):
        first.setdefault(tuple(np.floor(point / 0.5).astype(int)), index)
    np.testing.assert_array_equal(kept, points[sorted(first.values())])


def test_empty_or_all_nan_cloud_is_refused():
    with pytest.raises(InvalidCloudError, match="no finite point"):
        describe_points(np.full((10, 3), np.nan), PARAMS)
    with pytest.raises(InvalidCloudError, match="shape"):
        describe_points(np.zeros((10, 2)), PARAMS)


def test_patch_cap_limits_each_patch_and_is_seeded(rng):
    occupancy = rng.random((120, 120)) < 0.6
    capped = cap_patches(occupancy, PARAMS, seed=5)
    per_patch = capped.reshape(12, 10, 12, 10).sum(axis=(1, 3))
    original = occupancy.reshape(12, 10, 12, 10).sum(axis=(1, 3))
    assert np.all(per_patch == np.minimum(original, 20))
    assert not np.any(capped & ~occupancy)
    assert np.array_equal(capped, cap_patches(occupancy, PARAMS, seed=5))
    assert not np.array_equal(capped, cap_patches(occupancy, PARAMS, seed=6))


def test_reference_descriptor_is_reproducible_per_scan(world):
    cloud = world.points[np.hypot(*world.points[:, :2].T) < 25]
    a = describe_points(cloud, PARAMS, reference=True, seed_key=4)
    b = describe_points(cloud, PARAMS, reference=True, seed_key=4)
    query = describe_points(cloud, PARAMS)
    assert np.array_equal(a, b)
    assert a.sum() < query.sum()


def test_weights_and_pooling():
    occupancy = np.zeros((4, 4), dtype=bool)
    occupancy[0, 0] = True
    image = weighted(occupancy, -0.15)
    assert image[0, 0] == 1.0 and image[3, 3] == pytest.approx(-0.15)
    low = pool(image, 2)
    assert low.shape == (2, 2)
    assert low[0, 0] == pytest.approx((1 - 0.45) / 4)
    assert low[1, 1] == pytest.approx(-0.15)


@pytest.mark.parametrize("unoccupied_weight", [-0.3, -0.15, -0.05, 0.0])
def test_weights_are_exactly_one_the_unoccupied_weight_or_zero(unoccupied_weight):
    # Exact, not approximate: occupied cells must weigh 1.0 to the bit for any weight (an
    # arithmetic w + (1 - w) * occupancy gives 0.99999994 at -0.3).
    rng = np.random.default_rng(7)
    occupancy, covered = rng.random((3, 20, 20)) < 0.3, rng.random((20, 20)) < 0.7
    w = np.float32(unoccupied_weight)
    image = weighted(occupancy, unoccupied_weight)
    assert image.dtype == np.float32
    assert np.array_equal(image, np.where(occupancy, np.float32(1.0), w))
    footprinted = weighted(occupancy, unoccupied_weight, covered)
    expected = np.where(occupancy & covered, np.float32(1.0), np.where(covered, w, 0))
    assert np.array_equal(footprinted, expected)
    assert not np.signbit(footprinted[:, ~covered]).any()


@pytest.mark.parametrize("factor", [1, 2, 3])
def test_pooled_weights_equal_pooling_the_weights(factor):
    occupancy = np.random.default_rng(factor).random((5, 12, 12)) < 0.3
    np.testing.assert_allclose(pooled_weights(occupancy, -0.2, factor),
                               pool(weighted(occupancy, -0.2), factor), atol=1e-6)


def test_rotation_is_counter_clockwise_about_the_sensor():
    cloud = column_at(10.2, 0.2)
    occupancy = describe_points(cloud, PARAMS)
    rotated = rotate_occupancy(occupancy, np.array([90.0]))[0]
    expected = describe_points(column_at(-0.2, 10.2), PARAMS)
    assert np.array_equal(rotated, expected)
    assert np.array_equal(rotate_occupancy(occupancy, np.array([0.0]))[0], occupancy)


def test_a_few_angles_of_a_set_turn_as_the_whole_set_does():
    occupancy = np.random.default_rng(3).random((PARAMS.size, PARAMS.size)) < 0.2
    angles = np.arange(0.0, 360.0, 5.0)
    only = np.array([71, 3, 40])
    assert np.array_equal(rotate_occupancy(occupancy, angles, only),
                          rotate_occupancy(occupancy, angles)[only])
    # A set turned once, its table not kept, turns only to those angles and alike.
    odd = angles + 1.7
    assert np.array_equal(rotate_occupancy(occupancy, odd, only, cached=False),
                          rotate_occupancy(occupancy, odd)[only])


@pytest.mark.parametrize("size", [9, 10, 31])
def test_each_cell_takes_the_cell_it_turns_from_and_cells_from_outside_are_unoccupied(size):
    """Nearest-neighbour inverse mapping, cell by cell: the output cell at p takes the input at
    R(-theta) p; a source outside the window, on any side, leaves the cell unoccupied."""
    rng = np.random.default_rng(size)
    occupancy = rng.random((size, size)) < 0.5
    angles = np.concatenate([rng.uniform(-400.0, 400.0, 6), [0.0, 45.0, 90.0, 181.3]])
    turned = rotate_occupancy(occupancy, angles, cached=False)
    from_outside = 0
    for a, angle in enumerate(angles):
        cos, sin = np.cos(np.deg2rad(angle)), np.sin(np.deg2rad(angle))
        for row in range(size):
            for col in range(size):
                x, y = col - size / 2 + 0.5, row - size / 2 + 0.5
                source_col = int(np.floor(cos * x + sin * y + size / 2))
                source_row = int(np.floor(-sin * x + cos * y + size / 2))
                inside = 0 <= source_col < size and 0 <= source_row < size
                from_outside += not inside
                expected = inside and occupancy[source_row, source_col]
                assert turned[a, row, col] == expected, (angle, row, col)
    assert from_outside > 0
    assert np.array_equal(rotate_occupancy(occupancy, angles), turned)


@pytest.mark.parametrize("size,step", [(120, 5.0), (100, 10.0), (60, 7.5)])
def test_a_heading_is_its_roots_rotation_turned_by_rot90_cell_for_cell(size, step):
    angles = np.arange(0.0, 360.0, step)
    roots, turns = quarter_turn_roots(size, angles)
    occupancy = np.random.default_rng(5).random((size, size)) < 0.2
    turned = rotate_occupancy(occupancy, angles)
    for heading, (root, quarter_turns) in enumerate(zip(roots, turns)):
        assert np.array_equal(turned[heading], np.rot90(turned[root], -quarter_turns))
        assert turns[root] == 0 and (quarter_turns == 0) == (root == heading)
        if quarter_turns:
            assert (angles[heading] - angles[root]) % 360.0 == 90.0 * quarter_turns
    # The first quarter of the circle holds every root but a few 45-degree multiples, whose
    # tables put some cells across an edge from where rot90 puts them.
    first_quarter = np.flatnonzero(angles < 90.0)
    assert set(first_quarter) <= set(np.flatnonzero(turns == 0))
    assert (turns == 0).sum() <= len(first_quarter) + 4


def test_headings_no_quarter_turn_apart_are_each_their_own_root():
    angles = np.arange(0.0, 360.0, 7.0)
    roots, turns = quarter_turn_roots(120, angles)
    assert np.array_equal(roots, np.arange(len(angles))) and not turns.any()


def test_density_image_matches_point_descriptor():
    cloud = np.concatenate([column_at(x, y) for x, y in [(4.2, -7.7), (-12.3, 3.3), (0.2, 0.2)]])
    hdm = height_density(cloud, PARAMS)
    from_image = describe_density_image(hdm, 0.5, PARAMS)
    assert np.array_equal(from_image, describe_points(cloud, PARAMS))
    # A finer source image resampled to the descriptor grid keeps the occupied cells.
    fine = np.kron(hdm, np.ones((2, 2)))
    assert np.array_equal(describe_density_image(fine, 0.25, PARAMS), from_image)


def test_auto_voxel_size_follows_the_papers_rule(rng):
    dense = [rng.uniform(-30, 30, (200000, 3)) * np.array([1, 1, 0.1])]
    sparse = [rng.uniform(-10, 10, (300, 3))]
    assert auto_voxel_size(dense) < auto_voxel_size(sparse)
    assert 0.2 <= auto_voxel_size(dense) <= 0.5


def test_disc_crop_covers_the_same_ground_at_every_heading(world):
    # Turning the sensor by 45 degrees: the square window's corners then hold other parts of
    # the scene; the inscribed disc holds the same ground.
    from mf_lpr_ros.sim.synthetic import scan_world

    rng = np.random.default_rng(3)
    points, _ = scan_world(world, 5.0, -3.0, 0.0, rng)
    turn = np.deg2rad(45.0)
    rotation = np.array([[np.cos(turn), np.sin(turn), 0], [-np.sin(turn), np.cos(turn), 0],
                         [0, 0, 1]])
    turned = points[:, :3] @ rotation.T

    def mismatch(crop):
        params = DescriptorParams(voxel_size=0.4, z_min=-1.2, crop=crop)
        upright = describe_points(points, params)
        back = rotate_occupancy(describe_points(turned, params), np.array([45.0]))[0]
        return np.logical_xor(upright, back).sum() / upright.sum()

    disc, square = mismatch("disc"), mismatch("square")
    assert disc < 0.8 * square  # both lose cells to resampling; the square also its corners
    disc_params = DescriptorParams(voxel_size=0.4, z_min=-1.2, crop="disc")
    assert not (describe_points(points, disc_params) & ~footprint(disc_params)).any()


def test_cells_outside_the_footprint_weigh_nothing():
    params = DescriptorParams(crop="disc")
    covered = footprint(params)
    occupancy = np.random.default_rng(4).random((3, 120, 120)) < 0.2
    image = weighted(occupancy, -0.15, covered)
    assert np.all(image[:, ~covered] == 0)
    assert np.all(image[:, covered & ~occupancy[0]][0] == np.float32(-0.15))
    np.testing.assert_allclose(pooled_weights(occupancy, -0.15, 2, covered),
                               pool(image, 2), atol=1e-6)
    assert footprint(DescriptorParams(crop="square")) is None
    assert covered[60, 60] and not covered[0, 0] and covered[0, 60]


@pytest.mark.parametrize("crop", ["disc", "square"])
@pytest.mark.parametrize("fill", [0.0, 0.02, 0.12, 1.0])
def test_turned_pooling_gives_the_numbers_of_turning_then_pooling(crop, fill):
    params = DescriptorParams(voxel_size=0.4, crop=crop)
    covered = footprint(params)
    angles = np.arange(0.0, 360.0, 5.0)
    turned_pooling = TurnedPooling(params.size, angles, params.pool, params.unoccupied_weight,
                                   covered)
    occupancy = np.random.default_rng(3).random((params.size,) * 2) < fill
    expected = pooled_weights(rotate_occupancy(occupancy, angles), params.unoccupied_weight,
                              params.pool, covered)
    got = turned_pooling(occupancy)
    assert got.dtype == expected.dtype
    assert np.array_equal(got, expected)
