"""Sub-sample peaks of periodic samples, and the 2x2 closed forms (core/peak.py)."""

import numpy as np
import pytest

from mf_lpr_ros.core.peak import circular_peaks, inverse_2x2, smallest_eigenvalue


def periodic_peaks(centres: np.ndarray, n_samples: int = 40) -> np.ndarray:
    """(n_samples, len(centres)): a smooth periodic bump per column, its maximum at centres
    (in samples, fractional)."""
    phase = 2 * np.pi * (np.arange(n_samples)[:, None] - centres[None, :]) / n_samples
    return np.exp(4.0 * np.cos(phase))


def test_peaks_found_between_samples_and_across_the_wrap():
    centres = np.array([10.0, 10.3, 10.7, 0.2, 39.6, 39.9])
    values = periodic_peaks(centres)
    estimate = circular_peaks(values)
    error = (estimate - centres + 20.0) % 40.0 - 20.0
    # A parabola through three samples of a smooth bump: within a tenth of a sample.
    np.testing.assert_allclose(error, 0.0, atol=0.1)
    # Peaks nearest sample 0 take their other neighbour from the far end (39.6 reads -0.4).
    assert circular_peaks(values[:, 3:4])[0] > 0.1
    assert circular_peaks(values[:, 4:5])[0] < -0.1


def test_a_flat_top_gives_no_offset_and_a_plateau_of_two_its_middle():
    assert circular_peaks(np.ones((8, 1)))[0] == 0.0
    plateau = np.array([[0.0], [1.0], [2.0], [3.0], [3.0], [1.0], [0.0], [0.0]])
    assert circular_peaks(plateau)[0] == 3.5


def test_closed_forms_agree_with_numpy_linalg():
    rng = np.random.default_rng(4)
    for _ in range(50):
        a, b, c = rng.normal(size=3)
        symmetric = np.array([[a, b], [b, c]])
        assert smallest_eigenvalue(symmetric) == pytest.approx(
            np.linalg.eigvalsh(symmetric)[0], abs=1e-12)
        matrix = rng.normal(size=(2, 2))
        np.testing.assert_allclose(inverse_2x2(matrix), np.linalg.inv(matrix), rtol=1e-9,
                                   atol=1e-9)
