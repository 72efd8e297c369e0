"""Rotation- and translation-invariant ranking of references before the exact search.

Each low-resolution descriptor is reduced to its polar magnitude spectrum (Fourier-Mellin
without the log-radius): the 2-D FFT magnitude ignores where things are in the window, and
resampled on (radius, angle) a rotation of the scan becomes a circular shift along the angle
axis. Ranking a reference takes the best circular correlation of the two polar spectra over
angle shifts every half bin, computed for every reference at once in the angular-frequency
domain.

This keeps the relative layout of the spectrum across radii (unlike per-ring magnitudes). The
exact two-stage search then runs only on the best-ranked references (and their map neighbours,
search.py): the prefilter never decides a match, it only narrows the candidates. On KITTI 00
BEV the result equals the exhaustive search's on every revisit query (README, "Speed").
"""

from __future__ import annotations

import math

import numpy as np

from mf_lpr_ros.core.array_ops import NumpyArrays, half_spectrum_weights
from mf_lpr_ros.core.peak import circular_peaks
from mf_lpr_ros.core.workers import Workers

_MIN_RADIUS_BINS = 1.5
_RADIAL_SUBSAMPLE_BINS = 0.5
# References scored together: their temporaries (~0.5 MB a harmonic's products, 1 MB of
# scores over angles) stay in cache, so only the features stream from memory (3x faster
# at 192k references than blocks of 65536).
_SCORED_TOGETHER = 1 << 13
# A reference is scored by its correlation's best over shifts this many times finer than the
# angle bins. The features hold whole angular harmonics, so the correlation between two shifts
# is the same trigonometric sum evaluated there: read at whole shifts alone, a query turned by
# half a bin scores less than one turned by whole bins, and turned queries lose their place
# from the candidates more often (docs/RESULTS.md, session 44).
_SCORE_SHIFTS_PER_BIN = 2


