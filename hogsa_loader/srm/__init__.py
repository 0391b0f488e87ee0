"""SRM: StyleUNet refinement of splat renders (HOGSA's super-resolution module).

Modules: :mod:`~hogsa_loader.srm.stylegan` (StyleGAN2 / wavelet building blocks), :mod:`~hogsa_loader.srm.styleunet`
(the StyleUNet generator), :mod:`~hogsa_loader.srm.discriminator` (conditional wavelet discriminator),
:mod:`~hogsa_loader.srm.losses` (L1, VGG19 or Laplacian-pyramid substitute, GAN, R1), :mod:`~hogsa_loader.srm.model`
(:class:`SRM` with ``refine(rgb, alpha)``), :mod:`~hogsa_loader.srm.io` (:func:`save_srm` / :func:`load_srm`); the
trainer behind ``pretrain/train_srm.py`` is :mod:`hogsa_loader.train.srm_trainer`. Typical use::

    from hogsa_loader.srm import load_srm
    srm = load_srm("runs/srm", device="cuda")
    refined = srm.refine(rgb, alpha)    # (B,H,W,3) premultiplied, alpha (B,H,W)
    refined = srm.refine(rgb, alpha, tta=8)   # mean over the 8 symmetries of the square (8x the cost)
"""

from hogsa_loader.srm.io import load_srm, read_srm_manifest, save_srm, seen_views
from hogsa_loader.srm.model import SRM
from hogsa_loader.srm.styleunet import StyleUNet, StyleUNetConfig, count_gflops

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
