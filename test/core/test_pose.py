"""Planar pose algebra: the covariance of a composed pose, and one that encloses two."""

from __future__ import annotations

import math

import numpy as np

from mf_lpr_ros.core.pose import (
    compose_planar,
    composed_covariance,
    enclosing_covariance,
    wrap_angle,
)


def test_a_composed_poses_covariance_matches_sampled_compositions():
    """first (+) second with both uncertain: the first-order covariance equals that of many
    sampled compositions. A heading error of first swings the composed pose about first's
    position (40 m away here, so it dominates x and y), which a sum of the two covariances
    misses."""
    rng = np.random.default_rng(0)
    first, second = np.array([5.0, -3.0, 0.4]), np.array([30.0, 26.0, -0.3])
    first_covariance = np.array([[0.04, 0.01, 0.0], [0.01, 0.09, 0.002],
                                 [0.0, 0.002, math.radians(0.5) ** 2]])
    second_covariance = np.diag([0.16, 0.01, math.radians(1.0) ** 2])
    composed = compose_planar(first, second)
    samples = compose_planar(rng.multivariate_normal(first, first_covariance, 200_000),
                             rng.multivariate_normal(second, second_covariance, 200_000))
    deviation = samples - composed
    deviation[:, 2] = wrap_angle(deviation[:, 2])
    sampled = deviation.T @ deviation / len(samples)
    expected = composed_covariance(first, first_covariance, composed, second_covariance)
    assert np.allclose(expected, expected.T)
    assert np.allclose(expected, sampled, rtol=0.03, atol=1e-5)
    assert not np.allclose(first_covariance + second_covariance, sampled, rtol=0.3)


def _dominates(larger: np.ndarray, smaller: np.ndarray) -> bool:
    """larger's ellipsoid contains smaller's: larger - smaller is positive semi-definite."""
    return bool(np.linalg.eigvalsh(larger - smaller).min() > -1e-12)


def test_an_enclosing_covariance_contains_both_and_no_more_than_needed():
    """Two covariances, one wide along x, the other along a diagonal: the enclosing one
    contains both ellipsoids, is tighter than their sum, and is the larger one itself when
    one already contains the other."""
    along_x = np.diag([4.0, 0.01, 1e-4])
    turn = np.array([[math.cos(0.7), -math.sin(0.7), 0.0], [math.sin(0.7), math.cos(0.7), 0.0],
                     [0.0, 0.0, 1.0]])
    diagonal = turn @ np.diag([1.0, 0.04, 4e-4]) @ turn.T
    enclosing = enclosing_covariance(along_x, diagonal)
    assert np.allclose(enclosing, enclosing.T)
    assert _dominates(enclosing, along_x) and _dominates(enclosing, diagonal)
    assert _dominates(along_x + diagonal, enclosing)
    assert not np.allclose(enclosing, along_x + diagonal)
    assert np.allclose(enclosing_covariance(along_x, along_x / 2), along_x)
    assert np.allclose(enclosing_covariance(diagonal / 3, diagonal), diagonal)
