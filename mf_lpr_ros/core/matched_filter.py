"""Windowed linear cross-correlation of query images against reference images.

Every function here computes, for query Q and reference R (both H x W, zero outside),

    S(di, dj) = sum_ij Q(i, j) * R(i + di, j + dj),   |di|, |dj| <= max_shift,

returned as an array indexed [..., di + max_shift, dj + max_shift].

SpectralBank is the many-references engine: it transforms each reference once along x (rows
stay spatial), so that one query batch against a block of references is two dense matrix
products per block -- a complex one holding a direct correlation along y (the query side is
expanded into its row shifts), then a real inverse DFT restricted to the shift window. Both
run at BLAS speed and only the window is ever computed. A search that pairs each reference
with a few queries of its own correlates pair by pair instead, from 2-D spectra.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import cached_property

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy import fft as sp_fft

from mf_lpr_ros.core.array_ops import NumpyArrays, half_spectrum_weights, pair_products
from mf_lpr_ros.core.workers import Workers

# Pairs correlated at once by _allowed_scores: their spectra stay in a core's cache from product
# to inverse (~0.6 MB at the defaults).
_PAIRS_PER_CHUNK = 32

# A reference's 2-D spectrum, once a search of pairs has made it, is kept while the kept spectra
# of every reference the bank has room for take at most this much: at 1,500 references (29 MB)
# a query no longer transforms its 64 candidates along y (~0.7 ms alone; 0.15-0.22 ms of a
# query's median, 0.5 of its mean: docs/RESULTS.md, "Scale", session 59). A bank with room
# for more than ~12,000 references makes them per query.
_KEPT_PLANE_SPECTRA_BYTES = 256 * 2 ** 20


class PreparedQueries:
    """A batch of A query images (A, H, W) to correlate. Each search builds what it needs from
    them once: the operator that correlates every query at once (SpectralBank.operator), or
    their 2-D spectra, for a search that scores pairs of a query and a reference
    (SpectralBank._allowed_scores)."""

    def __init__(self, images, turned_from: np.ndarray | None = None) -> None:
        self.images = images
        self.n_queries = len(images)
        # (A, 2): the row each image is a quarter turn of, and the turns (SpectralBank.
        # prepare_queries); None: every image stands alone.
        self.turned_from = turned_from
        self.operator = None
        self.plane_spectra = None


class AllowedScores:
    """The scores of the (reference, query) pairs a search allowed: pair p is query queries[p]
    against the reference at position positions[p] of the subset searched, its scores
    scores[p] (2S+1 [di], 2S+1 [dj])."""

    def __init__(self, queries: np.ndarray, positions: np.ndarray, scores) -> None:
        self.queries, self.positions, self.scores = queries, positions, scores


class SpectralBank(NumpyArrays):
    """Reference images prepared once for windowed correlation against many queries.

    Storage is (capacity, K, H) complex64: for each reference and x-frequency k the spectra of
    its rows, so that the candidates of a query are gathered as whole blocks. The products
    read it as (K, H, references), which BLAS takes as a transposed operand without a copy.
    Beside it the bank keeps its images' norms and how many references are filled; the storage
    grows by doubling. The 2-D spectra a search of pairs needs are kept once made, where they
    fit kept_plane_spectra_bytes and the bank is not refilled.
    """

    kept_plane_spectra_bytes = _KEPT_PLANE_SPECTRA_BYTES

    def __init__(self, height: int, width: int, max_shift: int, capacity: int = 64,
                 workers: Workers | None = None) -> None:
        _require_shift(max_shift)
        self.height, self.width, self.max_shift = height, width, max_shift
        self.n_shifts = 2 * max_shift + 1
        self.fft_length = width + max_shift
        self.n_freqs = self.fft_length // 2 + 1
        # Pairs are correlated along y by DFTs this long: the shortest whose circular
        # correlation is the linear one within the shift window.
        self.column_length = height + max_shift
        self._start_empty(capacity)
        self._inverse = _windowed_inverse_dft(self.fft_length, self.n_freqs, max_shift)
        self._along_y = _windowed_column_inverse(self.column_length, max_shift)
        self._operator = np.empty(0, dtype=np.complex64)
        self.workers = workers or Workers()

    def _start_empty(self, capacity: int) -> None:
        self._bank = self._new_bank(max(capacity, 1))
        self._norms = np.zeros(max(capacity, 1), dtype=np.float32)
        self._count = 0
        self._kept_planes: np.ndarray | None = None
        self._kept_plane_made = np.zeros(0, dtype=bool)

    def append(self, images: np.ndarray) -> None:
        """Add references, (n, H, W) float32."""
        images = np.asarray(images, dtype=np.float32)
        spectra = self._spectra(images)
        start, stop = self._count, self._count + len(images)
        self._reserve(stop)
        self._bank[start:stop] = self._from_host(spectra)
        self._norms[start:stop] = np.sqrt(np.einsum("nij,nij->n", images, images))
        self._count = stop
        # Room for the kept 2-D spectra now, not at the first query: a localiser's memory is
        # then settled once its map is loaded (filling the room touches its pages, no more).
        self._kept_plane_spectra()

    def refill(self, images: np.ndarray) -> None:
        """Replace every reference by images, keeping the storage. A bank refilled (with each
        query's candidates) keeps no 2-D spectra from then on: none would be asked for twice."""
        self._count = 0
        self.kept_plane_spectra_bytes = 0
        self.append(images)

    def _reserve(self, needed: int) -> None:
        """Room for needed references, growing by doubling (the filled ones kept)."""
        capacity = self._bank.shape[0]
        if needed <= capacity:
            return
        new_capacity = max(needed, 2 * capacity)
        bank = self._new_bank(new_capacity)
        bank[: self._count] = self._bank[: self._count]
        norms = np.zeros(new_capacity, dtype=np.float32)
        norms[: self._count] = self._norms[: self._count]
        self._bank, self._norms = bank, norms

    def __len__(self) -> int:
        return self._count

    @property
    def norms(self) -> np.ndarray:
        """L2 norm of every reference image."""
        return self._norms[: self._count]

    @property
    def nbytes(self) -> int:
        kept = 0 if self._kept_planes is None else self._nbytes(self._kept_planes)
        return self._nbytes(self._bank) + self._norms.nbytes + kept

    def _spectra(self, images: np.ndarray) -> np.ndarray:
        """(n, K, H) row spectra of images (n, H, W)."""
        if images.ndim != 3 or images.shape[1:] != (self.height, self.width):
            raise ValueError(f"expected (n, {self.height}, {self.width}) images, "
                             f"got {images.shape}")
        return np.ascontiguousarray(
            sp_fft.rfft(images, n=self.fft_length, axis=2).transpose(0, 2, 1))

    def _new_bank(self, capacity: int) -> np.ndarray:
        return np.zeros((capacity, self.n_freqs, self.height), dtype=np.complex64)

    @staticmethod
    def _columns(blocks: np.ndarray) -> np.ndarray:
        """Reference blocks (n, K, H) as the products' right operand (K, H, n), a view."""
        return blocks.transpose(1, 2, 0)

    def prepare_queries(self, queries: np.ndarray, pairs: bool = False,
                        turned_from: np.ndarray | None = None) -> PreparedQueries:
        """A batch of query images (A, H, W) ready for the searches below; pairs: their 2-D
        spectra made now, for a search of allowed pairs. turned_from (A, 2): for each image,
        the row of an earlier image of the batch it equals turned by np.rot90(that, -k) and k,
        or (-1, 0): its 2-D spectrum is then laid out from that image's (quarter_turned), not
        transformed again."""
        prepared = PreparedQueries(self._from_host(np.asarray(queries, dtype=np.float32)),
                                   turned_from)
        if pairs:
            self._plane_spectra(prepared)
        return prepared

    def candidate_spectra(self, references: np.ndarray) -> np.ndarray:
        """The 2-D spectra (n, column_length, K) of references (indices, in their order) that
        a search of allowed pairs correlates: their stored row spectra transformed along y,
        each made once where they are kept (kept_plane_spectra_bytes)."""
        references = np.asarray(references, dtype=np.int64)
        kept = self._kept_plane_spectra()
        if kept is None:
            return self._transformed_along_y(references)
        missing = references[~self._kept_plane_made[references]]
        if len(missing):
            kept[missing] = self._transformed_along_y(missing)
            self._kept_plane_made[missing] = True
        return kept[references]

    def _transformed_along_y(self, references: np.ndarray) -> np.ndarray:
        return self._contiguous(self._dft(self._bank[self._index(references)],
                                          self.column_length).swapaxes(1, 2))

    def _kept_plane_spectra(self) -> np.ndarray | None:
        """The kept 2-D spectra (capacity, column_length, K), made empty once references are
        appended and again when the storage has grown; None where they would not fit or are
        not kept."""
        shape = (self._bank.shape[0], self.column_length, self.n_freqs)
        if math.prod(shape) * np.dtype(np.complex64).itemsize > self.kept_plane_spectra_bytes:
            self._kept_planes = None
        elif self._kept_planes is None or self._kept_planes.shape != shape:
            self._kept_planes = np.empty(shape, dtype=np.complex64)
            self._kept_plane_made = np.zeros(shape[0], dtype=bool)
        return self._kept_planes

    def operator(self, prepared: PreparedQueries) -> np.ndarray:
        """The operator (K, A (2S+1), H) of every query in prepared, built once.

        Row (a, di) holds the conjugate of query a's row spectrum shifted by di, so that
        multiplying by a reference's row spectra correlates along y. It lives in a buffer this
        bank reuses: valid until the next batch is prepared and searched (a fresh 10-30 MB
        array per query costs more in page faults than filling it).
        """
        if prepared.operator is None:
            shape = self.reserve_operator(prepared.n_queries)
            prepared.operator = self._expand(self._windows(prepared.images),
                                             self._operator_buffer(shape))
        return prepared.operator

    def _windows(self, images: np.ndarray) -> np.ndarray:
        """The windows (K, A, 2S+1, H) of the conjugated row spectra of images (A, H, W),
        zero-padded by the shift window on both sides of y: a view, window t of every row,
        t reversed so that di ascends."""
        height, shift = self.height, self.max_shift
        spectra = sp_fft.rfft(images, n=self.fft_length, axis=2).transpose(2, 0, 1)
        rows = np.zeros((self.n_freqs, len(images), height + 2 * shift), dtype=np.complex64)
        # Conjugated once here: the operator is then a plain copy of its windows (a conjugating
        # copy of the strided windows takes ~2x as long).
        np.conjugate(spectra, out=rows[:, :, shift: shift + height])
        # windows[k, a, t, i] = rows[k, a, t + i]; di = shift - t, so reverse t.
        return sliding_window_view(rows, height, axis=2)[:, :, ::-1]

    def _operator_buffer(self, shape: tuple[int, ...]) -> np.ndarray:
        return self._operator.reshape(shape)

    def _expand(self, windows: np.ndarray, out: np.ndarray) -> np.ndarray:
        """The operator of row windows (K, A, 2S+1, H), copied into out (same shape)."""
        np.copyto(out, windows)
        return out.reshape(self.n_freqs, -1, self.height)

    def reserve_operator(self, n_queries: int) -> tuple[int, ...]:
        """Allocate the operator buffer for batches of n_queries now (a long run's memory is
        then fixed before its first query); returns the operator's 4-D shape."""
        shape = (self.n_freqs, n_queries, self.n_shifts, self.height)
        if self._operator.size != np.prod(shape):
            self._operator = np.empty(shape, dtype=np.complex64)
        return shape

    def correlate_subset(self, prepared: PreparedQueries, references: np.ndarray) -> np.ndarray:
        """Scores of the prepared queries against references (indices), in the order given.

        Returns (2S+1 [dj], A, 2S+1 [di], len(references)) float32.
        """
        return self._correlate(self.operator(prepared),
                               self._columns(self._bank[self._index(references)]))

    def _correlate(self, operator: np.ndarray, columns: np.ndarray) -> np.ndarray:
        n_rows, n_refs = operator.shape[1], columns.shape[2]
        scores = self._windowed_inverse(self._product(operator, columns))
        return scores.reshape(self.n_shifts, n_rows // self.n_shifts, self.n_shifts, n_refs)

    def _windowed_inverse(self, spectra: np.ndarray) -> np.ndarray:
        """Correlation scores (2S+1 [dj], R x n) from y-correlated spectra (K, R, n)."""
        width = int(np.prod(spectra.shape[1:]))
        return self._product(self._inverse,
                             self._real_parts(spectra).reshape(2 * self.n_freqs, width))

    def best_of_subset(self, prepared: PreparedQueries, references: np.ndarray,
                       chunk_size: int = 256, allowed: np.ndarray | None = None,
                       candidates: np.ndarray | None = None
                       ) -> tuple[np.ndarray, "np.ndarray | AllowedScores | None"]:
        """Best score over the whole (dj, a, di) volume of each of references, in their order;
        with allowed ((n, A) bool on the host), only over the (reference, query) pairs it
        allows (-inf for a reference with none), from the references' candidate_spectra when
        given.

        Also returns the scores computed (the whole volume as correlate_subset, or the allowed
        pairs' AllowedScores) when the references fit one chunk, so that locating a few of
        them (peaks) needs no second pass.
        """
        references = np.asarray(references, dtype=np.int64)
        if allowed is not None:
            return self._best_of_allowed(prepared, references, chunk_size, allowed, candidates)
        best = self._empty_scores(len(references))
        volume = None
        for start in range(0, len(references), chunk_size):
            chunk = references[start: start + chunk_size]
            volume = self.correlate_subset(prepared, chunk)
            best[start: start + len(chunk)] = self._amax(volume.reshape(-1, len(chunk)), axis=0)
        return self._to_host(best), (volume if len(references) <= chunk_size else None)

    def _best_of_allowed(self, prepared: PreparedQueries, references: np.ndarray,
                         chunk_size: int, allowed: np.ndarray, candidates: np.ndarray | None
                         ) -> tuple[np.ndarray, "AllowedScores | None"]:
        best = np.full(len(references), -np.inf, dtype=np.float32)
        pairs = None
        for start in range(0, len(references), chunk_size):
            chunk = slice(start, start + chunk_size)
            pairs = self._allowed_scores(prepared, references[chunk], allowed[chunk],
                                         None if candidates is None else candidates[chunk])
            pair_best = self._to_host(self._amax(pairs.scores.reshape(
                len(pairs.positions), self.n_shifts ** 2), axis=1))
            np.maximum.at(best, start + pairs.positions, pair_best)
        return best, (pairs if len(references) <= chunk_size else None)

    def locate(self, prepared: PreparedQueries, references: np.ndarray,
               allowed: np.ndarray | None = None) -> np.ndarray:
        """Best alignment of each reference (among the pairs allowed permits, when given):
        (n, 4) rows of query a, di, dj and the score."""
        if allowed is None:
            return self.peaks(self.correlate_subset(prepared, references))
        return self.peaks(self._allowed_scores(prepared, references, allowed))

    def _allowed_scores(self, prepared: PreparedQueries, references: np.ndarray,
                        allowed: np.ndarray, candidates: np.ndarray | None = None
                        ) -> AllowedScores:
        """The scores of the pairs allowed[k, a] permits, each pair correlated by the 2-D
        spectra of its query and its reference (candidates, the references'
        candidate_spectra, made here when not given): a pair not allowed costs nothing, and no
        operator of every query is built. A pair's product is inverted on the window alone, by
        two matrix products over a chunk of pairs (along y, then along x as a real inverse of
        the half spectrum)."""
        queries, positions = np.nonzero(np.asarray(allowed).T)
        plane = self._plane_spectra(prepared)
        if candidates is None:
            candidates = self.candidate_spectra(references)
        scores = self._empty_scores(len(queries) * self.n_shifts ** 2).reshape(
            len(queries), self.n_shifts, self.n_shifts)
        starts = range(0, len(queries), _PAIRS_PER_CHUNK)

        def correlate(worker: int) -> None:
            """The pairs of every threads-th chunk, from the worker-th on."""
            for first in starts[worker:: self.workers.threads]:
                chunk = slice(first, first + _PAIRS_PER_CHUNK)
                product = self._pair_products(plane, candidates, queries[chunk],
                                              positions[chunk])
                # (pair, di, k): the correlation along y within the window, a spectrum along x.
                along_y = self._along_y @ product
                scores[chunk] = (self._interleaved(along_y).reshape(-1, 2 * self.n_freqs)
                                 @ self._inverse.T).reshape(-1, self.n_shifts, self.n_shifts)

        self.workers.run(correlate)
        return AllowedScores(queries, positions, scores)

    def _plane_spectra(self, prepared: PreparedQueries) -> np.ndarray:
        """The conjugated 2-D spectra (A, column_length, K) of the prepared queries, made once
        per batch."""
        if prepared.plane_spectra is None:
            prepared.plane_spectra = self._conjugated_plane_spectra(prepared.images,
                                                                    prepared.turned_from)
        return prepared.plane_spectra

    def _conjugated_plane_spectra(self, images: np.ndarray,
                                  turned_from: np.ndarray | None = None) -> np.ndarray:
        shape = (self.column_length, self.fft_length)
        if turned_from is None or (turned_from[:, 0] < 0).all():
            return sp_fft.rfft2(images, s=shape).conj()
        direct = turned_from[:, 0] < 0
        spectra = np.empty((len(images), *shape[:1], self.n_freqs), dtype=np.complex64)
        spectra[direct] = sp_fft.rfft2(images[direct], s=shape).conj()
        for turns in (1, 2, 3):
            rows = np.flatnonzero(~direct & (turned_from[:, 1] == turns))
            if len(rows):
                spectra[rows] = self.quarter_turned(spectra[turned_from[rows, 0]], turns)
        return spectra

    def quarter_turned(self, spectra: np.ndarray, turns: int) -> np.ndarray:
        """The conjugated 2-D spectra (n, L, K) of images turned by np.rot90(image, -turns),
        from those of the images (_conjugated_plane_spectra), equal up to rounding: on a square
        transform a turn permutes a spectrum's entries, conjugates those it takes from the half
        not stored (a real image's spectrum is Hermitian), and shifts their phase by the
        image's offset from the origin."""
        if (self.height, self.column_length) != (self.width, self.fft_length):
            raise ValueError("quarter turns need square images")
        turns %= 4
        if turns == 0:
            return spectra
        if turns == 2:
            return self._turn_layouts[2][2] * np.conj(spectra)
        sources, conjugated, phase = self._turn_layouts[turns]
        turned = np.take(spectra.reshape(len(spectra), -1), sources, axis=1).reshape(
            spectra.shape)
        np.conjugate(turned[:, conjugated], out=turned[:, conjugated])
        turned *= phase
        return turned

    @cached_property
    def _turn_layouts(self) -> dict[int, tuple[np.ndarray | None, slice | None, np.ndarray]]:
        """For each number of quarter turns: the flat source of every entry (k, l) of the
        turned spectrum in the stored one, the rows k whose entries are conjugated, and the
        phase. With L the transform's length, K = L // 2 + 1 and H the image's side: one turn
        takes row (-l) mod L, column k, conjugating rows k >= K (taken from row l, column
        L - k); three take row l, column (-k) mod L, conjugating rows 0 < k <= L - K (taken from
        row (-l) mod L, column k); two conjugate every entry in place. The phases are those of
        the image moved back to the origin: exp(2 pi i f (H - 1) / L), f = l, k, k + l."""
        length, n_freqs = self.fft_length, self.n_freqs
        k, l = np.arange(length)[:, None], np.arange(n_freqs)[None, :]

        def phase(frequencies: np.ndarray) -> np.ndarray:
            return np.exp(2j * np.pi * frequencies * (self.height - 1) / length).astype(
                np.complex64)

        one_row = np.where(k < n_freqs, (-l) % length, l)
        one_col = np.where(k < n_freqs, k, (length - k) % length)
        three_stored = (k == 0) | (k > length - n_freqs)
        three_row = np.where(three_stored, l, (-l) % length)
        three_col = np.where(three_stored, (-k) % length, k)
        return {1: ((one_row * n_freqs + one_col).ravel(), slice(n_freqs, None),
                    phase(np.broadcast_to(l, (length, n_freqs)))),
                2: (None, None, phase(k + l)),
                3: ((three_row * n_freqs + three_col).ravel(), slice(1, length - n_freqs + 1),
                    phase(np.broadcast_to(k, (length, n_freqs))))}

    def peaks(self, computed: "np.ndarray | AllowedScores",
              columns: np.ndarray | None = None) -> np.ndarray:
        """As locate, from what best_of_subset computed (only the given columns)."""
        if isinstance(computed, AllowedScores):
            return self._allowed_peaks(computed, columns)
        volume = computed if columns is None else computed[..., self._index(columns)]
        flat, scores = self._argmax_rows(volume.reshape(-1, volume.shape[3]))
        dj, a, di = np.unravel_index(flat, tuple(volume.shape[:3]))
        return np.stack([a, di - self.max_shift, dj - self.max_shift, scores], axis=1)

    def _allowed_peaks(self, pairs: AllowedScores, columns: np.ndarray | None) -> np.ndarray:
        if columns is None:
            columns = np.arange(pairs.positions.max(initial=-1) + 1)
        located = np.zeros((len(columns), 4))
        located[:, 3] = -np.inf
        for row, column in enumerate(np.asarray(columns)):
            own = np.flatnonzero(pairs.positions == column)
            if not len(own):
                continue
            flat, values = self._argmax_rows(
                pairs.scores[self._index(own)].reshape(len(own), self.n_shifts ** 2).T)
            best = int(np.argmax(values))
            di, dj = np.unravel_index(int(flat[best]), (self.n_shifts, self.n_shifts))
            located[row] = (pairs.queries[own[best]], di - self.max_shift,
                            dj - self.max_shift, values[best])
        return located


def _require_shift(max_shift: int) -> None:
    if max_shift < 0:
        raise ValueError(f"max_shift must be >= 0, got {max_shift}")


def _windowed_inverse_dft(length: int, n_freqs: int, max_shift: int) -> np.ndarray:
    """(2S+1, 2K) real matrix: interleaved [Re, Im] half-spectrum -> real signal at |dj| <= S."""
    shifts = np.arange(-max_shift, max_shift + 1)[:, None]
    freqs = np.arange(n_freqs)[None, :]
    weight = half_spectrum_weights(length, n_freqs)
    phase = 2 * np.pi * freqs * shifts / length
    inverse = np.empty((len(shifts), n_freqs, 2))
    inverse[:, :, 0] = weight * np.cos(phase) / length
    inverse[:, :, 1] = -weight * np.sin(phase) / length
    # spectra rows are ordered (k, part); match that ordering.
    return np.ascontiguousarray(inverse.reshape(len(shifts), 2 * n_freqs), dtype=np.float32)


def _windowed_column_inverse(length: int, max_shift: int) -> np.ndarray:
    """(2S+1, L) complex matrix: a length-L spectrum -> its inverse DFT at |di| <= S."""
    shifts = np.arange(-max_shift, max_shift + 1)[:, None]
    return (np.exp(2j * np.pi * shifts * np.arange(length)[None, :] / length)
            / length).astype(np.complex64)


def local_fft_shape(height: int, width: int, max_shift: int) -> tuple[int, int]:
    """The 2-D FFT size of a windowed correlation: 136 = 8 x 17 at the defaults; a 5-smooth
    length is ~2x faster."""
    return (sp_fft.next_fast_len(height + max_shift, real=True),
            sp_fft.next_fast_len(width + max_shift, real=True))


def detail_emphasis(shape: tuple[int, int], sharpening: float) -> np.ndarray:
    """The half-spectrum (shape[0], shape[1] // 2 + 1) of the separable kernel
    [-s, 1 + 2s, -s] along each axis (s = sharpening): 1 at the mean, 1 + 4s at the finest
    detail. A reference so sharpened scores a query by where its cells lie more than by the
    broad mass of its structures (docs/RESULTS.md, session 53)."""
    def along(frequencies: np.ndarray) -> np.ndarray:
        return 1.0 + 2.0 * sharpening * (1.0 - np.cos(2.0 * np.pi * frequencies))

    return (along(np.fft.fftfreq(shape[0]))[:, None]
            * along(np.fft.rfftfreq(shape[1]))[None, :]).astype(np.float32)


class LocalCorrelation:
    """The local stage's windowed correlation by 2-D FFT, for H x W images within max_shift.

    A query's spectrum is computed once (spectra) and correlated with any number of references
    (correlate, pair by pair, every finalist's in one batch): the finalists of one query mostly
    share their headings, and so their turned queries (KITTI 00: 909 distinct headings among
    1500 finalists).
    """

    def __init__(self, image_shape: tuple[int, int], max_shift: int,
                 sharpening: float = 0.0) -> None:
        self.shape = local_fft_shape(*image_shape, max_shift)
        self.window = np.arange(-max_shift, max_shift + 1)
        self.emphasis = detail_emphasis(self.shape, sharpening) if sharpening > 0 else None

    def spectra(self, images: np.ndarray) -> np.ndarray:
        """The spectra of images (..., H, W)."""
        return sp_fft.rfft2(np.asarray(images, dtype=np.float32), s=self.shape, axes=(-2, -1))

    def reference_spectra(self, images: np.ndarray) -> np.ndarray:
        """The spectra of reference images (..., H, W) as the queries are correlated with them:
        sharpened by detail_emphasis when sharpening > 0."""
        spectra = self.spectra(images)
        return spectra if self.emphasis is None else spectra * self.emphasis

    def correlate(self, query_spectra: np.ndarray, reference_spectra: np.ndarray) -> np.ndarray:
        """The windowed correlations (P, 2S+1, 2S+1) of query p with reference p, from their
        spectra (P, ...) (either batch may hold one, for every pair)."""
        return self._windowed(np.conj(query_spectra) * reference_spectra)

    def correlate_pairs(self, query_spectra: Sequence[np.ndarray], reference_spectra: np.ndarray,
                        reference_of_pair: np.ndarray) -> np.ndarray:
        """The windowed correlations (P, 2S+1, 2S+1) of each query spectrum p with
        reference_spectra[reference_of_pair[p]], each conjugated product written straight into
        the batch the inverse runs on (array_ops.pair_products)."""
        return self._windowed(pair_products(query_spectra, reference_spectra,
                                            range(len(query_spectra)), reference_of_pair,
                                            conjugate_left=True))

    def _windowed(self, products: np.ndarray) -> np.ndarray:
        """The correlations within the shift window from their 2-D spectra (P, ...), which it
        overwrites."""
        rows, cols = self.window % self.shape[0], self.window % self.shape[1]
        # Inverse along y first and keep the window's rows: the inverse along x then runs on
        # 2S+1 rows instead of all (~20 % of the whole correlation at the defaults).
        window_rows = sp_fft.ifft(products, axis=-2, overwrite_x=True)[:, rows]
        return sp_fft.irfft(window_rows, n=self.shape[1], axis=-1)[:, :, cols].astype(
            np.float32)


def correlate_fft2(queries: np.ndarray, reference: np.ndarray, max_shift: int) -> np.ndarray:
    """Windowed correlation of a few queries (A, H, W) with one reference (H, W) by 2-D FFT.

    Cheaper than a SpectralBank for a handful of references. Returns (A, 2S+1, 2S+1).
    """
    correlation = LocalCorrelation(reference.shape, max_shift)
    return correlation.correlate(correlation.spectra(queries), correlation.spectra(reference[None]))
