"""Sub-cell and sub-sample peak location on a correlation surface, with the curvature there."""

from __future__ import annotations

import math

import numpy as np

# Least-squares fit of f = c0 + c1 x + c2 y + c3 x^2 + c4 x y + c5 y^2 on the 3x3 grid
# (x along columns, y along rows, both -1..1).
_grid_y, _grid_x = np.mgrid[-1:2, -1:2]
_QUADRATIC_FIT = np.linalg.pinv(np.stack([
    np.ones(9), _grid_x.ravel(), _grid_y.ravel(), _grid_x.ravel() ** 2,
    _grid_x.ravel() * _grid_y.ravel(), _grid_y.ravel() ** 2], axis=1))


def subcell_peak(surface: np.ndarray, row: int, col: int) -> tuple[np.ndarray, np.ndarray]:
    """Sub-cell offset (dx, dy) of a peak from a quadratic fit on its 3x3 neighbourhood.

    Returns the offset (cells, clipped to +-0.5) and the fitted Hessian (x, y). At the window
    border the offset along that axis is 0 and the curvature comes from what is available.
    """
    rows, cols = surface.shape
    if 0 < row < rows - 1 and 0 < col < cols - 1:
        patch = surface[row - 1: row + 2, col - 1: col + 2].astype(np.float64).ravel()
        _, gx, gy, cxx, cxy, cyy = _QUADRATIC_FIT @ patch
        hessian = np.array([[2 * cxx, cxy], [cxy, 2 * cyy]])
        if smallest_eigenvalue(-hessian) > 1e-12:
            offset = -inverse_2x2(hessian) @ np.array([gx, gy])
            if np.all(np.abs(offset) <= 1.0):
                return np.clip(offset, -0.5, 0.5), hessian
    dx, hxx = subsample_peak(surface[row], col)
    dy, hyy = subsample_peak(surface[:, col], row)
    return np.array([dx, dy]), np.array([[hxx, 0.0], [0.0, hyy]])


# Closed forms: a numpy.linalg call on a 2x2 matrix costs ~20 us, and every match makes several.
def smallest_eigenvalue(symmetric: np.ndarray) -> float:
    """The smaller eigenvalue of a symmetric 2x2 matrix."""
    a, b, c = float(symmetric[0, 0]), float(symmetric[0, 1]), float(symmetric[1, 1])
    return 0.5 * (a + c) - math.hypot(0.5 * (a - c), b)


def inverse_2x2(matrix: np.ndarray) -> np.ndarray:
    """The inverse of an invertible 2x2 matrix."""
    (a, b), (c, d) = matrix
    return np.array([[d, -b], [-c, a]]) / (a * d - b * c)


def subsample_peak(values: np.ndarray, index: int) -> tuple[float, float]:
    """Parabola through a 1-D peak and its neighbours: (offset in samples, second difference)."""
    if index <= 0 or index >= len(values) - 1:
        return 0.0, 0.0
    left, centre, right = (float(values[index - 1]), float(values[index]),
                           float(values[index + 1]))
    curvature = left - 2 * centre + right
    if curvature >= 0:
        return 0.0, curvature
    return float(np.clip(0.5 * (left - right) / curvature, -0.5, 0.5)), curvature


def circular_peaks(values: np.ndarray) -> np.ndarray:
    """Per column of values (samples of a periodic function along axis 0): where its maximum
    lies, in samples, refined by the parabola through the best sample and its two neighbours
    (wrapping around) by at most half a sample; the best sample itself where the three are not
    concave."""
    values = np.asarray(values, dtype=np.float64)
    n_samples, columns = values.shape[0], np.arange(values.shape[1])
    best = np.argmax(values, axis=0)
    left = values[(best - 1) % n_samples, columns]
    centre = values[best, columns]
    right = values[(best + 1) % n_samples, columns]
    curvature = left - 2 * centre + right
    concave = curvature < 0
    offsets = np.zeros(len(columns))
    offsets[concave] = 0.5 * (left - right)[concave] / curvature[concave]
    return best + np.clip(offsets, -0.5, 0.5)
