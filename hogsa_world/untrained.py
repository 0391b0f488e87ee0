"""An untrained bundle of a world: HOGS parts initialised from MANO and the object template.

What tests, benchmarks and soak runs render with when trained models are not the point:
every Gaussian sits on its mesh face with the template's colour, so the pipeline, the
labels and the file formats are the real ones.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import torch

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.errors import PathLike
from hogsa_loader.models.bundle import write_bundle
from hogsa_loader.models.gaussians.binding import BindingConfig
from hogsa_loader.models.gaussians.checkpoint import save_part
from hogsa_loader.models.gaussians.parts import HandGaussians, ObjectGaussians

__all__ = ["write_untrained_bundle", "write_untrained_run"]


def write_untrained_run(
    data_root: PathLike,
    run: PathLike,
    subject: str,
    obj: str,
    gaussians_per_face: int = 1,
    hand_rgb: Optional[Sequence[float]] = None,
) -> Path:
    """Write one untrained HOGS run ``run/{hand_right,hand_left,object}`` of (subject, object).

    Args:
        data_root: ARCTIC(-format) data root with MANO and the object templates.
        run: the run folder.
        subject, obj: the pair the run stands for (recorded in its manifests).
        gaussians_per_face: Gaussians per mesh face (``k``), SH degree 0.
        hand_rgb: one colour in [0, 1] for every hand Gaussian (default: the hand albedo).

    Returns:
        the run folder.
    """
    root = ArcticRoot(data_root)
    layers, templates = root.mano_layers(), root.object_templates()
    run = Path(run)
    binding = BindingConfig(k=gaussians_per_face, sh_degree=0)
    for side in ("right", "left"):
        hand = HandGaussians(layers[side], binding)
        if hand_rgb is not None:
            hand.splats.set_colors_(torch.tensor([float(c) for c in hand_rgb]))
        save_part(hand, run / f"hand_{side}", dataset="arctic", subject=subject)
    save_part(ObjectGaussians(templates[obj], binding), run / "object", dataset="arctic", subject=subject)
    return run


def write_untrained_bundle(
    data_root: PathLike,
    out: PathLike,
    subject: str = "s01",
    obj: str = "box",
    srm: Optional[PathLike] = None,
    gaussians_per_face: int = 1,
) -> Path:
    """Write ``out/runs/<subject>_<obj>/{hand_right,hand_left,object}`` and the bundle ``out/bundle``.

    Args:
        data_root: ARCTIC(-format) data root with MANO and the object templates.
        out: folder of the runs and the bundle.
        subject, obj: the (subject, object) pair of the single HOGS run.
        srm: an SRM folder to include, or None.
        gaussians_per_face: Gaussians per mesh face (``k``), SH degree 0.

    Returns:
        the bundle folder.
    """
    run = write_untrained_run(data_root, Path(out) / "runs" / f"{subject}_{obj}", subject, obj, gaussians_per_face)
    return write_bundle(Path(out) / "bundle", data_root, [run], srm=srm)
