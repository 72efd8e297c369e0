"""The array primitives the reference banks are written in, on numpy.

SpectralBank and PolarSpectrumIndex do all their array work through these few methods (or
through operators numpy and torch share: `@`, slicing, reshape), so the torch backend only
overrides them (backends.torch_backend.TorchArrays) instead of copying the banks' methods.
Also the weights of a half spectrum in its real inverse, which both banks' inverse matrices
(the windowed correlation's and the prefilter's circular one) are built from, and the products
of pairs written straight into one batch (pair_products), for the global and the local stage.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import fft as sp_fft

from mf_lpr_ros.core.workers import Workers


class NumpyArrays:
    """Storage and reductions on numpy: host and storage are the same memory. Large products
    are shared among the bank's workers (core.workers)."""

    workers: Workers

    @staticmethod
    def _from_host(array: np.ndarray):
        return array

    @staticmethod
    def _to_host(array) -> np.ndarray:
        return np.asarray(array)

    @staticmethod
    def _index(indices) -> np.ndarray:
        return np.asarray(indices, dtype=np.int64)

    @staticmethod
    def _empty_scores(count: int):
        return np.empty(count, dtype=np.float32)

    @staticmethod
    def _amax(values, axis: int):
        # max over a leading axis is memory-bound and ~50x cheaper than argmax.
        return values.max(axis=axis)

    @staticmethod
    def _argmax_rows(values) -> tuple[np.ndarray, np.ndarray]:
        """Per column of a 2-D array: the row of its maximum and the maximum, on the host."""
        rows = values.argmax(axis=0)
        return rows, values[rows, np.arange(values.shape[1])]

    @staticmethod
    def _real_parts(values: np.ndarray) -> np.ndarray:
        """(N, 2 [Re, Im], ...) float32 view of complex64 (N, ...) whose last axis is
        contiguous."""
        return np.moveaxis(values.view(np.float32).reshape(*values.shape, 2), -1, 1)

    @staticmethod
    def _pair_products(left: np.ndarray, right: np.ndarray, left_of_pair: np.ndarray,
                       right_of_pair: np.ndarray) -> np.ndarray:
        return pair_products(left, right, left_of_pair, right_of_pair)

    def _product(self, left, right):
        """left @ right for a product too large for one worker thread to do alone."""
        return self.workers.matmul(left, right)

    @staticmethod
    def _dft(values: np.ndarray, length: int) -> np.ndarray:
        """The DFT of values along their last axis, zero-padded to length."""
        return sp_fft.fft(values, n=length, axis=-1)

    @staticmethod
    def _contiguous(values: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(values)

    @staticmethod
    def _interleaved(values: np.ndarray) -> np.ndarray:
        """complex64 (..., K) as float32 (..., 2K): [Re, Im] of each element in turn."""
        return np.ascontiguousarray(values).view(np.float32)

    @staticmethod
    def _nbytes(array) -> int:
        return array.nbytes


def pair_products(left: Sequence[np.ndarray], right: np.ndarray, left_of_pair: Sequence[int],
                  right_of_pair: Sequence[int], conjugate_left: bool = False) -> np.ndarray:
    """left[left_of_pair[p]] * right[right_of_pair[p]] for each pair p (the left one
    conjugated when conjugate_left), (P, ...): each product written into the batch as it is
    made, neither side gathered into a copy of its own first (the global stage's 256 pairs
    2.4 -> 2.0 ms, the local stage's 15 correlations 2.0 -> 0.7 ms; docs/RESULTS.md, "Scale",
    session 57)."""
    products = np.empty((len(left_of_pair), *right.shape[1:]),
                        dtype=np.result_type(left[0], right))
    for product, first, second in zip(products, left_of_pair, right_of_pair):
        if conjugate_left:
            np.conjugate(left[first], out=product)
            product *= right[second]
        else:
            np.multiply(left[first], right[second], out=product)
    return products


def half_spectrum_weights(length: int, n_freqs: int) -> np.ndarray:
    """How often each frequency of a real signal's half spectrum counts in its inverse: twice,
    but once for the mean and for the Nyquist frequency of an even length."""
    weight = np.full(n_freqs, 2.0)
    weight[0] = 1.0
    if length % 2 == 0:
        weight[-1] = 1.0
    return weight
