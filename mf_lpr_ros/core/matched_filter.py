"""Windowed linear cross-correlation of query images against reference images.

Every function here computes, for query Q and reference R (both H x W, zero outside),

    S(di, dj) = sum_ij Q(i, j) * R(i + di, j + dj),   |di|, |dj| <= max_shift,

returned as an array indexed [..., di + max_shift, dj + max_shift].

SpectralBank is the many-references engine: it transforms each reference once along x (rows
stay spatial), so that one query batch against a block of references is two dense real matrix
products per block -- a direct correlation along y inside the first (the query side is
expanded into its row shifts), and an inverse DFT restricted to the shift window in the
second. Both run at BLAS speed and only the window is ever computed.
"""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy import fft as sp_fft

from mf_lpr_ros.core.array_ops import NumpyArrays


class SpectralBank(NumpyArrays):
    """Reference images prepared once for windowed correlation against many queries.

    Storage is (K, 2H, capacity) float32: for each x-frequency k the real and imaginary parts
    of every reference row, references along the last axis so a block is a column slice.
    """

    def __init__(self, height: int, width: int, max_shift: int, capacity: int = 64) -> None:
        if max_shift < 0:
            raise ValueError(f"max_shift must be >= 0, got {max_shift}")
        self.height, self.width, self.max_shift = height, width, max_shift
        self.fft_length = width + max_shift
        self.n_freqs = self.fft_length // 2 + 1
        self._bank = self._new_bank(max(capacity, 1))
        self._norms = np.zeros(max(capacity, 1), dtype=np.float32)
        self._count = 0
        self._inverse = _windowed_inverse_dft(self.fft_length, self.n_freqs, max_shift)
        self._operator = np.empty(0, dtype=np.float32)

    def __len__(self) -> int:
        return self._count

    @property
    def norms(self) -> np.ndarray:
        """L2 norm of every reference image."""
        return self._norms[: self._count]

    @property
    def nbytes(self) -> int:
        return self._nbytes(self._bank) + self._norms.nbytes

    def append(self, images: np.ndarray) -> None:
        """Add references, (n, H, W) float32."""
        images = np.asarray(images, dtype=np.float32)
        if images.ndim != 3 or images.shape[1:] != (self.height, self.width):
            raise ValueError(f"expected (n, {self.height}, {self.width}) images, "
                             f"got {images.shape}")
        start, stop = self._count, self._count + len(images)
        self._reserve(stop)
        spectra = sp_fft.rfft(images, n=self.fft_length, axis=2)
        stacked = np.concatenate([spectra.real, spectra.imag], axis=1).transpose(2, 1, 0)
        self._bank[:, :, start:stop] = self._from_host(np.ascontiguousarray(stacked))
        self._norms[start:stop] = np.sqrt(np.einsum("nij,nij->n", images, images))
        self._count = stop

    def refill(self, images: np.ndarray) -> None:
        """Replace every reference by images (n, H, W), keeping the storage."""
        self._count = 0
        self.append(images)

    def _new_bank(self, capacity: int) -> np.ndarray:
        return np.zeros((self.n_freqs, 2 * self.height, capacity), dtype=np.float32)

    def _reserve(self, needed: int) -> None:
        capacity = self._bank.shape[2]
        if needed <= capacity:
            return
        new_capacity = max(needed, 2 * capacity)
        bank = self._new_bank(new_capacity)
        bank[:, :, : self._count] = self._bank[:, :, : self._count]
        norms = np.zeros(new_capacity, dtype=np.float32)
        norms[: self._count] = self._norms[: self._count]
        self._bank, self._norms = bank, norms

    def prepare_queries(self, queries: np.ndarray) -> np.ndarray:
        """The query-side operator (K, 2M, 2H) for a batch of A query images (A, H, W).

        Row m = (a, di) of the real block holds the query's row spectrum shifted by di, so
        that multiplying by a reference's [Re; Im] row spectra correlates along y. The operator
        lives in a buffer this bank reuses: it is valid until the next call (a fresh 20 MB
        array per query costs more in page faults than filling it).
        """
        queries = np.asarray(queries, dtype=np.float32)
        n_queries, height, shift = queries.shape[0], self.height, self.max_shift
        spectra = sp_fft.rfft(queries, n=self.fft_length, axis=2).transpose(2, 0, 1)
        shape = self.reserve_operator(n_queries)
        operator = self._operator.reshape(shape)
        padded = np.zeros((2, self.n_freqs, n_queries, height + 2 * shift), dtype=np.float32)
        padded[0, :, :, shift: shift + height] = spectra.real
        padded[1, :, :, shift: shift + height] = spectra.imag
        # windows[p, k, a, t, i] = padded[p, k, a, t + i]; di = shift - t, so reverse t.
        # Copying into views of the operator, never reshaping the window view (that copies).
        real, imag = sliding_window_view(padded, height, axis=3)[:, :, :, ::-1]
        operator[:, 0, :, :, :height] = real
        operator[:, 0, :, :, height:] = imag
        np.negative(imag, out=operator[:, 1, :, :, :height])
        operator[:, 1, :, :, height:] = real
        return operator.reshape(self.n_freqs, -1, 2 * height)

    def reserve_operator(self, n_queries: int) -> tuple[int, ...]:
        """Allocate the operator buffer for batches of n_queries now (a long run's memory is
        then fixed before its first query); returns the operator's 5-D shape."""
        shape = (self.n_freqs, 2, n_queries, 2 * self.max_shift + 1, 2 * self.height)
        if self._operator.size != np.prod(shape):
            self._operator = np.empty(shape, dtype=np.float32)
        return shape

    def correlate_block(self, operator: np.ndarray, start: int, stop: int) -> np.ndarray:
        """Scores of the prepared queries against references [start, stop).

        Returns (2S+1 [dj], A, 2S+1 [di], stop - start) float32.
        """
        return self._correlate(operator, self._bank[:, :, start:stop])

    def correlate_subset(self, operator: np.ndarray, references: np.ndarray) -> np.ndarray:
        """As correlate_block, for any references (indices), in the order given."""
        return self._correlate(operator, self._bank[:, :, self._index(references)])

    def _correlate(self, operator: np.ndarray, columns: np.ndarray) -> np.ndarray:
        n_rows, n_refs = operator.shape[1] // 2, columns.shape[2]
        # `@`, not np.matmul: the torch backend's tensors take this same path.
        spectra = operator @ columns
        scores = self._inverse @ spectra.reshape(2 * self.n_freqs, n_rows * n_refs)
        n_shifts = 2 * self.max_shift + 1
        return scores.reshape(n_shifts, n_rows // n_shifts, n_shifts, n_refs)

    def best_per_reference(self, operator: np.ndarray, stop: int | None = None,
                           chunk_size: int = 256) -> np.ndarray:
        """Best score over the whole (dj, a, di) volume of every reference in [0, stop)."""
        stop = self._count if stop is None else min(stop, self._count)
        best = self._empty_scores(stop)
        for start in range(0, stop, chunk_size):
            end = min(start + chunk_size, stop)
            best[start:end] = self._amax(self.correlate_block(operator, start, end).reshape(
                -1, end - start), axis=0)
        return self._to_host(best)

    def best_of_subset(self, operator: np.ndarray, references: np.ndarray,
                       chunk_size: int = 256, allowed: np.ndarray | None = None
                       ) -> tuple[np.ndarray, np.ndarray | None]:
        """best_per_reference for the given references only, in their order; with allowed
        ((n, A) bool on the host), only the (reference, query) pairs it allows.

        Also returns the whole score volume (as correlate_subset) when the references fit one
        chunk, so that locating a few of them needs no second pass over the operator.
        """
        references = np.asarray(references, dtype=np.int64)
        best = self._empty_scores(len(references))
        volume = None
        for start in range(0, len(references), chunk_size):
            chunk = references[start: start + chunk_size]
            volume = self._correlate_some(operator, chunk, None if allowed is None
                                          else allowed[start: start + len(chunk)])
            best[start: start + len(chunk)] = self._amax(volume.reshape(-1, len(chunk)), axis=0)
        return self._to_host(best), (volume if len(references) <= chunk_size else None)

    def locate(self, operator: np.ndarray, references: np.ndarray,
               allowed: np.ndarray | None = None) -> np.ndarray:
        """Best alignment of each reference: (n, 4) rows of query a, di, dj and the score."""
        return self.peaks(self._correlate_some(operator, references, allowed))

    def _correlate_some(self, operator: np.ndarray, references: np.ndarray,
                        allowed: np.ndarray | None) -> np.ndarray:
        """correlate_subset, or only the pairs allowed[k, a] permits (the others -inf), one
        query at a time: a pair not allowed costs nothing."""
        if allowed is None:
            return self.correlate_subset(operator, references)
        n_shifts = 2 * self.max_shift + 1
        n_queries = allowed.shape[1]
        by_query = self._full((n_queries, n_shifts, n_shifts, len(references)), -np.inf)
        per_query = operator.reshape(self.n_freqs, 2, n_queries, n_shifts, 2 * self.height)
        # Gathered once: gathering columns from the whole bank for every query costs more than
        # the products.
        candidates = self._bank[:, :, self._index(references)]
        for query in np.flatnonzero(allowed.any(axis=0)):
            picked = np.flatnonzero(allowed[:, query])
            rows = per_query[:, :, query].reshape(self.n_freqs, 2 * n_shifts, 2 * self.height)
            spectra = rows @ candidates[:, :, self._index(picked)]
            scores = self._inverse @ spectra.reshape(2 * self.n_freqs, n_shifts * len(picked))
            by_query[query][:, :, self._index(picked)] = scores.reshape(n_shifts, n_shifts,
                                                                        len(picked))
        return by_query.swapaxes(0, 1)

    def peaks(self, volume: np.ndarray, columns: np.ndarray | None = None) -> np.ndarray:
        """As locate, from a correlate_subset volume (only the given columns)."""
        if columns is not None:
            volume = volume[..., self._index(columns)]
        flat, scores = self._argmax_rows(volume.reshape(-1, volume.shape[3]))
        dj, a, di = np.unravel_index(flat, tuple(volume.shape[:3]))
        return np.stack([a, di - self.max_shift, dj - self.max_shift, scores], axis=1)


def _windowed_inverse_dft(length: int, n_freqs: int, max_shift: int) -> np.ndarray:
    """(2S+1, 2K) real matrix: interleaved [Re, Im] half-spectrum -> real signal at |dj| <= S."""
    shifts = np.arange(-max_shift, max_shift + 1)[:, None]
    freqs = np.arange(n_freqs)[None, :]
    weight = np.full(n_freqs, 2.0)
    weight[0] = 1.0
    if length % 2 == 0:
        weight[-1] = 1.0
    phase = 2 * np.pi * freqs * shifts / length
    inverse = np.empty((len(shifts), n_freqs, 2))
    inverse[:, :, 0] = weight * np.cos(phase) / length
    inverse[:, :, 1] = -weight * np.sin(phase) / length
    # spectra rows are ordered (k, part); match that ordering.
    return np.ascontiguousarray(inverse.reshape(len(shifts), 2 * n_freqs), dtype=np.float32)


def correlate_fft2(queries: np.ndarray, reference: np.ndarray, max_shift: int) -> np.ndarray:
    """Windowed correlation of a few queries (A, H, W) with one reference (H, W) by 2-D FFT.

    Cheaper than a SpectralBank for a handful of references. Returns (A, 2S+1, 2S+1).
    """
    queries = np.asarray(queries, dtype=np.float32)
    height, width = reference.shape
    # 136 = 8 x 17 at the defaults: a 5-smooth length is ~2x faster.
    shape = (sp_fft.next_fast_len(height + max_shift, real=True),
             sp_fft.next_fast_len(width + max_shift, real=True))
    ref_spectrum = sp_fft.rfft2(reference.astype(np.float32), s=shape)
    query_spectra = sp_fft.rfft2(queries, s=shape, axes=(-2, -1))
    window = np.arange(-max_shift, max_shift + 1)
    # Inverse along y first and keep the window's rows: the inverse along x then runs on
    # 2S+1 rows instead of all (~20 % of the whole correlation at the defaults).
    rows = sp_fft.ifft(np.conj(query_spectra) * ref_spectrum, axis=-2)[:, window % shape[0]]
    return sp_fft.irfft(rows, n=shape[1], axis=-1)[:, :, window % shape[1]].astype(np.float32)
