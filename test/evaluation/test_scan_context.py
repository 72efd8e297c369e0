"""The Scan Context baseline: descriptor, retrieval, yaw."""

import numpy as np
import pytest

from mf_lpr_ros.evaluation.scan_context import ScanContextIndex, ScanContextParams
from mf_lpr_ros.sim.synthetic import scan_world


def turned(points, yaw_deg):
    """The points as a sensor turned by yaw (counter-clockwise) at the same spot sees them."""
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    out = points.copy()
    out[:, 0], out[:, 1] = c * points[:, 0] + s * points[:, 1], -s * points[:, 0] + c * points[:, 1]
    return out


def test_context_keeps_the_highest_point_per_bin():
    index = ScanContextIndex(ScanContextParams(n_rings=4, n_sectors=4, max_range=8.0,
                                               height_offset=1.0))
    points = np.array([[1.0, 0.1, 0.5], [1.5, 0.2, 2.0], [-5.0, -0.1, 0.0], [100.0, 0, 9.0]])
    context = index.describe(points)
    assert context[0, 0] == pytest.approx(3.0)        # ring 0, sector 0: max(1.5, 3.0)
    assert context[2, 1] == pytest.approx(0.0)
    assert context[2, 2] == pytest.approx(1.0)        # x = -5: sector 2 (180 deg), ring 2
    assert np.count_nonzero(context) == 2             # the point beyond max_range is dropped


def test_finds_the_place_and_its_yaw(world):
    rng = np.random.default_rng(0)
    places = [(0, 0, 0.0), (25, 0, 1.0), (0, 25, -2.0), (-25, -10, 2.5), (20, 20, 0.3)]
    index = ScanContextIndex()
    for x, y, yaw in places:
        index.append(scan_world(world, x, y, yaw, rng)[0])
    for reference, (x, y, yaw) in enumerate(places):
        points, _ = scan_world(world, x, y, yaw, rng)
        for turn in (0.0, 42.0, -120.0):
            found, relative_yaw, distance, candidates = index.query(turned(points, turn))
            assert found == reference and candidates[0] == reference
            assert np.degrees(relative_yaw) == pytest.approx(turn, abs=6.1)
            assert distance < 0.2
    # n_active restricts the search.
    assert index.query(scan_world(world, 20, 20, 0.3, rng)[0], n_active=3)[0] < 3