class PolarSpectrumIndex(NumpyArrays):
    """Polar magnitude spectra of references, ranked against a query by rotation search.

    Storage is (H, capacity, R) complex64: for each angular harmonic h the Fourier
    coefficients of every reference's R radius rows, so one query is H batched mat-vecs.
    24 radii and 40 angles (4.5-degree shifts; H = 21): against 20 and 32, rotated KITTI 00
    queries 2-4 m from their nearest reference lost their true place from the 64 candidates
    1.2 % of the time instead of 2.1 %, for 1.5x the features (docs/RESULTS.md, session 19).
    """

    def __init__(self, image_size: int, n_radii: int = 24, n_angles: int = 40,
                 capacity: int = 64, workers: Workers | None = None) -> None:
        self.workers = workers or Workers()
        self.fft_size = 1 << int(np.ceil(np.log2(image_size)))
        self.n_radii, self.n_angles = n_radii, n_angles
        self.n_harmonics = n_angles // 2 + 1
        centres = np.arange(image_size) - image_size / 2 + 0.5
        x, y = np.meshgrid(centres, centres)
        # A disc, not the square: rotating the scene then only moves content inside it.
        self._disc = (np.hypot(x, y) <= image_size / 2).astype(np.float32)
        self._sampling = _polar_sampling(self.fft_size, n_radii, n_angles)
        self._inverse = _circular_inverse(n_angles, 1)
        self._score_inverse = _circular_inverse(n_angles, _SCORE_SHIFTS_PER_BIN)
        self._bank = self._new_bank(max(capacity, 1))
        self._count = 0
        self._last_image: np.ndarray | None = None
        self._last_query = None

    def __len__(self) -> int:
        return self._count

    @property
    def nbytes(self) -> int:
        return self._nbytes(self._bank)

    def features(self, images: np.ndarray) -> np.ndarray:
        """(n, H, R) complex64 angular spectra of images (n, S, S), unit energy each."""
        images = np.asarray(images, dtype=np.float32)
        centred = (images - images.mean(axis=(1, 2), keepdims=True)) * self._disc
        magnitude = np.abs(np.fft.rfft2(centred, s=(self.fft_size, self.fft_size)))
        rows, cols, weights = self._sampling
        flat = magnitude.reshape(len(images), -1)
        # sqrt compresses the dominant low frequencies so that structure at every scale counts.
        polar = np.sqrt(np.einsum("npk,pk->np", flat[:, rows * magnitude.shape[2] + cols],
                                  weights)).reshape(len(images), self.n_radii, self.n_angles)
        polar -= polar.mean(axis=(1, 2), keepdims=True)
        polar /= np.maximum(np.linalg.norm(polar, axis=(1, 2), keepdims=True), 1e-9)
        return np.fft.rfft(polar, axis=2).transpose(0, 2, 1).astype(np.complex64)

    @property
    def stored_features(self) -> np.ndarray:
        """(H, n, R) features of every reference, on the host (for prefilter_cache)."""
        return self._to_host(self._bank[:, : self._count])

    def adopt(self, features: np.ndarray) -> None:
        """Take (H, n, R) features of the first n references, computed earlier (a memory map
        stays one: appending copies it into memory)."""
        if self._count:
            raise ValueError("adopt needs an empty index")
        self._bank = self._from_host(features)
        self._count = features.shape[1]

    def append(self, images: np.ndarray) -> None:
        """Add references (n, S, S): the low-resolution weighted descriptors."""
        self._store(self._from_host(np.ascontiguousarray(self.features(images).transpose(1, 0, 2))))

    def _new_bank(self, capacity: int) -> np.ndarray:
        return np.zeros((self.n_harmonics, capacity, self.n_radii), dtype=np.complex64)

    def reserve(self, needed: int) -> None:
        """Room for needed references in all, made at once: an index that knows how many its
        map holds grows its bank to exactly that, where doubling would hold up to twice the
        features and copy them at every step (and the cache written from a bank with spare
        room would copy them once more: 3.8 GB each at a million references)."""
        if needed > self._bank.shape[1]:
            self._grow(needed)

    def _grow(self, capacity: int) -> None:
        grown = self._new_bank(capacity)
        grown[:, : self._count] = self._bank[:, : self._count]
        self._bank = grown

    def _store(self, spectra) -> None:
        """Append (H, n, R) spectra, growing the bank by doubling."""
        stop = self._count + spectra.shape[1]
        if stop > self._bank.shape[1]:
            self._grow(max(stop, 2 * self._bank.shape[1]))
        self._bank[:, self._count: stop] = spectra
        self._count = stop

    def scores(self, image: np.ndarray, stop: int | None = None) -> np.ndarray:
        """Best circular correlation over angle shifts of one query image against references
        [0, stop): (stop,) float32 in [-1, 1]."""
        stop = self._count if stop is None else min(stop, self._count)
        query = self._query(image)
        if stop <= _SCORED_TOGETHER:
            return self._to_host(self._best_over_angles(self._bank[:, :stop], query))
        return np.concatenate([
            self._to_host(self._best_over_angles(
                self._bank[:, start: min(start + _SCORED_TOGETHER, stop)], query))
            for start in range(0, stop, _SCORED_TOGETHER)])

    def _query(self, image: np.ndarray):
        """The query image's conjugate features (H, R, 1), computed once for the last image: a
        search ranks its candidates, then asks for their angles."""
        if self._last_image is None or not np.array_equal(image, self._last_image):
            self._last_query = self._from_host(self.features(image[None])[0]).conj()[:, :, None]
            self._last_image = np.array(image, copy=True)
        return self._last_query

    def _best_over_angles(self, features, query):
        return self._amax(self._over_angles(features, query, self._score_inverse), axis=0)

    def _over_angles(self, features, query, inverse):
        """(shifts, n) circular correlations of n references' features with the query's, at
        the shifts of inverse (_inverse: the n_angles whole shifts; _score_inverse: every half
        shift)."""
        cross = (features @ query)[:, :, 0]
        return self._product(inverse,
                             self._real_parts(cross).reshape(2 * self.n_harmonics, cross.shape[1]))

    def angles(self, image: np.ndarray, references: np.ndarray) -> np.ndarray:
        """Degrees in [0, 180) by which the query image is best turned onto each reference (its
        spectrum's best circular shift, refined between shifts by a parabola through it and its
        two neighbours): the yaw between them modulo half a turn."""
        return self._angles_of(self._query(image), references)

    def angles_between(self, reference: int, references: np.ndarray) -> np.ndarray:
        """angles, with a stored reference in the query's place: from its stored features, so
        the last query's stay cached (a search asks this of the map's own views mid-query)."""
        return self._angles_of(self._bank[:, reference].conj()[:, :, None], references)

    def _angles_of(self, query, references: np.ndarray) -> np.ndarray:
        correlation = self._to_host(self._over_angles(self._bank[:, self._index(references)],
                                                      query, self._inverse))
        return circular_peaks(correlation) * (180.0 / self.n_angles) % 180.0

    def top(self, image: np.ndarray, k: int, stop: int | None = None) -> np.ndarray:
        """Indices of the k best-ranked references in [0, stop), best first."""
        scores = self.scores(image, stop)
        k = min(k, len(scores))
        best = np.argpartition(-scores, k - 1)[:k]
        return best[np.argsort(-scores[best], kind="stable")]


