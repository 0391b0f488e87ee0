"""A dataset root opened by its format: ARCTIC's ``./data``, or H2O with its MANO and mesh folders."""

from __future__ import annotations

from typing import Optional, Union

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.assets.h2o_poses import H2OPoseRoot
from hogsa_loader.errors import PathLike, UsageError

__all__ = ["DATASETS", "DatasetRoot", "open_dataset_root"]

#: The dataset formats a root can have.
DATASETS = ("arctic", "h2o")
#: An opened root: what the pose stages, the build and the bundle read.
DatasetRoot = Union[ArcticRoot, H2OPoseRoot]


def open_dataset_root(
    dataset: str, root: PathLike, mano_dir: Optional[PathLike] = None, object_mesh_dir: Optional[PathLike] = None
) -> DatasetRoot:
    """Open ``root`` as ``dataset``: an :class:`ArcticRoot` (ARCTIC keeps MANO and the object
    templates in its root), or an :class:`H2OPoseRoot` with ``mano_dir`` and ``object_mesh_dir``.

    Raises:
        UsageError: an unknown dataset, an H2O root without one of the folders (the flag is
            named), or an ARCTIC root given one.
        AssetError: a folder is missing.
    """
    if dataset not in DATASETS:
        raise UsageError(f"--dataset: expected one of {', '.join(DATASETS)}, got {dataset!r}")
    folders = {"--mano-dir": mano_dir, "--object-mesh-dir": object_mesh_dir}
    if dataset == "h2o":
        missing = [flag for flag, value in folders.items() if not value]
        if missing:
            raise UsageError(
                f"--dataset h2o needs {' and '.join(missing)} (H2O keeps MANO and its meshes outside its root)"
            )
        return H2OPoseRoot(root, mano_dir, object_mesh_dir)
    extra = [flag for flag, value in folders.items() if value]
    if extra:
        raise UsageError(f"{', '.join(extra)}: only for --dataset h2o (ARCTIC keeps its models in the data root)")
    return ArcticRoot(root)
