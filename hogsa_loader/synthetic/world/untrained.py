"""An untrained bundle of a world: HOGS parts initialised from MANO and the object template.

What tests, benchmarks and soak runs render with when trained models are not the point:
every Gaussian sits on its mesh face with the template's colour, so the pipeline, the
labels and the file formats are the real ones.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

from hogsa_loader.bundle import write_bundle
from hogsa_loader.datasets.arctic import ArcticRoot
from hogsa_loader.errors import PathLike
from hogsa_loader.gaussians.binding import BindingConfig
from hogsa_loader.gaussians.checkpoint import save_part
from hogsa_loader.gaussians.parts import HandGaussians, ObjectGaussians

__all__ = ["write_untrained_bundle"]


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
    root = ArcticRoot(data_root)
    layers, templates = root.mano_layers(), root.object_templates()
    run = Path(out) / "runs" / f"{subject}_{obj}"
    binding = BindingConfig(k=gaussians_per_face, sh_degree=0)
    save_part(HandGaussians(layers["right"], binding), run / "hand_right", dataset="arctic", subject=subject)
    save_part(HandGaussians(layers["left"], binding), run / "hand_left", dataset="arctic", subject=subject)
    save_part(ObjectGaussians(templates[obj], binding), run / "object", dataset="arctic", subject=subject)
    return write_bundle(Path(out) / "bundle", data_root, [run], srm=srm)
