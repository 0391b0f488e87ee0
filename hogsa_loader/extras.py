"""Optional dependencies: what each extra of ``pip install hogsa-loader[EXTRA]`` brings, and
one-line errors when a feature needs an extra that is not installed.

The core install is what the runtime loader needs. The extras:

- ``cpu``: numba, the compiled CPU kernels of the rasterisers (without it the PyTorch paths
  run, with the same results, slower);
- ``coco``: pycocotools, COCO backgrounds (``coco_root`` / ``coco_ann``);
- ``demo``: scikit-image, the generated test world (procedural textures, the synthetic hand)
  and the demo's photographs, for ``hogsa demo``, ``hogsa world`` and ``hogsa assets``;
- ``cuda``: gsplat, the CUDA Gaussian rasteriser;
- ``test``: everything above plus the test tools.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from hogsa_loader.errors import HogsaError

__all__ = ["MissingExtraError", "require"]


class MissingExtraError(HogsaError, ImportError):
    """A feature needs a package of an extra that is not installed; the message names both."""


def require(module: str, extra: str, feature: str) -> ModuleType:
    """Import ``module`` for ``feature``, or say which extra brings it.

    Args:
        module: the module to import (``"pycocotools.coco"``).
        extra: the extra of hogsa-loader that installs it (``"coco"``).
        feature: what needs it, as the user named it (``"COCO backgrounds"``).

    Returns:
        the imported module.

    Raises:
        MissingExtraError: ``module`` cannot be imported.
    """
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        top = module.split(".")[0]
        raise MissingExtraError(
            f"{feature} needs the package that provides '{top}' ({exc.name or top} is not installed): "
            f"pip install 'hogsa-loader[{extra}]'"
        ) from None
