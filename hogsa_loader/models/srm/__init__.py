"""SRM: StyleUNet refinement of splat renders (HOGSA's super-resolution module).

Modules: :mod:`~hogsa_loader.models.srm.stylegan` (StyleGAN2 / wavelet building blocks),
:mod:`~hogsa_loader.models.srm.styleunet` (the StyleUNet generator), :mod:`~hogsa_loader.models.srm.model`
(:class:`SRM` with ``refine(rgb, alpha)``), :mod:`~hogsa_loader.models.srm.io` (:func:`save_srm` /
:func:`load_srm`). Training (``hogsa train srm``: the discriminator, the losses, the trainer) is in
:mod:`hogsa_loader.train`. Typical use::

    from hogsa_loader.models.srm import load_srm
    srm = load_srm("runs/srm", device="cuda")
    refined = srm.refine(rgb, alpha)    # (B,H,W,3) premultiplied, alpha (B,H,W)
    refined = srm.refine(rgb, alpha, tta=8)   # mean over the 8 symmetries of the square (8x the cost)
"""

from hogsa_loader.models.srm.io import load_srm, read_srm_manifest, save_srm, seen_views
from hogsa_loader.models.srm.model import SRM
from hogsa_loader.models.srm.styleunet import StyleUNet, StyleUNetConfig, count_gflops

__all__ = [
    "SRM",
    "StyleUNet",
    "StyleUNetConfig",
    "count_gflops",
    "load_srm",
    "save_srm",
    "read_srm_manifest",
    "seen_views",
]