def _circular_inverse(n_angles: int, per_bin: int) -> np.ndarray:
    """(n_angles x per_bin, (harmonic, [Re, Im])) float32: the real inverse DFT of a half
    spectrum of n_angles samples as one matrix, evaluated every 1/per_bin of a shift, so that
    one product gives the circular correlation at every such shift."""
    n_harmonics = n_angles // 2 + 1
    shifts = np.arange(n_angles * per_bin) / per_bin
    weight = half_spectrum_weights(n_angles, n_harmonics)
    phase = 2 * np.pi * np.arange(n_harmonics)[:, None] * shifts[None, :] / n_angles
    inverse = np.stack([weight[:, None] * np.cos(phase), -weight[:, None] * np.sin(phase)],
                       axis=1) / n_angles
    return np.ascontiguousarray(inverse.reshape(2 * n_harmonics, len(shifts)).T,
                                dtype=np.float32)


def _polar_sampling(fft_size: int, n_radii: int, n_angles: int
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bilinear taps of a half-plane rfft2 magnitude averaged over each sample's radial
    interval, at (radius, angle in [0, pi)) points.

    Returns rows, cols (P, T) into the (fft_size, fft_size // 2 + 1) spectrum and weights (P, T).
    The magnitude of a real image's spectrum is point-symmetric, so half a turn covers it. Each
    radius averages sub-samples at most _RADIAL_SUBSAMPLE_BINS apart across its interval: read
    at one radius alone, the structure between radii (~1.2 frequency bins apart at 24 radii,
    1.5 at session 16's 20) is lost, and rotated KITTI 00 queries between references 8 m apart
    lost their true place from the candidates twice as often (docs/RESULTS.md, session 16).
    """
    radii = np.linspace(_MIN_RADIUS_BINS, fft_size / 2 - 2, n_radii)
    step = radii[1] - radii[0] if n_radii > 1 else 0.0
    n_sub = max(1, math.ceil(step / _RADIAL_SUBSAMPLE_BINS))
    offsets = (np.arange(n_sub) - (n_sub - 1) / 2) * step / n_sub
    angles = np.arange(n_angles) * np.pi / n_angles
    taps = [_bilinear_taps(fft_size, np.maximum(radii + offset, 0.0), angles)
            for offset in offsets]
    rows, cols, weights = (np.concatenate(parts, axis=1) for parts in zip(*taps))
    return rows, cols, (weights / n_sub).astype(np.float32)


def _bilinear_taps(fft_size: int, radii: np.ndarray, angles: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """rows, cols, weights (P, 4) of the points (radius, angle), radius-major."""
    radius, angle = np.meshgrid(radii, angles, indexing="ij")
    kx, ky = radius * np.cos(angle), radius * np.sin(angle)
    mirrored = kx < 0
    kx, ky = np.where(mirrored, -kx, kx).ravel(), np.where(mirrored, -ky, ky).ravel()
    x0, y0 = np.floor(kx).astype(np.int64), np.floor(ky).astype(np.int64)
    fx, fy = kx - x0, ky - y0
    cols = np.stack([x0, x0 + 1, x0, x0 + 1], axis=1)
    rows = np.stack([y0, y0, y0 + 1, y0 + 1], axis=1) % fft_size
    weights = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], axis=1)
    return rows, np.minimum(cols, fft_size // 2), weights
