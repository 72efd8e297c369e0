"""Where the search's array work runs: numpy (the default) or torch, behind one factory.

make_backend returns the reference bank, the prefilter and the local-stage correlation for the
backend SearchParams.backend names; core.search uses nothing else backend-specific.
"""

from __future__ import annotations

import functools
import importlib
from dataclasses import dataclass
from typing import Callable

import numpy as np

from mf_lpr_ros.core.matched_filter import SpectralBank, local_correlator
from mf_lpr_ros.core.prefilter import PolarSpectrumIndex
from mf_lpr_ros.errors import ConfigError

BACKENDS = ("auto", "numpy", "torch")


@dataclass
class SearchBackend:
    """The backend-specific parts of a search."""

    name: str
    bank: SpectralBank
    prefilter: PolarSpectrumIndex | None
    # (reference image, max shift) -> the windowed correlation of query batches with it.
    local_correlator: Callable[[np.ndarray, int], Callable[[np.ndarray], np.ndarray]]


def resolve_backend(name: str) -> str:
    """The backend SearchParams.backend names: "numpy" or "torch" ("auto": torch on CUDA)."""
    if name == "numpy":
        return "numpy"
    try:
        torch_backend = importlib.import_module(f"{__name__}.torch_backend")
    except ImportError as error:
        if name == "torch":
            raise ConfigError(f"parameter backend is 'torch' but PyTorch cannot be imported "
                              f"({error})") from error
        return "numpy"
    return "torch" if name == "torch" or torch_backend.cuda_available() else "numpy"


def make_backend(name: str, image_size: int, max_shift: int, capacity: int,
                 prefilter: bool) -> SearchBackend:
    """A bank of image_size^2 low-resolution references searched within max_shift cells, with
    a prefilter when asked."""
    resolved = resolve_backend(name)
    if resolved == "torch":
        from mf_lpr_ros.core.backends import torch_backend

        device = torch_backend.default_device()
        return SearchBackend(
            resolved,
            torch_backend.TorchSpectralBank(image_size, image_size, max_shift, capacity, device),
            torch_backend.TorchPolarSpectrumIndex(image_size, capacity, device)
            if prefilter else None,
            functools.partial(torch_backend.local_correlator, device=device))
    return SearchBackend(resolved, SpectralBank(image_size, image_size, max_shift, capacity),
                         PolarSpectrumIndex(image_size, capacity=capacity) if prefilter else None,
                         local_correlator)
