"""What this library trains and draws from: HOGS Gaussians, POM grasps, the SRM, the bundle.

* :mod:`~hogsa_loader.models.gaussians` — HOGS: Gaussians bound to mesh faces, checkpoints.
* :mod:`~hogsa_loader.models.pom` — POM: perturbed grasps optimised against a ContactNet.
* :mod:`~hogsa_loader.models.srm` — the SRM (StyleUNet) that refines a coarse render.
* :mod:`~hogsa_loader.models.bundle` — :class:`Bundle`, the trained models a loader draws from.

Training these models lives in :mod:`hogsa_loader.train`; nothing here imports it.
"""
