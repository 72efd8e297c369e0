"""The search's array work on PyTorch: a CUDA GPU when there is one, else torch's CPU build.

The banks keep their storage on the device and override only the array primitives
(TorchArrays, after array_ops.NumpyArrays); what they return to the search (scores, peak
locations) is numpy, so everything above them is shared with the numpy backend and the two
give the same matches (test_torch_backend.py). Imported only when SearchParams.backend asks for
torch (or "auto" finds a CUDA device).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from mf_lpr_ros.core.matched_filter import LocalCorrelation, SpectralBank
from mf_lpr_ros.core.prefilter import PolarSpectrumIndex


def cuda_available() -> bool:
    return torch.cuda.is_available()


def default_device() -> torch.device:
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


class TorchArrays:
    """array_ops.NumpyArrays' primitives on a torch device (set self.device first)."""

    device: torch.device

    def _from_host(self, array: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(array)).to(self.device)

    @staticmethod
    def _product(left: torch.Tensor, right: torch.Tensor) -> torch.Tensor:
        return left @ right

    def _pair_products(self, left: torch.Tensor, right: torch.Tensor,
                       left_of_pair: np.ndarray, right_of_pair: np.ndarray) -> torch.Tensor:
        return left[self._index(left_of_pair)] * right[self._index(right_of_pair)]

    @staticmethod
    def _to_host(tensor: torch.Tensor) -> np.ndarray:
        return tensor.cpu().numpy()

    def _index(self, indices) -> torch.Tensor:
        return torch.as_tensor(np.asarray(indices, dtype=np.int64), device=self.device)

    def _empty_scores(self, count: int) -> torch.Tensor:
        return torch.empty(count, dtype=torch.float32, device=self.device)

    @staticmethod
    def _amax(values: torch.Tensor, axis: int) -> torch.Tensor:
        return values.amax(dim=axis)

    @staticmethod
    def _argmax_rows(values: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        rows = values.argmax(dim=0)
        return rows.cpu().numpy(), values.gather(0, rows[None])[0].cpu().numpy()

    @staticmethod
    def _real_parts(values: torch.Tensor) -> torch.Tensor:
        return torch.view_as_real(values).movedim(-1, 1)

    @staticmethod
    def _dft(values: torch.Tensor, length: int) -> torch.Tensor:
        return torch.fft.fft(values, n=length, dim=-1)

    @staticmethod
    def _contiguous(values: torch.Tensor) -> torch.Tensor:
        return values.contiguous()

    @staticmethod
    def _interleaved(values: torch.Tensor) -> torch.Tensor:
        return torch.view_as_real(values.contiguous()).flatten(-2)

    @staticmethod
    def _nbytes(tensor: torch.Tensor) -> int:
        return tensor.numel() * tensor.element_size()


class TorchSpectralBank(TorchArrays, SpectralBank):
    """SpectralBank with the bank and the query operators on a torch device. Operators are
    built on the device for each query batch (no reused host buffers, unlike numpy's), and so
    are the candidates' 2-D spectra: SpectralBank keeps those in a numpy array, not on a
    device."""

    kept_plane_spectra_bytes = 0

    def __init__(self, height: int, width: int, max_shift: int, capacity: int = 64,
                 device: torch.device | None = None) -> None:
        self.device = device or default_device()
        super().__init__(height, width, max_shift, capacity=capacity)
        self._inverse = self._from_host(self._inverse)
        self._along_y = self._from_host(self._along_y)

    def _new_bank(self, capacity: int) -> torch.Tensor:
        return torch.zeros((capacity, self.n_freqs, self.height), dtype=torch.complex64,
                           device=self.device)

    @staticmethod
    def _columns(blocks: torch.Tensor) -> torch.Tensor:
        return blocks.permute(1, 2, 0)

    def reserve_operator(self, n_queries: int) -> tuple[int, ...]:
        return (self.n_freqs, n_queries, self.n_shifts, self.height)

    def _operator_buffer(self, shape: tuple[int, ...]) -> None:
        return None

    def _windows(self, images: torch.Tensor) -> torch.Tensor:
        height, shift = self.height, self.max_shift
        rows = torch.zeros((self.n_freqs, len(images), height + 2 * shift),
                           dtype=torch.complex64, device=self.device)
        spectra = torch.fft.rfft(images, n=self.fft_length, dim=2)
        rows[:, :, shift: shift + height] = spectra.permute(2, 0, 1).conj()
        # (K, A, 2S+1, H): window t of every row, t reversed so that di ascends.
        return rows.unfold(2, height, 1).flip(2)

    def _conjugated_plane_spectra(self, images: torch.Tensor,
                                  turned_from: np.ndarray | None = None) -> torch.Tensor:
        # Every image transformed: quarter turns are laid out on the numpy path only.
        return torch.fft.rfft2(images, s=(self.column_length, self.fft_length)).conj()

    def _expand(self, windows: torch.Tensor, out: None) -> torch.Tensor:
        return windows.reshape(self.n_freqs, -1, self.height)


class TorchPolarSpectrumIndex(TorchArrays, PolarSpectrumIndex):
    """PolarSpectrumIndex with the reference spectra on a torch device."""

    def __init__(self, image_size: int, capacity: int = 64,
                 device: torch.device | None = None) -> None:
        self.device = device or default_device()
        super().__init__(image_size, capacity=capacity)
        self._inverse = self._from_host(self._inverse)
        self._score_inverse = self._from_host(self._score_inverse)

    def _new_bank(self, capacity: int) -> torch.Tensor:
        return torch.zeros((self.n_harmonics, capacity, self.n_radii), dtype=torch.complex64,
                           device=self.device)

    def adopt(self, features: np.ndarray) -> None:
        # The device needs its own copy; a read-only memory map cannot back a tensor.
        super().adopt(np.array(features))


class TorchLocalCorrelation(LocalCorrelation):
    """matched_filter.LocalCorrelation on a torch device (spectra stay on it)."""

    def __init__(self, image_shape: tuple[int, int], max_shift: int,
                 device: torch.device | None = None, sharpening: float = 0.0) -> None:
        super().__init__(image_shape, max_shift, sharpening)
        self.device = device or default_device()
        if self.emphasis is not None:
            self.emphasis = torch.from_numpy(self.emphasis).to(self.device)

    def spectra(self, images: np.ndarray) -> torch.Tensor:
        return torch.fft.rfft2(torch.from_numpy(np.asarray(images, np.float32)).to(self.device),
                               s=self.shape)

    def correlate_pairs(self, query_spectra: Sequence[torch.Tensor],
                        reference_spectra: torch.Tensor, reference_of_pair: np.ndarray
                        ) -> np.ndarray:
        pairs = torch.from_numpy(np.asarray(reference_of_pair, dtype=np.int64)).to(self.device)
        return self.correlate(torch.stack(list(query_spectra)), reference_spectra[pairs])

    def correlate(self, query_spectra: torch.Tensor, reference_spectra: torch.Tensor
                  ) -> np.ndarray:
        window = torch.from_numpy(self.window).to(self.device)
        rows, cols = window % self.shape[0], window % self.shape[1]
        full = torch.fft.irfft2(query_spectra.conj() * reference_spectra, s=self.shape)
        return full[:, rows][:, :, cols].cpu().numpy()
