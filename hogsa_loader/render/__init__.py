"""Classical rendering utilities (mesh rasterisation, previews) and Gaussian splatting.

The Gaussian-splatting entry point is :func:`render` (gsplat-like, with a CPU backend --
PyTorch, compositing by compiled kernels on the CPU -- and a gsplat CUDA backend), whose
options make one :class:`RenderSettings`; it imports gsplat lazily, only for CUDA tensors.
"""

from hogsa_loader.render.api import BackendUnavailableError, antialias_compensation, render
from hogsa_loader.render.gaussians import RenderOutput
from hogsa_loader.render.settings import RenderSettings

__all__ = ["render", "RenderSettings", "RenderOutput", "BackendUnavailableError", "antialias_compensation"]
