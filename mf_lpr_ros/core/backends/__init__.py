"""Where the search's array work runs: numpy (the default) or torch, behind one factory.

make_backend returns the reference bank, the prefilter and the local-stage correlation for the
backend SearchParams.backend names; core.search uses nothing else backend-specific.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

from mf_lpr_ros.core.matched_filter import LocalCorrelation, SpectralBank
from mf_lpr_ros.core.prefilter import PolarSpectrumIndex
from mf_lpr_ros.core.workers import Workers
from mf_lpr_ros.errors import ConfigError


@dataclass
class SearchBackend:
    """The backend-specific parts of a search."""

    name: str
    bank: SpectralBank
    prefilter: PolarSpectrumIndex | None
    # The local stage's correlation of high-resolution images within the local shift window.
    local: LocalCorrelation
    # The threads one search shares its work among (one on torch, which has its own).
    workers: Workers


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
                 prefilter: bool, local_size: int, local_shift: int, threads: int = 1,
                 local_sharpening: float = 0.0) -> SearchBackend:
    """A bank of image_size^2 low-resolution references searched within max_shift cells (its
    products on threads threads, numpy only), with a prefilter when asked, and the local
    stage's correlation of local_size^2 images within local_shift cells, its references
    sharpened by local_sharpening (matched_filter.detail_emphasis)."""
    resolved = resolve_backend(name)
    if resolved == "torch":
        from mf_lpr_ros.core.backends import torch_backend

        device = torch_backend.default_device()
        return SearchBackend(
            resolved,
            torch_backend.TorchSpectralBank(image_size, image_size, max_shift, capacity, device),
            torch_backend.TorchPolarSpectrumIndex(image_size, capacity, device)
            if prefilter else None,
            torch_backend.TorchLocalCorrelation((local_size, local_size), local_shift, device,
                                                 local_sharpening),
            Workers())
    workers = Workers(threads)
    return SearchBackend(resolved, SpectralBank(image_size, image_size, max_shift, capacity,
                                                workers),
                         PolarSpectrumIndex(image_size, capacity=capacity, workers=workers)
                         if prefilter else None,
                         LocalCorrelation((local_size, local_size), local_shift,
                                          local_sharpening), workers)
