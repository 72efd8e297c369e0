"""The search's array work on PyTorch: a CUDA GPU when there is one, else torch's CPU build.

The classes mirror SpectralBank and PolarSpectrumIndex and keep their storage on the device;
what they return to the search (scores, peak locations) is numpy, so everything above them is
shared with the numpy backend and the two give the same matches (test_torch_backend.py).
Imported only when SearchParams.backend asks for torch (or "auto" finds a CUDA device).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy import fft as sp_fft

from .matched_filter import SpectralBank
from .prefilter import PolarSpectrumIndex


def cuda_available() -> bool:
    return torch.cuda.is_available()


def default_device() -> torch.device:
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


class TorchSpectralBank(SpectralBank):
    """SpectralBank with the bank and the query operator on a torch device."""

    def __init__(self, height: int, width: int, max_shift: int, capacity: int = 64,
                 device: torch.device | None = None) -> None:
        self.device = device or default_device()
        super().__init__(height, width, max_shift, capacity=capacity)
        self._inverse = torch.from_numpy(self._inverse).to(self.device)

    @property
    def nbytes(self) -> int:
        return self._bank.numel() * self._bank.element_size() + self._norms.nbytes

    def append(self, images: np.ndarray) -> None:
        images = np.asarray(images, dtype=np.float32)
        if images.ndim != 3 or images.shape[1:] != (self.height, self.width):
            raise ValueError(f"expected (n, {self.height}, {self.width}) images, got {images.shape}")
        start, stop = self._count, self._count + len(images)
        self._reserve(stop)
        spectra = sp_fft.rfft(images, n=self.fft_length, axis=2)
        stacked = np.concatenate([spectra.real, spectra.imag], axis=1).transpose(2, 1, 0)
        self._bank[:, :, start:stop] = torch.from_numpy(np.ascontiguousarray(stacked)).to(
            self.device)
        self._norms[start:stop] = np.sqrt(np.einsum("nij,nij->n", images, images))
        self._count = stop

    def _new_bank(self, capacity: int) -> torch.Tensor:
        return torch.zeros((self.n_freqs, 2 * self.height, capacity), dtype=torch.float32,
                           device=self.device)

    def reserve_operator(self, n_queries: int) -> tuple[int, ...]:
        """The operator lives on the device, built per query: no host buffer."""
        return (self.n_freqs, 2, n_queries, 2 * self.max_shift + 1, 2 * self.height)

    def prepare_queries(self, queries: np.ndarray) -> torch.Tensor:
        height, shift = self.height, self.max_shift
        images = torch.from_numpy(np.asarray(queries, dtype=np.float32)).to(self.device)
        spectra = torch.fft.rfft(images, n=self.fft_length, dim=2).permute(2, 0, 1)
        padded = torch.zeros((2, self.n_freqs, len(images), height + 2 * shift),
                             dtype=torch.float32, device=self.device)
        padded[0, :, :, shift: shift + height] = spectra.real
        padded[1, :, :, shift: shift + height] = spectra.imag
        # (2, K, A, 2S+1, H): window t of every row, t reversed so that di ascends.
        real, imag = padded.unfold(3, height, 1).flip(3)
        top = torch.cat([real, imag], dim=3)
        bottom = torch.cat([-imag, real], dim=3)
        operator = torch.stack([top, bottom], dim=1)
        return operator.reshape(self.n_freqs, -1, 2 * height)

    def correlate_subset(self, operator: torch.Tensor, references: np.ndarray) -> torch.Tensor:
        index = torch.as_tensor(np.asarray(references, dtype=np.int64), device=self.device)
        return self._correlate(operator, self._bank.index_select(2, index))

    def best_per_reference(self, operator: torch.Tensor, stop: int | None = None,
                           chunk_size: int = 256) -> np.ndarray:
        stop = self._count if stop is None else min(stop, self._count)
        best = torch.empty(stop, dtype=torch.float32, device=self.device)
        for start in range(0, stop, chunk_size):
            end = min(start + chunk_size, stop)
            best[start:end] = self.correlate_block(operator, start, end).reshape(
                -1, end - start).amax(dim=0)
        return best.cpu().numpy()

    def best_of_subset(self, operator: torch.Tensor, references: np.ndarray,
                       chunk_size: int = 256) -> tuple[np.ndarray, torch.Tensor | None]:
        references = np.asarray(references, dtype=np.int64)
        best = torch.empty(len(references), dtype=torch.float32, device=self.device)
        volume = None
        for start in range(0, len(references), chunk_size):
            chunk = references[start: start + chunk_size]
            volume = self.correlate_subset(operator, chunk)
            best[start: start + len(chunk)] = volume.reshape(-1, len(chunk)).amax(dim=0)
        return best.cpu().numpy(), (volume if len(references) <= chunk_size else None)

    def peaks(self, volume: torch.Tensor, columns: np.ndarray | None = None) -> np.ndarray:
        if columns is not None:
            index = torch.as_tensor(np.asarray(columns, dtype=np.int64), device=self.device)
            volume = volume.index_select(3, index)
        per_reference = volume.reshape(-1, volume.shape[3])
        flat = per_reference.argmax(dim=0)
        scores = per_reference.gather(0, flat[None])[0].cpu().numpy()
        dj, a, di = np.unravel_index(flat.cpu().numpy(), tuple(volume.shape[:3]))
        return np.stack([a, di - self.max_shift, dj - self.max_shift, scores], axis=1)


class TorchPolarSpectrumIndex(PolarSpectrumIndex):
    """PolarSpectrumIndex with the reference spectra on a torch device."""

    def __init__(self, image_size: int, capacity: int = 64,
                 device: torch.device | None = None) -> None:
        self.device = device or default_device()
        super().__init__(image_size, capacity=capacity)
        self._inverse_real = torch.from_numpy(self._inverse_real).to(self.device)
        self._inverse_imag = torch.from_numpy(self._inverse_imag).to(self.device)

    @property
    def nbytes(self) -> int:
        return self._bank.numel() * self._bank.element_size()

    def append(self, images: np.ndarray) -> None:
        self._store(torch.from_numpy(np.ascontiguousarray(
            self.features(images).transpose(1, 0, 2))).to(self.device))

    def _new_bank(self, capacity: int) -> torch.Tensor:
        return torch.zeros((self.n_harmonics, capacity, self.n_radii), dtype=torch.complex64,
                           device=self.device)

    def scores(self, image: np.ndarray, stop: int | None = None) -> np.ndarray:
        stop = self._count if stop is None else min(stop, self._count)
        query = torch.from_numpy(self.features(image[None])[0]).to(self.device)
        cross = torch.matmul(self._bank[:, :stop], query.conj()[:, :, None])[:, :, 0]
        correlation = cross.real.T @ self._inverse_real + cross.imag.T @ self._inverse_imag
        return correlation.amax(dim=1).cpu().numpy()


def correlate_fft2(queries: np.ndarray, reference: np.ndarray, max_shift: int,
                   device: torch.device | None = None) -> np.ndarray:
    """matched_filter.correlate_fft2 on a torch device."""
    device = device or default_device()
    height, width = reference.shape
    shape = (sp_fft.next_fast_len(height + max_shift, real=True),
             sp_fft.next_fast_len(width + max_shift, real=True))
    query_spectra = torch.fft.rfft2(torch.from_numpy(np.asarray(queries, np.float32)).to(device),
                                    s=shape)
    ref_spectrum = torch.fft.rfft2(torch.from_numpy(np.asarray(reference, np.float32)).to(device),
                                   s=shape)
    full = torch.fft.irfft2(query_spectra.conj() * ref_spectrum, s=shape)
    window = torch.arange(-max_shift, max_shift + 1, device=device)
    rows, cols = window % shape[0], window % shape[1]
    return full[:, rows][:, :, cols].cpu().numpy()
