"""Classical rendering utilities (mesh rasterisation, previews) and Gaussian splatting.

The Gaussian-splatting entry point is :func:`render` (gsplat-like, with a CPU backend --
PyTorch, compositing by compiled kernels on the CPU -- and a gsplat CUDA backend), whose
options make one :class:`RenderSettings` and whose tensors one :class:`SplatInputs`; it
imports gsplat lazily, only for CUDA tensors.
"""

from hogsa_loader.render.api import BackendUnavailableError, antialias_compensation, render
from hogsa_loader.render.gaussians import RenderOutput
from hogsa_loader.render.settings import RenderSettings, SplatInputs

__all__ = [
    "render",
    "RenderSettings",
    "SplatInputs",
    "RenderOutput",
    "BackendUnavailableError",
    "antialias_compensation",
]
