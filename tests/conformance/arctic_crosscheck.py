#!/usr/bin/env python
"""Cross-check a world, the real-data dataset and the synthetic loader against ARCTIC's own code.

Example::

    python tests/conformance/arctic_crosscheck.py --arctic-src ~/code/arctic --data ./hogsa_world \
        --json out/arctic_crosscheck.json

``--arctic-src`` is an unmodified checkout of ``zc-alexfan/arctic`` (its ``src/`` and
``common/`` are used as they are); ``--data`` is the world: the folder that plays ARCTIC's
``./data`` (holding ``arctic_data/data`` and ``body_models``) or its ``arctic_data/data``.
Nothing of ARCTIC's is copied into this project: its modules are imported from the
checkout and run, in a temporary working folder that holds ``data`` (a link to the world),
``src`` and ``common`` (links into the checkout), because ARCTIC's code opens
``./data/arctic_data/data/...`` relative to the working folder.

Checks (``--checks``, default all four):

``dataset``
    ARCTIC's ``src/datasets/arctic_dataset.py`` ``ArcticDataset`` against
    :class:`hogsa_loader.sample.arctic_dataset.ArcticDataset` on the same split files,
    for ``p1``/``p2`` × ``train``/``val``: the same image names, then ``--items`` items per
    split compared field by field (keys and their order, python type, dtype, shape, max
    and mean absolute difference). Train splits are compared twice: with augmentation
    (ARCTIC's own ``augm_params`` code runs, but its ``np.random`` draws are routed to the
    per-item generator that our dataset uses, so both get the same rotation, scale and
    colour noise) and with augmentation off. Tolerances: 2D labels (``*2d.norm*``) exact;
    the image ``inputs.img`` within ``--img-tol`` (max abs, normalised units; one 8-bit
    grey level is about 0.017) and a mean below a tenth of it; every other number
    within 1e-4.
``train``
    One ArcticNet-SF training step with ARCTIC's own ``ArcticSFWrapper``
    (``src/models/arctic_sf/``: ResNet-50 backbone, its ``process_data`` and
    ``compute_loss``) on a batch of ``--batch`` samples mixed by
    :class:`hogsa_loader.sample.MixedLoader`: real samples of our ``ArcticDataset``
    (``p1_train``) and synthetic samples of :class:`hogsa_loader.sample.HOGSADataset`
    (``--synthetic-ratio``). With ``--bundle`` the synthetic samples come from that
    bundle; without it an *untrained* bundle (Gaussians initialised from the world's MANO
    and object template, ``perturb`` poses, procedural backgrounds) is built in the work
    folder, which exercises the same sample code at no training cost. Passes when every
    loss key of ARCTIC's ``compute_loss`` is present and finite, the total loss and every
    gradient are finite, and the optimiser step changes the weights. The losses of the
    real-only and synthetic-only halves are reported too.
``processing``
    ARCTIC's ``src/arctic/processing.py`` ``process_seq`` on every raw sequence of the
    world (on the CPU) and ``src/arctic/split.py`` ``build_split`` for ``p1``/``p2`` ×
    ``train``/``val`` (and ``test`` where the world has one), compared with the world's
    ``splits/*.npy`` (written by :mod:`hogsa_loader.assets.arctic_processing`): image
    names, sequences, then per key shape, dtype and max abs difference (rotations as the
    geodesic angle between the two rotations). Keys that only ARCTIC writes because the
    project's worlds have no body (``joints.smplx``, ``smplx_*``) are listed, not failed.
``field``
    InterField-SF's loss and metrics against ARCTIC's ``src/callbacks/loss/loss_field.py``
    ``dist_loss`` and ``src/utils/eval_modules.py`` ``eval_field_errors`` /
    ``eval_acc_field``: one clip of ``p1_train`` (its first 8 frames in temporal order, no
    augmentation), the field targets prepared by
    :func:`hogsa_loader.baselines.prepare_targets` (clamped to 0.1 m), the predictions of a
    randomly initialised :class:`hogsa_loader.baselines.InterFieldSF` and the targets plus
    Gaussian noise; both sides get the same tensors. Passes when every loss term, per-frame
    average error and acceleration error agrees within a relative 1e-5 (and NaN where the
    other is NaN), and when the state dict of ARCTIC's ``FieldSF`` (resnet18, saved as a
    Lightning checkpoint) loads into an ``InterFieldSF`` through
    :func:`hogsa_loader.baselines.load_field_weights` with every name, shape and value
    unchanged (ARCTIC's up-samplers have 778 hand and 4000 object outputs; where the world's
    MANO or longest object template differs, both models get the world's counts).

Packages. ARCTIC imports packages that a CPU-only machine may lack. Those that ``pip``
installs and that the selected checks really run (``loguru``, ``easydict``,
``pytorch_lightning``) are required: without them the script stops (exit 2) and prints
the ``pip install`` line. The others get a minimal stub injected through ``sys.modules``
(only when the real module does not import), and the report lists every stub with what
it replaces and why:

* ``pytorch3d`` — no wheel or source release for this torch/python on PyPI (its CUDA/C++
  build is not pip-installable here); ARCTIC uses ``rotation_conversions``
  (axis-angle ↔ matrix, 6D ↔ matrix) and ``ops.knn_points``: reimplemented with the
  project's :mod:`hogsa_loader.geometry.rotations` and an exact brute-force search;
* ``torchvision`` — the PyPI wheel for a CPU-only torch build may not load
  (``operator torchvision::nms does not exist``); ARCTIC uses ``transforms.Normalize``;
* ``chumpy`` — read by smplx's MANO pickle loader; chumpy 0.70 does not import on
  Python ≥ 3.11 / numpy ≥ 1.24; the stub only turns the pickled ``Ch`` state into arrays;
* ``pyrender`` — ARCTIC's visualisation renderer (needs an EGL context), never used in
  the forward pass or the loss;
* ``comet_ml`` — experiment logging, imported at module level but never called here
  (``pip install comet_ml`` gives the real one).

Run-time patches (printed too; neither the installed packages nor the checkout change):
smplx's ``MANO`` returns ARCTIC's 21 joints (ARCTIC's setup asks users to uncomment
``joints = self.vertex_joint_selector(vertices, joints)`` in smplx; here
``common.body_models.MANO`` is a subclass that appends the same fingertip vertices);
``Tensor.cuda`` is a no-op while ARCTIC's code runs on a machine without CUDA (ARCTIC
calls ``.cuda()`` unconditionally in processing); the ResNet-50 ImageNet download is
replaced by random initialisation (or ``--resnet-weights``); the visualisation
``Renderer`` is a no-op.

Missing files. Before running, the files ARCTIC's code opens are listed against the
world (meta files, the 11 object templates of ARCTIC's ``OBJECTS``, MANO and SMPL-X
models, subject templates, raw sequences, split files, images); a check whose required
files are missing is reported as ``SKIPPED`` (and fails the run).

Output: a report on stdout (a table per check) and, with ``--json``, every figure.
Exit code 0 when every selected check passes, 1 otherwise, 2 for usage errors (a missing
folder, an unknown check, a package to pip-install).
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import json
import math
import os
import platform
import shutil
import sys
import tempfile
import time
import traceback
import types
from collections import namedtuple
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Optional, Sequence

import numpy as np

# ----------------------------------------------------------------------------------------
# Constants (facts read from ARCTIC's code; see the docstrings for the file each comes from)
# ----------------------------------------------------------------------------------------

CHECKS = ("dataset", "train", "processing", "field")
SPLITS = ("p1_train", "p1_val", "p2_train", "p2_val")
ARCTIC_SUBDIR = "arctic_data/data"

#: ``common/object_tensors.py`` ``OBJECTS`` (read from the checkout when it is given).
ARCTIC_OBJECTS_FALLBACK = (
    "capsulemachine",
    "box",
    "ketchup",
    "laptop",
    "microwave",
    "mixer",
    "notebook",
    "espressomachine",
    "waffleiron",
    "scissors",
    "phone",
)
#: Files of one object template opened by ``common/object_tensors.py`` ``construct_obj``.
OBJECT_TEMPLATE_FILES = (
    "mesh.obj",
    "parts.json",
    "object_params.json",
    "top_keypoints_300.json",
    "bottom_keypoints_300.json",
)
#: ``misc.json`` fields per subject read by ARCTIC (dataset, processing, SMPL-X).
MISC_FIELDS = ("world2cam", "intris_mat", "image_size", "ioi_offset", "gender")
#: ``scripts_data/build_splits.py`` default ``--request_keys``.
REQUEST_KEYS = ("cam_coord", "2d", "bbox", "params")

#: Packages ARCTIC's code needs that pip installs: import name -> (pip name, checks, used for).
PIP_PACKAGES: dict[str, tuple[str, tuple[str, ...], str]] = {
    "loguru": ("loguru", CHECKS, "ARCTIC's logger (imported by most modules)"),
    "easydict": ("easydict", CHECKS, "common/object_tensors.py, src/parsers/parser.py"),
    "pytorch_lightning": (
        "pytorch_lightning",
        ("train",),
        "common/abstract_pl.py: ArcticSFWrapper is a LightningModule",
    ),
}

#: Modules that get a stub when they do not import: name -> (what is replaced, why).
STUB_REASONS: dict[str, tuple[str, str]] = {
    "pytorch3d": (
        "pytorch3d.transforms.rotation_conversions (axis_angle_to_matrix, matrix_to_axis_angle, "
        "rotation_6d_to_matrix, matrix_to_rotation_6d) and pytorch3d.ops.knn_points",
        "not installable with pip here (no PyPI wheel or source release for this torch/python; "
        "the real package needs a CUDA/C++ build); reimplemented with hogsa_loader.geometry.rotations "
        "and an exact brute-force nearest-neighbour search",
    ),
    "torchvision": (
        "torchvision.transforms.Normalize (src/datasets/arctic_dataset.py)",
        "torchvision does not import with this torch (the PyPI wheel matching a CPU-only torch "
        "build fails with 'operator torchvision::nms does not exist'); Normalize is "
        "(x - mean) / std per channel in float32",
    ),
    "chumpy": (
        "chumpy classes inside the MANO .pkl files that smplx unpickles",
        "chumpy 0.70 (PyPI) does not import on Python >= 3.11 / numpy >= 1.24 "
        "(inspect.getargspec, numpy.bool/int aliases); the stub keeps the pickled state and "
        "gives its array (np.asarray / slicing), nothing else",
    ),
    "pyrender": (
        "pyrender (common/rend_utils.py, ARCTIC's visualisation renderer)",
        "needs an OpenGL/EGL context; only used to render visualisations, never in the forward "
        "pass or the loss (the wrapper's Renderer is patched to a no-op anyway)",
    ),
    "comet_ml": (
        "comet_ml (common/comet_utils.py, experiment logging)",
        "imported at module level but only used to create/log experiments, which this check never "
        "does; 'pip install comet_ml' gives the real one",
    ),
}

#: Tolerances (see module docstring).
DEFAULT_IMG_TOL = 0.05
NUMBER_TOL = 1e-4
#: Allocentric cropped-image side ARCTIC's code hard-codes (dataset_utils.py, data_utils.transform_kp2d).
ARCTIC_CROPPED_SIZE = 1000
SPLIT_TOL = {"2d": 1e-2, "bbox": 1e-3, "rot": 1e-4, "flag": 0.0, "point": 1e-5, "param": 1e-6}


class UsageError(Exception):
    """A command-line or setup problem (exit code 2)."""


# ----------------------------------------------------------------------------------------
# Notes: stubs, patches, packages (printed, never silent)
# ----------------------------------------------------------------------------------------


@dataclass
class Notes:
    stubs: list[dict[str, str]] = field(default_factory=list)
    patches: list[dict[str, str]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    def stub(self, name: str) -> None:
        replaces, why = STUB_REASONS[name]
        if not any(s["module"] == name for s in self.stubs):
            self.stubs.append({"module": name, "replaces": replaces, "why": why})

    def patch(self, what: str, how: str, why: str) -> None:
        if not any(p["what"] == what for p in self.patches):
            self.patches.append({"what": what, "how": how, "why": why})


def _ordered_union(groups: Any) -> list[str]:
    """The keys of several mappings, each once, in order of first appearance."""
    return list(dict.fromkeys(k for g in groups for k in g))


def plan_packages(importable: Mapping[str, bool], checks: Sequence[str]) -> tuple[list[str], list[str]]:
    """Which stubs to inject and which pip packages are missing for ``checks``.

    Args:
        importable: module name -> whether the real module imports.
        checks: the selected checks.

    Returns:
        ``(stubs, pip_missing)``: modules of :data:`STUB_REASONS` that do not import (in
        that order), and pip names of :data:`PIP_PACKAGES` that the checks need and that do
        not import.
    """
    stubs = [m for m in STUB_REASONS if not importable.get(m, False)]
    pip_missing = [
        pip
        for mod, (pip, needed_by, _) in PIP_PACKAGES.items()
        if not importable.get(mod, False) and any(c in needed_by for c in checks)
    ]
    return stubs, pip_missing


def module_imports(name: str) -> bool:
    """True when ``import name`` works; a failed import leaves nothing in ``sys.modules``."""
    if importlib.util.find_spec(name) is None:
        return False
    before = set(sys.modules)
    try:
        importlib.import_module(name)
        return True
    except Exception:  # a broken install (e.g. torchvision vs. a CPU torch): treat as absent
        for mod in set(sys.modules) - before:
            if mod == name or mod.startswith(name + "."):
                del sys.modules[mod]
        return False


# ----------------------------------------------------------------------------------------
# Stub modules
# ----------------------------------------------------------------------------------------


def _module(name: str, doc: str, **attrs: Any) -> types.ModuleType:
    mod = types.ModuleType(name, doc)
    mod.__dict__.update(attrs)
    mod.__dict__["__hogsa_stub__"] = True
    return mod


def make_pytorch3d_stub() -> dict[str, types.ModuleType]:
    """``pytorch3d``, ``pytorch3d.transforms(.rotation_conversions)``, ``pytorch3d.ops``."""
    import torch
    import torch.nn.functional as F

    from hogsa_loader.geometry import rotations

    def axis_angle_to_matrix(axis_angle: torch.Tensor) -> torch.Tensor:
        return rotations.axis_angle_to_matrix(axis_angle)

    def matrix_to_axis_angle(matrix: torch.Tensor) -> torch.Tensor:
        return rotations.matrix_to_axis_angle(matrix)

    def rotation_6d_to_matrix(d6: torch.Tensor) -> torch.Tensor:
        # pytorch3d's definition (Zhou et al. 2019, rows): Gram-Schmidt of the two 3-vectors
        a1, a2 = d6[..., :3], d6[..., 3:]
        b1 = F.normalize(a1, dim=-1)
        b2 = F.normalize(a2 - (b1 * a2).sum(-1, keepdim=True) * b1, dim=-1)
        b3 = torch.cross(b1, b2, dim=-1)
        return torch.stack((b1, b2, b3), dim=-2)

    def matrix_to_rotation_6d(matrix: torch.Tensor) -> torch.Tensor:
        return matrix[..., :2, :].clone().reshape(matrix.shape[:-2] + (6,))

    KNN = namedtuple("KNN", ["dists", "idx", "knn"])

    def knn_points(p1, p2, lengths1=None, lengths2=None, K=1, return_nn=False, **_):
        """Exact K nearest neighbours (squared distances), padded points ignored/zeroed."""
        n, p1n, _ = p1.shape
        p2n = p2.shape[1]
        d = torch.cdist(p1, p2, compute_mode="donot_use_mm_for_euclid_dist") ** 2
        if lengths2 is not None:
            pad2 = torch.arange(p2n, device=p2.device)[None, :] >= lengths2.view(-1, 1)
            d = d.masked_fill(pad2[:, None, :], float("inf"))
        dists, idx = d.topk(K, dim=2, largest=False)
        if lengths1 is not None:
            pad1 = torch.arange(p1n, device=p1.device)[None, :] >= lengths1.view(-1, 1)
            dists = dists.masked_fill(pad1[..., None], 0.0)
            idx = idx.masked_fill(pad1[..., None], 0)
        knn = None
        if return_nn:
            knn = torch.gather(p2[:, None].expand(n, p1n, p2n, 3), 2, idx[..., None].expand(n, p1n, K, 3))
        return KNN(dists, idx, knn)

    funcs = dict(
        axis_angle_to_matrix=axis_angle_to_matrix,
        matrix_to_axis_angle=matrix_to_axis_angle,
        rotation_6d_to_matrix=rotation_6d_to_matrix,
        matrix_to_rotation_6d=matrix_to_rotation_6d,
    )
    rc = _module("pytorch3d.transforms.rotation_conversions", "stub (arctic_crosscheck)", **funcs)
    tr = _module("pytorch3d.transforms", "stub (arctic_crosscheck)", rotation_conversions=rc, **funcs)
    ops = _module("pytorch3d.ops", "stub (arctic_crosscheck)", knn_points=knn_points)
    root = _module("pytorch3d", "stub (arctic_crosscheck)", transforms=tr, ops=ops)
    return {
        "pytorch3d": root,
        "pytorch3d.transforms": tr,
        "pytorch3d.transforms.rotation_conversions": rc,
        "pytorch3d.ops": ops,
    }


def make_torchvision_stub() -> dict[str, types.ModuleType]:
    import torch

    class Normalize:
        """torchvision's ``Normalize`` arithmetic: ``(x - mean) / std`` per channel."""

        def __init__(self, mean: Sequence[float], std: Sequence[float], inplace: bool = False) -> None:
            self.mean, self.std = list(mean), list(std)

        def __call__(self, tensor: torch.Tensor) -> torch.Tensor:
            mean = torch.as_tensor(self.mean, dtype=tensor.dtype, device=tensor.device).view(-1, 1, 1)
            std = torch.as_tensor(self.std, dtype=tensor.dtype, device=tensor.device).view(-1, 1, 1)
            return tensor.clone().sub_(mean).div_(std)

    tf = _module("torchvision.transforms", "stub (arctic_crosscheck)", Normalize=Normalize)
    return {
        "torchvision": _module("torchvision", "stub (arctic_crosscheck)", transforms=tf),
        "torchvision.transforms": tf,
    }


class _ChumpyFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Creates stub modules for ``chumpy`` and any ``chumpy.*`` a pickle names."""

    def find_spec(self, fullname, path=None, target=None):  # noqa: D401 - importlib API
        if fullname == "chumpy" or fullname.startswith("chumpy."):
            return importlib.machinery.ModuleSpec(fullname, self, is_package=True)
        return None

    def create_module(self, spec):
        return _chumpy_module(spec.name)

    def exec_module(self, module):
        return None


def _chumpy_module(name: str) -> types.ModuleType:
    from hogsa_loader.io.mano_pickle import ChumpyStub

    classes: dict[str, type] = {}

    def _array(self) -> np.ndarray:
        cached = self.__dict__.get("_array_cache")
        if cached is None:
            cached = np.asarray(self.to_array(where="<MANO pickle>"))
            self.__dict__["_array_cache"] = cached
        return cached

    def make(cls_name: str) -> type:
        if cls_name not in classes:
            classes[cls_name] = type(
                cls_name,
                (ChumpyStub,),
                {
                    "chumpy_name": f"{name}.{cls_name}",
                    "__array__": lambda self, dtype=None, copy=None: (
                        _array(self) if dtype is None else _array(self).astype(dtype)
                    ),
                    "__getitem__": lambda self, key: _array(self)[key],
                    "__len__": lambda self: len(_array(self)),
                    "shape": property(lambda self: _array(self).shape),
                    "ndim": property(lambda self: _array(self).ndim),
                    "dtype": property(lambda self: _array(self).dtype),
                    "r": property(_array),
                },
            )
        return classes[cls_name]

    mod = types.ModuleType(name, "stub (arctic_crosscheck): pickled chumpy objects as arrays")
    mod.__path__ = []  # a package, so chumpy.ch etc. resolve through the finder
    mod.__dict__["__hogsa_stub__"] = True

    def __getattr__(attr: str) -> Any:
        if attr.startswith("__"):
            raise AttributeError(attr)
        return make(attr)

    mod.__getattr__ = __getattr__  # type: ignore[attr-defined]
    return mod


def make_pyrender_stub() -> dict[str, types.ModuleType]:
    class _Unavailable:
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            pass

        def __getattr__(self, name: str) -> Any:
            raise RuntimeError("pyrender is stubbed by arctic_crosscheck: nothing can be rendered")

    mod = _module("pyrender", "stub (arctic_crosscheck)")

    def __getattr__(attr: str) -> Any:
        if attr.startswith("__"):
            raise AttributeError(attr)
        return _Unavailable

    mod.__getattr__ = __getattr__  # type: ignore[attr-defined]
    return {"pyrender": mod}


def make_comet_stub() -> dict[str, types.ModuleType]:
    class _NoExperiment:
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            raise RuntimeError("comet_ml is stubbed by arctic_crosscheck: no experiment can be created")

    return {
        "comet_ml": _module(
            "comet_ml", "stub (arctic_crosscheck)", Experiment=_NoExperiment, ExistingExperiment=_NoExperiment
        )
    }


STUB_FACTORIES: dict[str, Callable[[], dict[str, types.ModuleType]]] = {
    "pytorch3d": make_pytorch3d_stub,
    "torchvision": make_torchvision_stub,
    "chumpy": lambda: {},  # installed as a meta-path finder (any chumpy.* submodule)
    "pyrender": make_pyrender_stub,
    "comet_ml": make_comet_stub,
}


# ----------------------------------------------------------------------------------------
# Files ARCTIC's code opens
# ----------------------------------------------------------------------------------------


def arctic_objects(arctic_src: Optional[Path]) -> list[str]:
    """``OBJECTS`` of ARCTIC's ``common/object_tensors.py`` (read, not imported)."""
    if arctic_src is not None:
        path = Path(arctic_src) / "common" / "object_tensors.py"
        if path.is_file():
            for node in ast.parse(path.read_text()).body:
                if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "OBJECTS" for t in node.targets):
                    return [str(v) for v in ast.literal_eval(node.value)]
    return list(ARCTIC_OBJECTS_FALLBACK)


def arctic_loss_keys(arctic_src: Path) -> list[str]:
    """Keys of the dict ``compute_loss`` returns in ``src/callbacks/loss/loss_arctic_sf.py``."""
    path = Path(arctic_src) / "src" / "callbacks" / "loss" / "loss_arctic_sf.py"
    keys: list[str] = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Dict) and node.keys and all(isinstance(k, ast.Constant) for k in node.keys):
            names = [k.value for k in node.keys]
            if all(isinstance(n, str) and n.startswith("loss/") for n in names):
                keys = names
    return keys


def required_files(
    data_root: Path,
    objects: Sequence[str],
    splits: Sequence[str] = SPLITS,
    image_names: Optional[Mapping[str, Sequence[str]]] = None,
    require_smplx: bool = False,
) -> list[dict[str, Any]]:
    """Every file ARCTIC's code opens for the checks, with whether the world has it.

    Args:
        data_root: the folder that plays ARCTIC's ``./data``.
        objects: ARCTIC's object names (all are loaded by ``ObjectTensors``).
        splits: the ``<setup>_<split>`` files the dataset check reads.
        image_names: per split, the image names of the split file (``./data/arctic_data/
            data/images/...``); the cropped images they map to are counted (soft: ARCTIC
            substitutes a zero image for a missing one).
        require_smplx: count the SMPL-X models and subject templates as required (else
            they are soft: the processing check replaces the SMPL-X layer by a NaN stand-in).

    Returns:
        Entries ``{"path" (relative to data_root), "needed_by" (checks), "why", "exists",
        "soft"}``; an entry for a missing ``misc.json`` field has ``"field"`` set.
    """
    root = Path(data_root)
    arctic = f"{ARCTIC_SUBDIR}"
    out: list[dict[str, Any]] = []

    def add(
        rel: str, needed_by: Sequence[str], why: str, soft: bool = False, exists: Optional[bool] = None, **extra: Any
    ) -> None:
        out.append(
            {
                "path": rel,
                "needed_by": list(needed_by),
                "why": why,
                "exists": (root / rel).exists() if exists is None else bool(exists),
                "soft": soft,
                **extra,
            }
        )

    add(f"{arctic}/meta/misc.json", CHECKS, "cameras, image sizes, ioi_offset, gender (dataset, processing)")
    add(f"{arctic}/meta/object_meta.json", CHECKS, "object diameters (common/object_tensors.py)")
    for obj in objects:
        for fname in OBJECT_TEMPLATE_FILES:
            add(
                f"{arctic}/meta/object_vtemplates/{obj}/{fname}",
                CHECKS,
                "ObjectTensors loads all of ARCTIC's OBJECTS (common/object_tensors.py)",
                group=f"{arctic}/meta/object_vtemplates/<object>/<file>",
                member=f"{obj}/{fname}",
            )
    for name in sorted(set(splits) | {"p1_train"}):
        needed = (["dataset"] if name in splits else []) + (["train", "field"] if name == "p1_train" else [])
        add(
            f"{arctic}/splits/{name}.npy",
            needed,
            "ARCTIC's ArcticDataset reads the world's split; the train check's real samples come from p1_train",
        )
    add(f"{arctic}/meta/downsamplers.npy", ("train",), "object_sampler (src/models/generic/wrapper.py __init__)")
    add(
        f"{arctic}/meta/mano_decimator_195.npy",
        ("train", "field"),
        "MANODecimator (common/body_models.py), every forward; InterField-SF's hand templates",
    )
    for side in ("RIGHT", "LEFT"):
        add(f"body_models/mano/MANO_{side}.pkl", ("train", "processing", "field"), "smplx MANO (common/body_models.py)")

    misc: dict[str, Any] = {}
    misc_path = root / arctic / "meta" / "misc.json"
    if misc_path.is_file():
        try:
            misc = json.loads(misc_path.read_text())
        except (OSError, ValueError):
            misc = {}
    for sid in sorted(misc):
        for key in MISC_FIELDS:
            if key not in misc[sid]:
                add(
                    f"{arctic}/meta/misc.json [{sid}].{key}",
                    CHECKS,
                    "field read by ARCTIC's code",
                    exists=False,
                    field=key,
                )

    raw = root / arctic / "raw_seqs"
    subjects = set()
    for mano_p in sorted(raw.glob("*/*.mano.npy")) if raw.is_dir() else []:
        sid, seq = mano_p.parent.name, mano_p.name[: -len(".mano.npy")]
        subjects.add(sid)
        for kind in ("object", "egocam.dist", "smplx"):
            add(
                f"{arctic}/raw_seqs/{sid}/{seq}.{kind}.npy",
                ("processing",),
                "src/arctic/preprocess_dataset.py construct_loader",
                group=f"{arctic}/raw_seqs/<sid>/<seq>.{kind}.npy",
                member=f"{sid}/{seq}",
            )
    if not subjects and raw.is_dir() is False:
        add(f"{arctic}/raw_seqs", ("processing",), "raw sequences (scripts_data/process_seqs.py)")
    genders = {"neutral"} | {str(misc[s].get("gender")) for s in subjects if s in misc and "gender" in misc[s]}
    standin = "; missing: the SMPL-X layer is replaced by a NaN stand-in (see --require-smplx)"
    for gender in sorted(genders):
        add(
            f"body_models/smplx/SMPLX_{gender.upper()}.npz",
            ("processing",),
            "SMPL-X layer (common/body_models.py construct_layers / build_subject_smplx)" + standin,
            soft=not require_smplx,
        )
    for sid in sorted(subjects):
        add(
            f"{arctic}/meta/subject_vtemplates/{sid}.obj",
            ("processing",),
            "build_subject_smplx v_template" + standin,
            soft=not require_smplx,
            group=f"{arctic}/meta/subject_vtemplates/<sid>.obj",
            member=sid,
        )
    for protocol in sorted({s.split("_")[0] for s in splits}):
        add(f"{arctic}/splits_json/protocol_{protocol}.json", ("processing",), "src/arctic/split.py get_selected_seqs")

    for split, names in (image_names or {}).items():
        missing = [n for n in names if not (root / cropped_image_rel(n)).is_file()]
        if missing:
            add(
                f"{cropped_image_rel(missing[0])} (+{len(missing) - 1} more of {len(names)} in {split})",
                ("dataset", "train"),
                "cropped image of a split entry (ARCTIC reads a zero image instead)",
                soft=True,
                exists=False,
                count=len(missing),
            )
    return out


def cropped_image_rel(imgname: str) -> str:
    """The file (relative to ``./data``) ARCTIC reads for a split image name with ``speedup``."""
    name = imgname.replace("/images/", "/cropped_images/")
    name = name.replace("/arctic_data/", "/data/arctic_data/data/").replace("/data/data/", "/data/")
    for prefix in ("./data/", "data/"):
        if name.startswith(prefix):
            return name[len(prefix) :]
    return name


def blocking_missing(entries: Sequence[Mapping[str, Any]], check: str) -> list[str]:
    """Paths that are missing, not soft, and needed by ``check``."""
    return [e["path"] for e in entries if not e["exists"] and not e["soft"] and check in e["needed_by"]]


# ----------------------------------------------------------------------------------------
# Comparisons (pure)
# ----------------------------------------------------------------------------------------


def describe(x: Any) -> dict[str, Any]:
    """Python type, dtype and shape of a sample value."""
    try:
        import torch

        if isinstance(x, torch.Tensor):
            return {"type": "Tensor", "dtype": str(x.dtype).replace("torch.", ""), "shape": list(x.shape)}
    except ImportError:  # pragma: no cover - torch is a dependency
        pass
    if isinstance(x, np.ndarray):
        return {"type": "ndarray", "dtype": str(x.dtype), "shape": list(x.shape)}
    if isinstance(x, np.generic):
        return {"type": type(x).__name__, "dtype": str(x.dtype), "shape": []}
    return {"type": type(x).__name__, "dtype": None, "shape": None}


def _as_float_array(x: Any) -> Optional[np.ndarray]:
    if isinstance(x, (str, bytes)) or x is None:
        return None
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    try:
        arr = np.asarray(x)
    except Exception:  # pragma: no cover - exotic values
        return None
    if arr.dtype.kind not in "biuf":
        return None
    return arr.astype(np.float64)


def compare_values(arctic: Any, ours: Any) -> dict[str, Any]:
    """One field: types and, for numbers, the absolute differences (NaN-aware).

    Returns ``{"arctic", "ours" (describe()), "same_type", "numeric", "max_abs",
    "mean_abs", "nan_match", "equal"}``: ``numeric`` when both are numbers (arrays, tensors
    or scalars); ``max_abs``/``mean_abs`` over the entries finite on both sides, None when
    not numeric or the shapes differ; ``equal`` is exact equality (strings and other
    values by ``==``; numbers: max_abs 0 with NaNs at the same places).
    """
    da, do = describe(arctic), describe(ours)
    out: dict[str, Any] = {
        "arctic": da,
        "ours": do,
        "same_type": da == do,
        "numeric": False,
        "max_abs": None,
        "mean_abs": None,
        "nan_match": True,
        "equal": False,
    }
    a, b = _as_float_array(arctic), _as_float_array(ours)
    if a is None or b is None:
        try:
            out["equal"] = bool(arctic == ours)
        except Exception:  # e.g. an array against a string
            out["equal"] = False
        return out
    out["numeric"] = True
    if a.shape != b.shape:
        return out
    nan_a, nan_b = np.isnan(a), np.isnan(b)
    out["nan_match"] = bool(np.array_equal(nan_a, nan_b))
    ok = ~(nan_a | nan_b)
    diff = np.abs(a[ok] - b[ok])
    out["max_abs"] = float(diff.max()) if diff.size else 0.0
    out["mean_abs"] = float(diff.mean()) if diff.size else 0.0
    out["num_diff"], out["size"] = int((diff > 0).sum()), int(a.size)
    out["equal"] = out["max_abs"] == 0.0 and out["nan_match"]
    return out


def compare_samples(
    arctic: Sequence[Mapping[str, Any]],
    ours: Sequence[Mapping[str, Any]],
    groups: Sequence[str] = ("inputs", "targets", "meta_info"),
) -> dict[str, Any]:
    """Compare one ``(inputs, targets, meta_info)`` item of each dataset.

    Returns ``{"keys": {group: {"arctic_only", "ours_only", "same_order"}}, "fields":
    {"group.key": compare_values(...)}}`` (fields present in both only).
    """
    keys: dict[str, Any] = {}
    fields: dict[str, Any] = {}
    for group, a, o in zip(groups, arctic, ours):
        ka, ko = list(a), list(o)
        keys[group] = {
            "arctic_only": [k for k in ka if k not in o],
            "ours_only": [k for k in ko if k not in a],
            "same_order": ka == ko,
        }
        for k in ka:
            if k in o:
                fields[f"{group}.{k}"] = compare_values(a[k], o[k])
    return {"keys": keys, "fields": fields}


#: Share of 2D label coordinates allowed to differ by one patch pixel when ARCTIC computes
#: them in another pixel frame than ours (world crops rescaled to ARCTIC's 1000 px).
FLIP_FRACTION = 0.005


def dataset_tolerance(name: str, img_tol: float = DEFAULT_IMG_TOL, flip_px: Optional[float] = None) -> dict[str, Any]:
    """Tolerance of one dataset field (``group.key``).

    ``flip_px`` (normalised size of one patch pixel, ``2 / img_res``) relaxes the 2D labels
    when ARCTIC computes them in another pixel frame than ours: both truncate the patch
    position to an integer the HMR way, so a label whose exact position is an integer can
    land one pixel apart after float round-off of the rescale; at most
    :data:`FLIP_FRACTION` of the coordinates may.
    """
    if name == "inputs.img":
        return {"max_abs": img_tol, "mean_abs": img_tol / 10, "rule": "image noise"}
    if "2d.norm" in name:
        if flip_px is not None:
            return {
                "max_abs": flip_px * (1 + 1e-6),
                "max_fraction": FLIP_FRACTION,
                "rule": "exact but one-pixel truncation flips (labels computed in a rescaled frame)",
            }
        return {"max_abs": 0.0, "rule": "exact (2D label)"}
    return {"max_abs": NUMBER_TOL, "rule": "float round-off"}


def aggregate_fields(
    per_item: Sequence[Mapping[str, Any]], img_tol: float = DEFAULT_IMG_TOL, flip_px: Optional[float] = None
) -> dict[str, Any]:
    """Fold the field comparisons of several items and judge each field by its tolerance.

    A field passes when its type/dtype/shape agree on every item and: numbers — every item
    comparable (same shape), NaNs at the same places, max (and for the image mean) absolute
    difference within :func:`dataset_tolerance`; other values — equal on every item.
    """
    out: dict[str, Any] = {}
    for item in per_item:
        for name, c in item["fields"].items():
            agg = out.setdefault(
                name,
                {
                    "arctic": c["arctic"],
                    "ours": c["ours"],
                    "same_type": True,
                    "numeric": True,
                    "max_abs": 0.0,
                    "mean_abs": 0.0,
                    "nan_match": True,
                    "equal": True,
                    "items": 0,
                    "num_diff": 0,
                    "size": 0,
                },
            )
            agg["items"] += 1
            agg["num_diff"] += int(c.get("num_diff", 0))
            agg["size"] += int(c.get("size", 0))
            agg["same_type"] &= bool(c["same_type"])
            agg["numeric"] &= bool(c["numeric"])
            agg["nan_match"] &= bool(c["nan_match"])
            agg["equal"] &= bool(c["equal"])
            if c["max_abs"] is None or agg["max_abs"] is None:
                agg["max_abs"] = agg["mean_abs"] = None
            else:
                agg["max_abs"] = max(agg["max_abs"], c["max_abs"])
                agg["mean_abs"] = max(agg["mean_abs"], c["mean_abs"])
    for name, agg in out.items():
        tol = dataset_tolerance(name, img_tol, flip_px)
        agg["tolerance"] = tol
        if not agg["numeric"]:
            agg["max_abs"] = agg["mean_abs"] = None
            ok = agg["equal"]
        else:
            ok = (
                agg["max_abs"] is not None
                and agg["nan_match"]
                and agg["max_abs"] <= tol["max_abs"]
                and agg["mean_abs"] <= tol.get("mean_abs", math.inf)
                and agg["num_diff"] <= tol.get("max_fraction", 1.0) * max(agg["size"], 1)
            )
        agg["ok"] = bool(ok and agg["same_type"])
    return out


def split_key_kind(group: str, key: str) -> str:
    """Tolerance class of a processed-split key (see :data:`SPLIT_TOL`)."""
    if group == "2d":
        return "2d"
    if group == "bbox":
        return "bbox"
    if key.endswith("valid"):
        return "flag"
    if "rot" in key and group in ("cam_coord", "params"):
        return "rot"
    if group == "params":
        return "param"
    return "point"


def _geodesic(a: np.ndarray, b: np.ndarray) -> float:
    """Largest angle (rad) between the rotations of two (..., 3) axis-angle arrays."""
    import cv2

    a2, b2 = a.reshape(-1, 3), b.reshape(-1, 3)
    worst = 0.0
    for u, v in zip(a2, b2):
        ra, _ = cv2.Rodrigues(u.astype(np.float64))
        rb, _ = cv2.Rodrigues(v.astype(np.float64))
        c = (np.trace(ra.T @ rb) - 1.0) / 2.0
        worst = max(worst, float(np.arccos(np.clip(c, -1.0, 1.0))))
    return worst


#: Keys ARCTIC writes that the project's worlds omit on purpose (no SMPL-X body).
def expected_arctic_only(group: str, key: str) -> bool:
    return "smplx" in key


def compare_split_data(arctic: Mapping[str, Any], ours: Mapping[str, Any]) -> dict[str, Any]:
    """Compare two processed split dicts (``{"data_dict", "imgnames"}``).

    Returns ``{"imgnames_equal", "num_images": [arctic, ours], "sequences_equal",
    "sequences": [...], "keys": {"group/key": {...}}}`` where each key entry has shapes,
    dtypes, ``max_abs`` (over sequences; the geodesic angle for rotations), ``kind``,
    ``tolerance``, ``ok``; keys on one side only have ``"only": "arctic"|"ours"`` and
    ``"expected"`` (the SMPL-X keys ARCTIC writes and our worlds do not).
    """
    ia, io = [str(n) for n in arctic["imgnames"]], [str(n) for n in ours["imgnames"]]
    da, do = arctic["data_dict"], ours["data_dict"]
    out: dict[str, Any] = {
        "imgnames_equal": ia == io,
        "num_images": [len(ia), len(io)],
        "sequences_equal": sorted(da) == sorted(do),
        "sequences": sorted(set(da) | set(do)),
        "keys": {},
    }
    if ia != io:
        sa, so = set(ia), set(io)
        out["imgnames_arctic_only"] = sorted(sa - so)[:5]
        out["imgnames_ours_only"] = sorted(so - sa)[:5]
        out["imgnames_same_set"] = sa == so
    for seq in sorted(set(da) & set(do)):
        for group in sorted(set(da[seq]) | set(do[seq])):
            ga, go = da[seq].get(group), do[seq].get(group)
            if not isinstance(ga, Mapping) and not isinstance(go, Mapping):
                items = [("", ga, go)]
            else:
                ga, go = ga or {}, go or {}
                items = [(k, ga.get(k), go.get(k)) for k in sorted(set(ga) | set(go))]
            for key, va, vo in items:
                name = f"{group}/{key}" if key else group
                kind = split_key_kind(group, key)
                e = out["keys"].setdefault(
                    name,
                    {
                        "kind": kind,
                        "tolerance": SPLIT_TOL[kind],
                        "max_abs": 0.0,
                        "arctic": None,
                        "ours": None,
                        "ok": True,
                    },
                )
                if va is None or vo is None:
                    e["only"] = "arctic" if vo is None else "ours"
                    e["expected"] = e["only"] == "arctic" and expected_arctic_only(group, key)
                    e["max_abs"] = None
                    e["ok"] = bool(e["expected"])
                    e["arctic" if vo is None else "ours"] = describe(np.asarray(va if vo is None else vo))
                    continue
                a, b = np.asarray(va), np.asarray(vo)
                e["arctic"], e["ours"] = describe(a), describe(b)
                if a.shape != b.shape:
                    e["ok"], e["max_abs"] = False, None
                    e.setdefault("problems", []).append(f"{seq}: shape {list(a.shape)} vs {list(b.shape)}")
                    continue
                if e["max_abs"] is None:
                    continue
                if kind == "rot":
                    d = _geodesic(a.astype(np.float64), b.astype(np.float64)) if a.size else 0.0
                else:
                    fa, fb = a.astype(np.float64), b.astype(np.float64)
                    if not np.array_equal(np.isnan(fa), np.isnan(fb)):
                        e.setdefault("problems", []).append(f"{seq}: NaNs differ")
                        e["ok"] = False
                    fin = np.isfinite(fa) & np.isfinite(fb)
                    d = float(np.abs(fa[fin] - fb[fin]).max()) if fin.any() else 0.0
                if d > e["max_abs"]:
                    e["max_abs"], e["worst_sequence"] = d, seq
                if d > e["tolerance"]:
                    e["ok"] = False
    return out


# ----------------------------------------------------------------------------------------
# ARCTIC session: work folder, stubs, patches
# ----------------------------------------------------------------------------------------


def _mano21_class(base: type) -> type:
    """smplx ``MANO`` that returns ARCTIC's 21 joints (16 + the 5 fingertip vertices)."""

    class MANO21(base):  # type: ignore[misc, valid-type]
        __doc__ = (
            "smplx MANO + vertex_joint_selector (arctic_crosscheck): the joints ARCTIC gets after "
            "uncommenting 'joints = self.vertex_joint_selector(vertices, joints)' in smplx"
        )

        def forward(self, *args: Any, **kwargs: Any) -> Any:
            out = super().forward(*args, **kwargs)
            if out.joints is not None and out.joints.shape[1] == 16:
                # transl (if any) is already in both: the tips move with it, as in ARCTIC's order
                out.joints = self.vertex_joint_selector(out.vertices, out.joints)
            return out

    MANO21.__name__ = MANO21.__qualname__ = "MANO"
    return MANO21


class _NoRenderer:
    """Stands in for ``common.rend_utils.Renderer`` (visualisation only)."""

    def __init__(self, img_res: int = 224, **_: Any) -> None:
        self.img_res = img_res

    def __getattr__(self, name: str) -> Any:
        raise RuntimeError("ARCTIC's Renderer is disabled by arctic_crosscheck")


class _RandomFromGenerator:
    """The ``np.random`` functions ARCTIC's ``augm_params`` calls, drawn from a Generator."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.draws = 0

    def uniform(self, low: float = 0.0, high: float = 1.0, size: Any = None) -> Any:
        self.draws += 1
        return self.rng.uniform(low, high, size)

    def randn(self, *shape: int) -> Any:
        self.draws += 1
        return self.rng.standard_normal(shape) if shape else self.rng.standard_normal()

    def __getattr__(self, name: str) -> Any:
        raise AttributeError(f"ARCTIC drew np.random.{name}, which arctic_crosscheck does not route")


class _NumpyRouted:
    """``numpy`` with ``random`` replaced (assigned to ``common.data_utils.np``)."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.random = _RandomFromGenerator(rng)

    def __getattr__(self, name: str) -> Any:
        return getattr(np, name)


class _NullBar:
    def set_description(self, *_: Any, **__: Any) -> None:
        pass


@dataclass(frozen=True)
class ImageGeometry:
    """Sizes of the world's image files against the sizes ARCTIC's code assumes."""

    cropped_size: int
    ego_scale: float
    ego_full_sizes: Mapping[str, tuple[int, int]]
    arctic_cropped: int = ARCTIC_CROPPED_SIZE
    arctic_ego_scale: float = 0.3

    @property
    def arctic_sized(self) -> bool:
        return self.cropped_size == self.arctic_cropped and self.ego_scale == self.arctic_ego_scale

    @staticmethod
    def is_ego(imgname: str) -> bool:
        return "/0/" in imgname  # ARCTIC's own test (src/datasets/arctic_dataset.py)

    def factor(self, imgname: str) -> float:
        """File pixels per pixel of the frame ARCTIC assumes for this image."""
        if self.is_ego(imgname):
            return self.ego_scale / self.arctic_ego_scale
        return self.cropped_size / self.arctic_cropped

    def arctic_size(self, imgname: str) -> tuple[int, int]:
        """(width, height) ARCTIC assumes for the file of this image."""
        if self.is_ego(imgname):
            w, h = self.ego_full_sizes[imgname.split("/")[-4]]
            return int(w * self.arctic_ego_scale), int(h * self.arctic_ego_scale)
        return self.arctic_cropped, self.arctic_cropped


class ArcticSession:
    """ARCTIC's code importable from a work folder that mirrors its repository root."""

    def __init__(
        self,
        arctic_src: Path,
        data_root: Path,
        workdir: Path,
        notes: Notes,
        stubs: Sequence[str],
        resnet_weights: Optional[Path] = None,
    ) -> None:
        self.arctic_src = Path(arctic_src).resolve()
        self.data_root = Path(data_root).resolve()
        self.workdir = Path(workdir)
        self.notes = notes
        self.stubs = list(stubs)
        self.resnet_weights = resnet_weights
        self._old_cwd: Optional[str] = None
        self._finder: Optional[_ChumpyFinder] = None
        self._patched: dict[str, bool] = {}

    # ------------------------------------------------------------------ enter / leave
    def __enter__(self) -> "ArcticSession":
        self.workdir.mkdir(parents=True, exist_ok=True)
        links = {"data": self.data_root, "src": self.arctic_src / "src", "common": self.arctic_src / "common"}
        for name, target in links.items():
            link = self.workdir / name
            if link.is_symlink() or link.exists():
                link.unlink()
            link.symlink_to(target, target_is_directory=True)
        for mod in [m for m in sys.modules if m in ("src", "common") or m.startswith(("src.", "common."))]:
            del sys.modules[mod]  # another 'src'/'common' package must not shadow ARCTIC's
        self._old_cwd = os.getcwd()
        os.chdir(self.workdir)
        sys.path.insert(0, str(self.workdir))
        self._stub_modules: list[str] = []
        for name in self.stubs:
            if name == "chumpy":
                self._finder = _ChumpyFinder()
                sys.meta_path.insert(0, self._finder)
            else:
                mods = STUB_FACTORIES[name]()
                sys.modules.update(mods)
                self._stub_modules += list(mods)
            self.notes.stub(name)
        return self

    def __exit__(self, *exc: Any) -> None:
        if self._old_cwd is not None:
            os.chdir(self._old_cwd)
        with contextlib.suppress(ValueError):
            sys.path.remove(str(self.workdir))
        if self._finder is not None:
            with contextlib.suppress(ValueError):
                sys.meta_path.remove(self._finder)
        for mod in [m for m in sys.modules if m == "chumpy" or m.startswith("chumpy.")] if self._finder else []:
            del sys.modules[mod]
        for mod in getattr(self, "_stub_modules", []):
            sys.modules.pop(mod, None)

    # ------------------------------------------------------------------ imports
    def module(self, name: str) -> types.ModuleType:
        """Import one of ARCTIC's modules (``src.*`` / ``common.*``) with the patches applied."""
        mod = importlib.import_module(name)
        where = Path(getattr(mod, "__file__", "") or "").resolve()
        if self.arctic_src not in where.parents:
            raise RuntimeError(f"{name} was imported from {where}, not from the ARCTIC checkout")
        self._apply_patches()
        return mod

    def _apply_patches(self) -> None:
        bm = sys.modules.get("common.body_models")
        if bm is not None and not self._patched.get("mano"):
            bm.MANO = _mano21_class(bm.MANO)
            self._patched["mano"] = True
            self.notes.patch(
                "smplx MANO returns 21 joints",
                "common.body_models.MANO (used by build_mano_aa) is a subclass whose forward appends "
                "smplx's own vertex_joint_selector (the 5 fingertip vertices) when smplx returns 16 joints",
                "ARCTIC's docs/setup.md asks to uncomment 'joints = self.vertex_joint_selector(vertices, "
                "joints)' in the installed smplx/body_models.py; the installed package is not modified",
            )
        res = sys.modules.get("src.nets.backbone.resnet")
        if res is not None and not self._patched.get("resnet"):
            weights = self.resnet_weights

            def load_state_dict_from_url(url: str, progress: bool = True, **_: Any) -> dict:
                if weights is None:
                    return {}
                import torch

                return torch.load(weights, map_location="cpu", weights_only=True)

            res.load_state_dict_from_url = load_state_dict_from_url
            self._patched["resnet"] = True
            self.notes.patch(
                "ResNet ImageNet weights",
                "src.nets.backbone.resnet.load_state_dict_from_url returns "
                + (f"the state dict of {weights}" if weights else "{} (random initialisation)"),
                "ArcticSF builds resnet50(pretrained=True), which downloads weights; nothing is downloaded here",
            )
        wrapper = sys.modules.get("src.models.generic.wrapper")
        if wrapper is not None and not self._patched.get("renderer"):
            wrapper.Renderer = _NoRenderer
            self._patched["renderer"] = True
            self.notes.patch(
                "visualisation Renderer",
                "src.models.generic.wrapper.Renderer is a no-op class",
                "GenericWrapper.__init__ opens a pyrender OffscreenRenderer (needs EGL); used only to draw "
                "visualisations, never in forward/loss",
            )

    @contextlib.contextmanager
    def cuda_as_cpu(self) -> Iterator[None]:
        """``Tensor.cuda()`` returns the tensor itself (no CUDA here)."""
        import torch

        if torch.cuda.is_available():
            yield
            return
        orig = torch.Tensor.cuda
        torch.Tensor.cuda = lambda self, *a, **k: self  # type: ignore[assignment]
        self.notes.patch(
            "Tensor.cuda() on a machine without CUDA",
            "torch.Tensor.cuda returns the tensor unchanged while ARCTIC's code runs",
            "src/arctic/processing.py (transform_mano_rot_cam) and src/callbacks/process/process_generic.py "
            "call .cuda() unconditionally",
        )
        try:
            yield
        finally:
            torch.Tensor.cuda = orig  # type: ignore[assignment]

    @contextlib.contextmanager
    def routed_random(self, rng: np.random.Generator) -> Iterator[_RandomFromGenerator]:
        """ARCTIC's ``common.data_utils`` draws its augmentation from ``rng``."""
        du = self.module("common.data_utils")
        orig = du.np
        routed = _NumpyRouted(rng)
        du.np = routed
        try:
            yield routed.random
        finally:
            du.np = orig

    @contextlib.contextmanager
    def world_sized_images(self, mode: str, geometry: "ImageGeometry") -> Iterator[dict[str, Any]]:
        """Let ARCTIC's dataset read a world whose image files are not the sizes it assumes.

        ARCTIC's ``src/datasets/dataset_utils.py`` maps allocentric labels and the crop box
        into a 1000-px crop, and its parser scales the egocentric frame by
        ``ego_image_scale`` = 0.3. For a world with other image sizes (``meta/
        hogsa_world.json``), ``mode``:

        * ``"map"``: ARCTIC's ``rgb_processing`` (blur, warp, colour noise) runs on the file as
          it is, with ARCTIC's crop box (centre, side) scaled from its assumed frame into the
          file's pixels -- the image pipeline compared pixel for pixel;
        * ``"upsample"``: the file is upsampled (bicubic) to ARCTIC's sizes before ARCTIC's
          code sees it -- end to end, but with resampling differences;
        * ``"raw"``: nothing adapted (ARCTIC crops the wrong region of a smaller file).
        """
        import cv2

        ad = self.module("src.datasets.arctic_dataset")
        du = self.module("common.data_utils")
        orig_read, orig_rgb = ad.read_img, du.rgb_processing
        stats: dict[str, Any] = {"mode": mode, "images": 0, "sizes": {}}
        current: dict[str, Any] = {}

        def read_img(img_fn: str, dummy_shape: Any) -> Any:
            img, ok = orig_read(img_fn, dummy_shape)
            current.update(name=img_fn, ok=ok)
            if ok and mode == "upsample":
                w, h = geometry.arctic_size(img_fn)
                if (img.shape[1], img.shape[0]) != (w, h):
                    stats["sizes"][f"{img.shape[1]}x{img.shape[0]}"] = f"{w}x{h}"
                    img = cv2.resize(img, (w, h), interpolation=cv2.INTER_CUBIC)
                    stats["images"] += 1
            return img, ok

        def rgb_processing(
            is_train: Any, rgb_img: Any, center: Any, bbox_dim: Any, augm_dict: Any, img_res: Any
        ) -> Any:
            if mode == "map" and current.get("ok"):
                k = geometry.factor(current["name"])
                center, bbox_dim = [center[0] * k, center[1] * k], bbox_dim * k
                stats["images"] += 1
                stats["sizes"][f"{rgb_img.shape[1]}x{rgb_img.shape[0]}"] = f"box x{k:g}"
            return orig_rgb(is_train, rgb_img, center, bbox_dim, augm_dict, img_res)

        ad.read_img, du.rgb_processing = read_img, rgb_processing
        ego_part = (
            ""
            if geometry.ego_scale == geometry.arctic_ego_scale
            else (f", egocentric x{geometry.ego_scale:g}/{geometry.arctic_ego_scale:g}")
        )
        how = {
            "map": "common.data_utils.rgb_processing gets ARCTIC's crop centre and side scaled into the file's "
            f"pixels (allocentric x{geometry.cropped_size}/{geometry.arctic_cropped}{ego_part}); labels "
            "untouched",
            "upsample": "src.datasets.arctic_dataset.read_img upsamples the files (bicubic) to "
            f"{geometry.arctic_cropped}x{geometry.arctic_cropped} (allocentric)"
            + ("" if not ego_part else f" and x{geometry.arctic_ego_scale:g} of the frame (egocentric)"),
        }
        if mode in how:
            self.notes.patch(
                f"image sizes ARCTIC assumes ({mode})",
                how[mode],
                f"ARCTIC hard-codes {geometry.arctic_cropped}-px allocentric crops "
                "(dataset_utils.transform_2d_for_speedup)"
                f"; this world's crops are {geometry.cropped_size} px (meta/hogsa_world.json); --image-mode",
            )
        try:
            yield stats
        finally:
            ad.read_img, du.rgb_processing = orig_read, orig_rgb

    @contextlib.contextmanager
    def smplx_standin(self) -> Iterator[None]:
        """ARCTIC's SMPL-X layers are replaced by a layer that returns NaN joints/vertices."""
        import torch

        bm = self.module("common.body_models")
        orig = bm.build_smplx, bm.build_subject_smplx

        class NanSMPLX(torch.nn.Module):
            """Stand-in SMPL-X: NaN joints (B, 127, 3) and vertices (B, 1, 3)."""

            def forward(self, **params: Any) -> Any:
                b = params["global_orient"].shape[0]
                nan = float("nan")
                return types.SimpleNamespace(vertices=torch.full((b, 1, 3), nan), joints=torch.full((b, 127, 3), nan))

        bm.build_smplx = lambda batch_size, gender, vtemplate: NanSMPLX()
        bm.build_subject_smplx = lambda batch_size, subject_id: NanSMPLX()
        self.notes.patch(
            "SMPL-X layer (processing)",
            "common.body_models.build_smplx / build_subject_smplx return a layer giving NaN joints (B,127,3) "
            "(and one NaN vertex; vertices are not exported)",
            "the world ships no SMPL-X model or subject template (licensed, see meta/hogsa_world.json); only "
            "joints.smplx depends on it, which the world's splits hold as NaN stand-ins; --require-smplx turns this "
            "off",
        )
        try:
            yield
        finally:
            bm.build_smplx, bm.build_subject_smplx = orig

    def args(self, setup: str) -> Any:
        """ARCTIC's own ``construct_args()`` for ArcticNet-SF on ``setup``."""
        parser = self.module("src.parsers.parser")
        argv = sys.argv
        sys.argv = ["train.py", "--method", "arctic_sf", "--setup", setup, "--trainsplit", "train", "--valsplit", "val"]
        try:
            args = parser.construct_args()
        finally:
            sys.argv = argv
        args.experiment = None  # scripts_method/train.py sets a comet experiment; none here
        return args


# ----------------------------------------------------------------------------------------
# Check 1: datasets
# ----------------------------------------------------------------------------------------


def _pick_indices(n: int, k: int) -> list[int]:
    if n <= 0 or k <= 0:
        return []
    if k >= n:
        return list(range(n))
    return sorted({int(round(i * (n - 1) / (k - 1))) for i in range(k)}) if k > 1 else [0]


def our_config(args: Any) -> Any:
    from hogsa_loader.sample.augment import ArcticConfig

    return ArcticConfig(
        img_res=int(args.img_res),
        focal_length=float(args.focal_length),
        rot_factor=float(args.rot_factor),
        noise_factor=float(args.noise_factor),
        scale_factor=float(args.scale_factor),
        flip_prob=float(args.flip_prob),
        img_norm_mean=tuple(args.img_norm_mean),
        img_norm_std=tuple(args.img_norm_std),
        window_size=int(args.window_size),
        use_gt_k=bool(args.use_gt_k),
    )


def run_dataset_check(
    sess: ArcticSession,
    data_root: Path,
    splits: Sequence[str],
    items: int,
    seed: int,
    img_tol: float,
    image_mode: str,
    log: Callable[[str], None],
) -> dict[str, Any]:
    from hogsa_loader.assets.arctic import ArcticRoot

    root = ArcticRoot(data_root)
    meta = root.world_meta()
    parser_ego = float(sess.args("p2").ego_image_scale)
    world_ego = float(meta.ego_image_scale)
    # ego_image_scale is one of ARCTIC's settings (its parser's 0.3 matches its released
    # egocentric images): set it to the world's, as a user of such data would
    ego_setting = None if world_ego == parser_ego else world_ego
    if ego_setting is not None:
        sess.notes.patch(
            "ARCTIC setting ego_image_scale",
            f"args.ego_image_scale = {world_ego:g} (the world's, meta/hogsa_world.json) instead of the "
            f"parser's {parser_ego:g}",
            "a setting of ARCTIC's (src/parsers/parser.py), which scales the "
            "egocentric labels and box to the egocentric image files",
        )
    geometry = ImageGeometry(
        cropped_size=int(meta.cropped_size),
        ego_scale=world_ego,
        ego_full_sizes={sid: tuple(int(v) for v in root.subject_misc(sid).image_size[0]) for sid in root.subjects()},
        arctic_ego_scale=world_ego,
    )
    if geometry.arctic_sized:
        ctx: Any = contextlib.nullcontext({"mode": "none", "images": 0, "sizes": {}})
    else:
        ctx = sess.world_sized_images(image_mode, geometry)
    with ctx as stats:
        result = _dataset_runs(
            sess, data_root, splits, items, seed, img_tol, None if geometry.arctic_sized else geometry, ego_setting, log
        )
    result["world_image_sizes"] = {
        "cropped_size": geometry.cropped_size,
        "ego_image_scale": world_ego,
        "arctic_cropped_size": geometry.arctic_cropped,
        "arctic_parser_ego_image_scale": parser_ego,
    }
    result["arctic_ego_image_scale_used"] = world_ego
    result["image_adaptation"] = stats
    if ego_setting is not None:
        result["notes"].append(
            f"ARCTIC ran with args.ego_image_scale = {world_ego:g} (the world's egocentric image "
            f"scale; its parser sets {parser_ego:g} for ARCTIC's released images)"
        )
    if not geometry.arctic_sized:
        result["notes"].append(
            f"the world's allocentric crops are {geometry.cropped_size} px but ARCTIC's code hard-codes "
            f"{geometry.arctic_cropped} px (src/datasets/dataset_utils.py, common/data_utils.py transform_kp2d): "
            "ARCTIC "
            "computes those labels and the crop box in a 1000-px frame. 2D labels may then differ by one-pixel "
            f"truncation flips (allowed on <= {FLIP_FRACTION:.1%} of the coordinates); --image-mode {image_mode}: "
            + {
                "map": "ARCTIC's image processing ran on the file with its crop box scaled into the file's pixels",
                "upsample": "ARCTIC read the files upsampled to 1000 px, so inputs.img differs by resampling "
                "(and by the blur: ours blurs the small file with ARCTIC's 5-px kernel)",
                "raw": "ARCTIC cropped the small files with its own geometry (the wrong region)",
            }[image_mode]
            + "; meta_info.center is compared in the file's pixels (ARCTIC's value times the same factor)"
        )
    return result


def _dataset_runs(
    sess: ArcticSession,
    data_root: Path,
    splits: Sequence[str],
    items: int,
    seed: int,
    img_tol: float,
    geometry: Optional[ImageGeometry],
    ego_setting: Optional[float],
    log: Callable[[str], None],
) -> dict[str, Any]:
    from hogsa_loader.assets.conventions import EGO_VIEW
    from hogsa_loader.sample.arctic_dataset import ArcticDataset as OurDataset

    ad = sess.module("src.datasets.arctic_dataset")
    result: dict[str, Any] = {"runs": {}, "notes": []}
    for name in splits:
        setup, split = name.split("_", 1)
        args = sess.args(setup)
        if ego_setting is not None:
            args.ego_image_scale = ego_setting
        t0 = time.time()
        theirs = ad.ArcticDataset(args, split)
        modes = ("aug", "noaug") if split.endswith("train") else ("noaug",)
        for mode in modes:
            aug = mode == "aug"
            ours = OurDataset(
                data_root,
                split=name,
                augment=aug,
                seed=seed,
                use_gt_k=bool(args.use_gt_k),
                speedup=bool(args.speedup),
                config=our_config(args),
            )
            run: dict[str, Any] = {
                "split": name,
                "augment": aug,
                "imgnames_equal": [str(n) for n in theirs.imgnames] == list(ours.imgnames),
                "num_images": [len(theirs.imgnames), len(ours.imgnames)],
                "items": [],
            }
            theirs.aug_data = aug
            # ARCTIC caches the first egocentric patch K it computes; ours takes the first
            # egocentric image in split order: prime ARCTIC's cache with that image
            first_ego = next((n for n in theirs.imgnames if int(str(n).split("/")[-2]) == EGO_VIEW), None)
            if first_ego is not None and theirs.egocam_k is None:
                theirs.aug_data = False
                theirs.getitem(first_ego, load_rgb=False)
                theirs.aug_data = aug
            per_item = []
            keys_report: dict[str, Any] = {}
            for idx in _pick_indices(len(ours), items):
                imgname = theirs.imgnames[idx]
                if aug:
                    with sess.routed_random(ours.rng(idx)) as rnd:
                        a = theirs.getitem(imgname)
                    draws = rnd.draws
                else:
                    a = theirs.getitem(imgname)
                    draws = 0
                b = ours[idx]
                if geometry is not None:  # ARCTIC's centre is in its assumed frame, ours in the file's pixels
                    a[2]["center"] = (a[2]["center"] * np.float32(geometry.factor(str(imgname)))).astype(np.float32)
                c = compare_samples(a, b)
                per_item.append(c)
                run["items"].append(
                    {
                        "index": idx,
                        "imgname": str(imgname),
                        "random_draws": draws,
                        "rot": [float(a[2]["rot_angle"]), float(b[2]["rot_angle"])],
                    }
                )
                for group, k in c["keys"].items():
                    cur = keys_report.setdefault(group, {"arctic_only": set(), "ours_only": set(), "same_order": True})
                    cur["arctic_only"] |= set(k["arctic_only"])
                    cur["ours_only"] |= set(k["ours_only"])
                    cur["same_order"] &= k["same_order"]
            run["keys"] = {
                g: {
                    "arctic_only": sorted(v["arctic_only"]),
                    "ours_only": sorted(v["ours_only"]),
                    "same_order": v["same_order"],
                }
                for g, v in keys_report.items()
            }
            run["keys_equal"] = all(
                not v["arctic_only"] and not v["ours_only"] and v["same_order"] for v in run["keys"].values()
            )
            rescaled = geometry is not None and any(geometry.factor(i["imgname"]) != 1.0 for i in run["items"])
            run["labels_rescaled"] = rescaled
            run["fields"] = aggregate_fields(per_item, img_tol, 2.0 / float(args.img_res) if rescaled else None)
            run["ok"] = bool(
                run["imgnames_equal"]
                and run["keys_equal"]
                and per_item
                and all(f["ok"] for f in run["fields"].values())
            )
            result["runs"][name + ({"aug": " aug", "noaug": " noaug"}[mode] if len(modes) > 1 else "")] = run
            log(
                f"  dataset {name} ({'augmented' if aug else 'no augmentation'}): {len(per_item)} items, "
                f"{'ok' if run['ok'] else 'DIFFERENT'} ({time.time() - t0:.1f}s)"
            )
    result["ok"] = bool(result["runs"]) and all(r["ok"] for r in result["runs"].values())
    result["notes"].append(
        "augmented runs: ARCTIC's augm_params runs unchanged, its np.random.uniform/randn calls are answered "
        "by our dataset's per-item generator numpy.random.default_rng([seed, epoch, index]) in the same order "
        "(flip draw, 3 colour factors, rotation, scale, rotation-off draw), so both get identical augmentation"
    )
    return result


# ----------------------------------------------------------------------------------------
# Check 2: one training step on a mixed batch
# ----------------------------------------------------------------------------------------


def _index_batch(batch: Any, keep: Sequence[int]) -> Any:
    import torch

    if isinstance(batch, torch.Tensor):
        return batch[list(keep)]
    if isinstance(batch, Mapping):
        return type(batch)({k: _index_batch(v, keep) for k, v in batch.items()})
    if isinstance(batch, tuple):
        return tuple(_index_batch(v, keep) for v in batch)
    if isinstance(batch, list):
        return [batch[i] for i in keep]
    return batch


def untrained_bundle(data_root: Path, out: Path, sid: str, obj: str) -> Path:
    """A bundle of untrained HOGS models (Gaussians initialised from MANO / the template)."""
    from hogsa_world.untrained import write_untrained_bundle

    return write_untrained_bundle(data_root, out, sid, obj)


def run_train_check(
    sess: ArcticSession,
    data_root: Path,
    arctic_src: Path,
    bundle: Optional[Path],
    batch: int,
    ratio: float,
    seed: int,
    log: Callable[[str], None],
) -> dict[str, Any]:
    import torch
    from torch.utils.data import DataLoader

    from hogsa_loader.assets.arctic import ArcticRoot
    from hogsa_loader.compose import ProceduralBackgrounds
    from hogsa_loader.sample import HOGSADataset, MixedLoader, is_synthetic, with_options
    from hogsa_loader.sample.arctic_dataset import ArcticDataset as OurDataset

    result: dict[str, Any] = {"notes": []}
    args = sess.args("p1")
    wrapper_mod = sess.module("src.models.arctic_sf.wrapper")
    sess.module("src.nets.backbone.resnet")
    sess.module("common.body_models")
    torch.manual_seed(seed)
    t0 = time.time()
    with sess.cuda_as_cpu():
        wrapper = wrapper_mod.ArcticSFWrapper(args)
    log(f"  train: ArcticSFWrapper built ({time.time() - t0:.1f}s)")

    real = OurDataset(
        data_root,
        split="p1_train",
        augment=True,
        seed=seed,
        use_gt_k=bool(args.use_gt_k),
        speedup=bool(args.speedup),
        config=our_config(args),
    )
    if bundle is None:
        root = ArcticRoot(data_root)
        sid, seq = str(real.imgnames[0]).split("/")[-4:-2]
        obj = seq.split("_")[0]
        t1 = time.time()
        bundle = untrained_bundle(data_root, sess.workdir / "hogsa_bundle", sid, obj)
        result["bundle"] = {"path": str(bundle), "trained": False, "subject": sid, "object": obj}
        result["notes"].append(
            f"no --bundle: synthetic samples from an untrained bundle for ({sid}, {obj}) "
            "(Gaussians initialised from the world's MANO and object template), 'perturb' poses, "
            f"procedural backgrounds ({time.time() - t1:.1f}s to build)"
        )
        del root
    else:
        result["bundle"] = {"path": str(bundle), "trained": True}
    n_syn = int(math.floor(ratio * batch + 0.5))
    synth = HOGSADataset(
        bundle,
        data_root,
        with_options(
            poses="perturb",
            batch_size=max(1, n_syn),
            num_samples=max(1, n_syn) * 4,
            seed=seed,
            protocol="p1",
            split="train",
            arctic=our_config(args),
        ),
        backgrounds=ProceduralBackgrounds(),
    )
    gen = torch.Generator().manual_seed(seed)
    mixed = MixedLoader(DataLoader(real, batch_size=batch, shuffle=True, generator=gen), synth, ratio=ratio)
    t1 = time.time()
    inputs, targets, meta_info = next(iter(mixed))
    names = list(meta_info["imgname"])
    syn_idx = [i for i, n in enumerate(names) if is_synthetic(n)]
    real_idx = [i for i, n in enumerate(names) if not is_synthetic(n)]
    result["batch"] = {
        "size": len(names),
        "real": len(real_idx),
        "synthetic": len(syn_idx),
        "imgnames": names,
        "seconds": time.time() - t1,
    }
    log(f"  train: mixed batch of {len(real_idx)} real + {len(syn_idx)} synthetic ({time.time() - t1:.1f}s)")

    expected = arctic_loss_keys(arctic_src)
    try:
        optimizers, _ = wrapper.configure_optimizers()
        opt = optimizers[0]
        result["optimizer"] = "ARCTIC's configure_optimizers (Adam, lr=args.lr)"
    except TypeError as exc:  # MultiStepLR(verbose=...) is gone from recent torch
        opt = torch.optim.Adam(wrapper.parameters(), lr=args.lr)
        result["optimizer"] = f"Adam(lr=args.lr) as ARCTIC's configure_optimizers (its scheduler failed: {exc})"
    before = {n: p.detach().clone() for n, p in wrapper.named_parameters() if p.requires_grad}
    t1 = time.time()
    wrapper.train()
    with sess.cuda_as_cpu():
        out = wrapper.training_step((inputs, targets, meta_info), 0)
        loss = out["loss"]
        opt.zero_grad()
        loss.backward()
        grads = [p.grad for p in wrapper.parameters() if p.grad is not None]
        no_grad = [n for n, p in wrapper.named_parameters() if p.requires_grad and p.grad is None]
        grads_finite = all(bool(torch.isfinite(g).all()) for g in grads)
        grad_norm = float(torch.nn.utils.clip_grad_norm_(wrapper.parameters(), float(args.grad_clip)))
        opt.step()
    changed = sum(int(not torch.equal(before[n], p.detach())) for n, p in wrapper.named_parameters() if n in before)
    result["step_seconds"] = time.time() - t1
    losses = {k: float(v.detach().reshape(-1)[0]) for k, v in out.items()}
    result["losses"] = losses
    result["expected_keys"] = expected
    result["missing_keys"] = [k for k in expected if k not in losses]
    result["nonfinite_keys"] = [k for k, v in losses.items() if not math.isfinite(v)]
    result["zero_keys"] = [k for k in expected if losses.get(k) == 0.0]
    result["grads_finite"] = grads_finite
    result["grad_norm"] = grad_norm
    result["params_changed"] = [changed, len(before)]
    result["params_without_grad"] = no_grad
    log(f"  train: step done, loss {losses.get('loss', float('nan')):.4f} ({time.time() - t1:.1f}s)")

    # the two halves on their own (no step), for scale
    halves: dict[str, Any] = {}
    with torch.no_grad(), sess.cuda_as_cpu():
        for label, keep in (("real", real_idx), ("synthetic", syn_idx)):
            if not keep:
                continue
            sub = _index_batch((inputs, targets, meta_info), keep)
            o = wrapper.forward(*sub, "train")["loss"]
            halves[label] = {k: float(v.detach().reshape(-1)[0]) for k, v in o.items()}
    result["halves"] = halves
    result["ok"] = bool(
        not result["missing_keys"]
        and not result["nonfinite_keys"]
        and grads_finite
        and math.isfinite(grad_norm)
        and changed > 0
        and syn_idx
        and real_idx
    )
    return result


# ----------------------------------------------------------------------------------------
# Check 3: processing and splits
# ----------------------------------------------------------------------------------------


def run_processing_check(
    sess: ArcticSession, data_root: Path, smplx_standin: bool, log: Callable[[str], None]
) -> dict[str, Any]:
    import torch

    from hogsa_loader.assets.arctic import ArcticRoot

    root = ArcticRoot(data_root)
    result: dict[str, Any] = {"sequences": {}, "splits": {}, "notes": [], "smplx_standin": smplx_standin}
    if smplx_standin:
        result["notes"].append(
            "SMPL-X models/templates missing: ARCTIC's SMPL-X layer returned NaN (joints.smplx "
            "compares NaN with the world's NaN stand-ins)"
        )
    with sess.cuda_as_cpu(), sess.smplx_standin() if smplx_standin else contextlib.nullcontext():
        bm = sess.module("common.body_models")
        ot = sess.module("common.object_tensors")
        proc = sess.module("src.arctic.processing")
        split_mod = sess.module("src.arctic.split")
        misc = json.loads((root.meta_dir / "misc.json").read_text())
        statcams = {
            sub: {
                "world2cam": torch.FloatTensor(np.array(misc[sub]["world2cam"])),
                "intris_mat": torch.FloatTensor(np.array(misc[sub]["intris_mat"])),
            }
            for sub in misc
        }
        t0 = time.time()
        layers = bm.construct_layers("cpu")
        object_tensor = ot.ObjectTensors()
        object_tensor.to("cpu")
        layers["object"] = object_tensor
        log(f"  processing: layers built ({time.time() - t0:.1f}s)")
        mano_ps = sorted(str(p) for p in Path("./data/arctic_data/data/raw_seqs").glob("*/*.mano.npy"))
        mano_ps = ["./" + os.path.relpath(p) if not p.startswith(".") else p for p in mano_ps]
        for mano_p in mano_ps:
            t1 = time.time()
            key = "/".join(mano_p.split("/")[-2:]).replace(".mano.npy", "")
            try:
                proc.process_seq([mano_p, "cpu", statcams, layers, _NullBar()], export_verts=False)
                result["sequences"][key] = {"ok": True, "seconds": time.time() - t1}
            except Exception as exc:  # reported per sequence, as process_seqs.py logs and goes on
                result["sequences"][key] = {
                    "ok": False,
                    "error": f"{type(exc).__name__}: {exc}",
                    "traceback": traceback.format_exc(limit=6),
                }
            log(f"  processing: {key} {'ok' if result['sequences'][key]['ok'] else 'FAILED'} ({time.time() - t1:.1f}s)")
        for protocol in ("p1", "p2"):
            for split in ("train", "val", "test"):
                ours_p = root.arctic_dir / "splits" / f"{protocol}_{split}.npy"
                if split == "test" and not ours_p.is_file():
                    continue
                name = f"{protocol}_{split}"
                try:
                    split_mod.build_split(protocol, split, list(REQUEST_KEYS), "./outputs/processed/seqs")
                    theirs = np.load(f"./outputs/splits/{name}.npy", allow_pickle=True).item()
                except Exception as exc:
                    result["splits"][name] = {
                        "ok": False,
                        "error": f"{type(exc).__name__}: {exc}",
                        "traceback": traceback.format_exc(limit=6),
                    }
                    continue
                if not ours_p.is_file():
                    result["splits"][name] = {"ok": False, "error": f"the world has no {ours_p.name}"}
                    continue
                ours = np.load(ours_p, allow_pickle=True).item()
                cmp = compare_split_data(theirs, ours)
                cmp["ok"] = bool(
                    cmp["imgnames_equal"] and cmp["sequences_equal"] and all(k["ok"] for k in cmp["keys"].values())
                )
                result["splits"][name] = cmp
                log(f"  processing: split {name} {'ok' if cmp['ok'] else 'DIFFERENT'}")
    meta = root.world_meta()
    ego = tuple(int(v) for v in getattr(meta, "ego_image_size", (2800, 2000)))
    result["world"] = {"ego_image_size": list(ego)}
    if ego != (2800, 2000):
        result["notes"].append(
            f"the world's egocentric images are {ego[0]}x{ego[1]}; ARCTIC's processing "
            "hard-codes 2800x2000 for the ego box and ego validity region (forward_define_bbox, "
            "forward_valid), so bbox view 0 and the view-0 flags differ by design"
        )
    result["ok"] = (
        bool(result["sequences"])
        and all(s["ok"] for s in result["sequences"].values())
        and bool(result["splits"])
        and all(s["ok"] for s in result["splits"].values())
    )
    return result


# ----------------------------------------------------------------------------------------
# Report
# ----------------------------------------------------------------------------------------


def run_field_check(sess: ArcticSession, data_root: Path, seed: int, log: Callable[[str], None]) -> dict[str, Any]:
    import numpy as np
    import torch
    from torch.utils.data import DataLoader, Subset

    from hogsa_loader.assets.arctic import ArcticRoot
    from hogsa_loader.baselines import (
        BodyLayers,
        InterFieldSF,
        field_acceleration,
        field_metrics,
        interfield_loss,
        load_field_weights,
        prepare_targets,
        read_mano_decimator,
        temporal_order,
    )
    from hogsa_loader.baselines.arcticnet_sf import read_arctic_weights
    from hogsa_loader.sample.arctic_dataset import ArcticDataset as OurDataset

    loss_field = sess.module("src.callbacks.loss.loss_field")
    eval_modules = sess.module("src.utils.eval_modules")
    xdict = sess.module("common.xdict").xdict
    root = ArcticRoot(data_root)
    layers = BodyLayers.from_root(root)
    real = OurDataset(data_root, split="p1_train", augment=False, seed=seed, config=our_config(sess.args("p1")))
    order = temporal_order(real.imgnames)
    clip = "/".join(str(real.imgnames[order[0]]).split("/")[-4:-1])
    frames = [i for i in order if "/".join(str(real.imgnames[i]).split("/")[-4:-1]) == clip][:8]
    inputs, targets, meta = next(iter(DataLoader(Subset(real, frames), batch_size=len(frames))))
    img_res = int(inputs["img"].shape[-1])
    targets, meta = prepare_targets(
        dict(targets), dict(meta), layers.mano_r, layers.mano_l, layers.objects, img_res=img_res, max_dist=0.1
    )
    D = read_mano_decimator(root.meta_dir / "mano_decimator_195.npy", int(layers.mano_r.v_template.shape[0]))
    torch.manual_seed(seed)
    with torch.no_grad():
        model = InterFieldSF("resnet18", layers.mano_r, layers.mano_l, layers.objects, D).eval()
        out = model(inputs, meta)
    keys = ("dist.ro", "dist.lo", "dist.or", "dist.ol")
    gen = torch.Generator().manual_seed(seed)
    noisy = {k: targets[k].float() + 0.01 * torch.randn(targets[k].shape, generator=gen) for k in keys}
    gt = {k: targets[k].float() for k in ("is_valid", "right_valid", "left_valid", *keys)}
    v_len = torch.as_tensor(targets["object.v_len"])
    mask = (torch.arange(gt["dist.or"].shape[1])[None] < v_len[:, None]).float()
    rows: list[dict[str, Any]] = []

    def compare(what: str, key: str, ours: Any, theirs: Any) -> None:
        a = np.asarray(ours, dtype=np.float64).reshape(-1)
        b = np.asarray(torch.as_tensor(theirs).detach().double().reshape(-1))
        same_nan = a.shape == b.shape and bool((np.isnan(a) == np.isnan(b)).all())
        fin = ~np.isnan(a) & ~np.isnan(b) if same_nan else np.zeros(0, bool)
        diff = float(np.abs(a[fin] - b[fin]).max()) if fin.any() else 0.0
        scale = float(np.abs(b[fin]).max()) if fin.any() else 0.0
        ok = same_nan and diff <= 1e-5 * max(scale, 1e-6)
        rows.append(
            {
                "predictions": what,
                "key": key,
                "ours": float(np.nanmean(a)) if fin.any() else float("nan"),
                "arctic": float(np.nanmean(b)) if fin.any() else float("nan"),
                "max_abs_diff": diff,
                "nan_agree": same_nan,
                "ok": ok,
            }
        )

    for what, pred in (("InterFieldSF", {k: out[k] for k in keys}), ("targets + noise", noisy)):
        ours = interfield_loss(pred, dict(gt, **{"object.v_len": v_len}), 0.1)
        theirs = loss_field.dist_loss(xdict(), xdict(pred), xdict(gt), {"mask": mask})
        for k in ("ro", "lo", "or", "ol"):
            value, weight = theirs[f"loss/dist/{k}"]
            compare(what, f"loss/dist/{k}", float(ours[f"loss/dist/{k}"]), float(value) * weight)
        ours_m = field_metrics(pred, dict(gt, **{"object.v_len": v_len}))
        theirs_m = eval_modules.eval_field_errors(xdict(pred), xdict(gt), xdict({"object.v_len": v_len}))
        for k in ("avg/ho", "avg/oh"):
            compare(what, k, ours_m[k], theirs_m[k])
        ours_a = field_acceleration(pred, dict(gt, **{"object.v_len": v_len}))
        theirs_a = eval_modules.eval_acc_field(xdict(pred), xdict(gt), xdict())
        for k in ("acc/ho", "acc/oh"):
            compare(what, k, ours_a[k], theirs_a[k])
    # ARCTIC's FieldSF state dict (a Lightning checkpoint of it) loads into ours: every name and
    # shape agrees, every tensor arrives unchanged. ARCTIC sizes its up-samplers for MANO's 778
    # vertices and 4000 object vertices; both sides get the world's counts where they differ
    sess.module("src.nets.backbone.resnet")  # FieldSF imports it when built: patched first (no download)
    field_sf = sess.module("src.models.field_sf.model")
    theirs_model = field_sf.FieldSF("resnet18", focal_length=1000.0, img_res=img_res)
    longest = max(int(layers.objects.v_len.max()), int(theirs_model.num_v_o))
    theirs_model.upsampling_o = field_sf.Upsampler(theirs_model.num_v_o_sub, longest)  # the world's objects
    n_hand = int(layers.mano_r.v_template.shape[0])  # ARCTIC: MANO's 778; the world's MANO may differ
    theirs_model.upsampling_r = field_sf.Upsampler(theirs_model.num_v_sub, n_hand)
    theirs_model.upsampling_l = field_sf.Upsampler(theirs_model.num_v_sub, n_hand)
    with tempfile.TemporaryDirectory() as tmp:
        ckpt = Path(tmp) / "field_sf.ckpt"
        torch.save({"state_dict": {f"model.{k}": v for k, v in theirs_model.state_dict().items()}}, ckpt)
        ours_model = InterFieldSF("resnet18", layers.mano_r, layers.mano_l, layers.objects, D, object_outputs=longest)
        error = None
        try:
            load_field_weights(ours_model, ckpt)
        except Exception as exc:  # reported as a failed row
            error = f"{type(exc).__name__}: {exc}"
        state = read_arctic_weights(ckpt)
    own = ours_model.network_state_dict()
    same = [k for k, v in state.items() if k in own and own[k].shape == v.shape]
    diff = max((float((own[k].double() - state[k].double()).abs().max()) for k in same), default=0.0)
    rows.append(
        {
            "predictions": "FieldSF weights",
            "key": "state dict" + (f" ({error})" if error else ""),
            "ours": float(len(own)),
            "arctic": float(len(state)),
            "max_abs_diff": diff,
            "nan_agree": True,
            "ok": error is None and set(own) == set(state) == set(same) and diff == 0.0,
        }
    )
    log(f"  field: {sum(r['ok'] for r in rows)}/{len(rows)} figures agree on {len(frames)} frames of {clip}")
    return {"ok": all(r["ok"] for r in rows), "clip": clip, "frames": len(frames), "rows": rows}


def _fmt(x: Any) -> str:
    if x is None:
        return "-"
    if isinstance(x, float):
        if x == 0.0:
            return "0"
        return f"{x:.3g}" if abs(x) < 1e4 else f"{x:.3e}"
    return str(x)


def table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """Plain-text table with aligned columns."""
    cells = [[str(h) for h in headers]] + [[_fmt(c) if not isinstance(c, str) else c for c in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def _type_str(d: Optional[Mapping[str, Any]]) -> str:
    if not d:
        return "-"
    s = d["type"]
    if d.get("dtype"):
        s += f" {d['dtype']}"
    if d.get("shape") is not None and d["type"] in ("Tensor", "ndarray"):
        s += " " + "x".join(str(v) for v in d["shape"]) if d["shape"] else " scalar"
    return s


def format_notes(notes: Notes, pip_missing: Sequence[str]) -> str:
    parts = ["Stubs (modules ARCTIC imports that do not import here; injected through sys.modules):"]
    if notes.stubs:
        parts.append(
            table(["module", "replaces", "why"], [[s["module"], s["replaces"], s["why"]] for s in notes.stubs])
        )
    else:
        parts.append("  (none)")
    parts.append("\nRun-time patches (the installed packages and the ARCTIC checkout are not modified):")
    if notes.patches:
        parts.append(table(["what", "how", "why"], [[p["what"], p["how"], p["why"]] for p in notes.patches]))
    else:
        parts.append("  (none)")
    if pip_missing:
        parts.append(f"\nMissing packages: pip install {' '.join(pip_missing)}")
    return "\n".join(parts)


def group_missing(entries: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Missing entries with the same ``group`` folded into one row (``members`` listed)."""
    rows: list[dict[str, Any]] = []
    by_group: dict[str, dict[str, Any]] = {}
    for e in entries:
        if e["exists"]:
            continue
        g = e.get("group")
        if g is None:
            rows.append({"path": e["path"], "needed_by": e["needed_by"], "why": e["why"], "soft": e["soft"]})
            continue
        if g not in by_group:
            by_group[g] = {"path": g, "needed_by": e["needed_by"], "why": e["why"], "soft": e["soft"], "members": []}
            rows.append(by_group[g])
        by_group[g]["members"].append(e["member"])
    for r in rows:
        members = r.get("members")
        if not members:
            continue
        if "/<file>" in r["path"]:  # object templates: list objects, and the files when not all are missing
            objs: dict[str, list[str]] = {}
            for m in members:
                o, f = m.split("/", 1)
                objs.setdefault(o, []).append(f)
            whole = [o for o, fs in objs.items() if len(fs) == len(OBJECT_TEMPLATE_FILES)]
            part = [f"{o} ({', '.join(fs)})" for o, fs in objs.items() if len(fs) != len(OBJECT_TEMPLATE_FILES)]
            r["detail"] = (
                (f"{len(whole)} objects entirely: {', '.join(whole)}" if whole else "")
                + ("; " if whole and part else "")
                + ("; ".join(part))
            )
        else:
            r["detail"] = f"{len(members)}: {', '.join(members[:6])}" + (" ..." if len(members) > 6 else "")
    return rows


def format_missing(entries: Sequence[Mapping[str, Any]]) -> str:
    missing = [e for e in entries if not e["exists"]]
    head = f"Missing files (ARCTIC's code opens them; the world lacks them): {len(missing)}"
    if not missing:
        return head + "\n  (none)"
    rows = [
        [r["path"], r.get("detail", ""), ",".join(r["needed_by"]), ("soft: " if r["soft"] else "") + r["why"]]
        for r in group_missing(entries)
    ]
    return head + "\n" + table(["path (relative to ./data)", "which", "needed by", "what for"], rows)


def format_dataset(res: Mapping[str, Any]) -> str:
    runs = res.get("runs", {})
    if not runs:
        return "  (no run)"
    lines = [
        table(
            ["run", "images arctic/ours", "names equal", "items (rotated)", "keys equal", "ok"],
            [
                [
                    n,
                    f"{r['num_images'][0]}/{r['num_images'][1]}",
                    str(r["imgnames_equal"]),
                    f"{len(r['items'])} ({sum(1 for i in r['items'] if i['rot'][0] != 0)})",
                    str(r["keys_equal"]),
                    "PASS" if r["ok"] else "FAIL",
                ]
                for n, r in runs.items()
            ],
        )
    ]
    for n, r in runs.items():
        for g, k in r["keys"].items():
            if k["arctic_only"] or k["ours_only"] or not k["same_order"]:
                lines.append(
                    f"  {n} {g}: ARCTIC only {k['arctic_only']}, ours only {k['ours_only']}, "
                    f"same order {k['same_order']}"
                )
    names = _ordered_union(r["fields"] for r in runs.values())
    rows = []
    for f in names:
        first = next(r["fields"][f] for r in runs.values() if f in r["fields"])
        same = all(r["fields"][f]["same_type"] for r in runs.values() if f in r["fields"])
        row = [
            f,
            _type_str(first["ours"])
            if same
            else f"ours {_type_str(first['ours'])} / ARCTIC {_type_str(first['arctic'])}",
        ]
        for r in runs.values():
            c = r["fields"].get(f)
            if c is None:
                row.append("absent")
                continue
            if not c["numeric"]:
                cell = "equal" if c["equal"] else "DIFFERENT"
            else:
                cell = _fmt(c["max_abs"]) if c["max_abs"] is not None else "shape differs"
                if "2d.norm" in f and c.get("num_diff"):
                    cell += f" ({c['num_diff']}/{c['size']} flips)"
            row.append(cell + ("" if c["ok"] else " !"))
        row.append(f"{first['tolerance']['max_abs']:g}" if "tolerance" in first else "")
        rows.append(row)
    lines.append("\nmax |ARCTIC - ours| per field over the items ('!' = outside tolerance or type differs):")
    lines.append(table(["field", "type (both)"] + list(runs) + ["tol"], rows))
    img = [(n, r["fields"]["inputs.img"]["mean_abs"]) for n, r in runs.items() if "inputs.img" in r["fields"]]
    if img:
        lines.append("inputs.img mean |diff|: " + ", ".join(f"{n} {_fmt(v)}" for n, v in img))
    return "\n".join(lines)


def _short_list(items: Sequence[str], n: int = 4) -> str:
    return ", ".join(items[:n]) + (f" (+{len(items) - n} more)" if len(items) > n else "") if items else "none"


def format_train(res: Mapping[str, Any]) -> str:
    if "losses" not in res:
        return "  (no result)"
    halves = res.get("halves", {})
    keys = list(res["expected_keys"]) + [k for k in res["losses"] if k not in res["expected_keys"]]
    rows = [
        [
            k,
            _fmt(res["losses"].get(k)),
            _fmt(halves.get("real", {}).get(k)),
            _fmt(halves.get("synthetic", {}).get(k)),
            "missing" if k not in res["losses"] else ("NON-FINITE" if not math.isfinite(res["losses"][k]) else "ok"),
        ]
        for k in keys
    ]
    b = res["batch"]
    lines = [
        f"batch: {b['size']} samples = {b['real']} real (our ArcticDataset p1_train) + {b['synthetic']} "
        f"synthetic (HOGSADataset, bundle {res['bundle']['path']}, trained={res['bundle']['trained']})",
        table(["loss key", "mixed batch", "real half", "synthetic half", "status"], rows),
        f"gradients finite: {res['grads_finite']}, grad norm {_fmt(res['grad_norm'])}, parameters changed by "
        f"the step: {res['params_changed'][0]}/{res['params_changed'][1]} ({len(res['params_without_grad'])} get no "
        f"gradient: {_short_list(res['params_without_grad'])}); optimiser: {res['optimizer']}",
    ]
    if res["zero_keys"]:
        lines.append(f"losses exactly 0 on this batch (no valid target of that kind): {res['zero_keys']}")
    return "\n".join(lines)


def format_field(res: Mapping[str, Any]) -> str:
    if "rows" not in res:
        return "  (no result)"
    rows = [
        [
            r["predictions"],
            r["key"],
            _fmt(r["ours"]),
            _fmt(r["arctic"]),
            _fmt(r["max_abs_diff"]),
            "ok" if r["ok"] else "DIFFER",
        ]
        for r in res["rows"]
    ]
    head = f"{res['frames']} frames of {res['clip']} (p1_train, no augmentation); means over frames shown"
    return head + "\n" + table(["predictions", "figure", "ours", "ARCTIC", "max abs diff", "status"], rows)


def format_processing(res: Mapping[str, Any]) -> str:
    lines = [
        table(
            ["sequence", "ARCTIC process_seq", "seconds"],
            [
                [k, "ok" if v["ok"] else "FAILED: " + v["error"], _fmt(v.get("seconds"))]
                for k, v in res.get("sequences", {}).items()
            ],
        )
    ]
    splits = res.get("splits", {})
    good = {n: s for n, s in splits.items() if "keys" in s}
    for n, s in splits.items():
        if "keys" not in s:
            lines.append(f"  {n}: {s.get('error')}")
    if good:
        lines.append("")
        lines.append(
            table(
                ["split", "images arctic/ours", "names equal", "sequences equal", "ok"],
                [
                    [
                        n,
                        f"{s['num_images'][0]}/{s['num_images'][1]}",
                        str(s["imgnames_equal"]),
                        str(s["sequences_equal"]),
                        "PASS" if s["ok"] else "FAIL",
                    ]
                    for n, s in good.items()
                ],
            )
        )
        keys = _ordered_union(s["keys"] for s in good.values())
        rows = []
        for k in keys:
            first = next(s["keys"][k] for s in good.values() if k in s["keys"])
            t_a, t_o = _type_str(first.get("arctic")), _type_str(first.get("ours"))
            row = [k, t_o if t_a == t_o else f"ours {t_o} / ARCTIC {t_a}"]
            for s in good.values():
                e = s["keys"].get(k)
                if e is None:
                    row.append("absent")
                elif e.get("only"):
                    row.append(f"{e['only']} only" + (" (expected)" if e.get("expected") else " !"))
                else:
                    row.append(_fmt(e["max_abs"]) + ("" if e["ok"] else " !"))
            row.append(f"{first['tolerance']:g}" + (" rad" if first["kind"] == "rot" else ""))
            rows.append(row)
        lines.append("\nmax |ARCTIC - ours| per key over the sequences (rotations: geodesic angle):")
        lines.append(table(["key", "type (both)"] + list(good) + ["tol"], rows))
    for note in res.get("notes", []):
        lines.append(f"note: {note}")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------
# Main
# ----------------------------------------------------------------------------------------


def parse_args(argv: Optional[Sequence[str]] = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[1])
    p.add_argument("--arctic-src", required=True, help="checkout of zc-alexfan/arctic (with src/ and common/)")
    p.add_argument("--data", required=True, help="world: the folder playing ./data, or its arctic_data/data")
    p.add_argument("--json", default=None, help="write every figure to this JSON file")
    p.add_argument("--checks", default=",".join(CHECKS), help=f"comma-separated subset of {','.join(CHECKS)}")
    p.add_argument("--splits", default=",".join(SPLITS), help="dataset check: splits to compare")
    p.add_argument("--items", type=int, default=8, help="dataset check: items compared per split and mode")
    p.add_argument("--img-tol", type=float, default=DEFAULT_IMG_TOL, help="dataset check: max |diff| of inputs.img")
    p.add_argument("--bundle", default=None, help="train check: bundle for synthetic samples (default: untrained)")
    p.add_argument("--batch", type=int, default=4, help="train check: batch size")
    p.add_argument("--synthetic-ratio", type=float, default=0.5, help="train check: synthetic share of the batch")
    p.add_argument("--resnet-weights", default=None, help="train check: local torchvision resnet50 state dict")
    p.add_argument(
        "--image-mode",
        choices=("map", "upsample", "raw"),
        default="map",
        help="dataset check, worlds whose images are not ARCTIC's sizes: map ARCTIC's crop box into the "
        "file's pixels (default), upsample the files to ARCTIC's sizes, or adapt nothing",
    )
    p.add_argument(
        "--require-smplx", action="store_true", help="processing check: require the SMPL-X models (no NaN stand-in)"
    )
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--threads", type=int, default=1, help="torch/OpenCV threads")
    p.add_argument("--workdir", default=None, help="work folder (default: a temporary folder, removed)")
    p.add_argument("--keep-workdir", action="store_true", help="keep the work folder (ARCTIC's outputs/)")
    return p.parse_args(argv)


def _validate(ns: argparse.Namespace) -> tuple[Path, Path, list[str], list[str]]:
    src = Path(ns.arctic_src).expanduser()
    if not src.is_dir():
        raise UsageError(f"--arctic-src {src}: no such folder")
    if not (src / "src" / "models" / "arctic_sf").is_dir() or not (src / "common").is_dir():
        raise UsageError(f"--arctic-src {src}: not an ARCTIC checkout (no src/models/arctic_sf or common/)")
    data = Path(ns.data).expanduser()
    if not data.is_dir():
        raise UsageError(f"--data {data}: no such folder")
    data = data.resolve()
    if not (data / ARCTIC_SUBDIR).is_dir():
        if data.name == "data" and data.parent.name == "arctic_data":
            data = data.parent.parent
        else:
            raise UsageError(f"--data {data}: not a world (no {ARCTIC_SUBDIR} inside)")
    checks = [c.strip() for c in ns.checks.split(",") if c.strip()]
    bad = [c for c in checks if c not in CHECKS]
    if bad or not checks:
        raise UsageError(f"--checks: unknown {bad or '(empty)'}; choose from {','.join(CHECKS)}")
    splits = [s.strip() for s in ns.splits.split(",") if s.strip()]
    bad = [s for s in splits if s not in SPLITS]
    if bad:
        raise UsageError(f"--splits: unknown {bad}; choose from {','.join(SPLITS)}")
    if ns.bundle is not None and not Path(ns.bundle).is_dir():
        raise UsageError(f"--bundle {ns.bundle}: no such folder")
    if ns.resnet_weights is not None and not Path(ns.resnet_weights).is_file():
        raise UsageError(f"--resnet-weights {ns.resnet_weights}: no such file")
    if ns.batch < 2 or not 0.0 < ns.synthetic_ratio < 1.0:
        raise UsageError("--batch must be >= 2 and --synthetic-ratio in (0, 1) (the batch mixes both kinds)")
    return src.resolve(), data, checks, splits


def _split_imgnames(data: Path, splits: Sequence[str]) -> dict[str, list[str]]:
    out = {}
    for name in splits:
        p = data / ARCTIC_SUBDIR / "splits" / f"{name}.npy"
        if p.is_file():
            with contextlib.suppress(Exception):
                out[name] = [str(n) for n in np.load(p, allow_pickle=True).item()["imgnames"]]
    return out


def _versions() -> dict[str, str]:
    out = {"python": platform.python_version(), "numpy": np.__version__}
    for mod in ("torch", "smplx", "cv2", "pytorch_lightning"):
        with contextlib.suppress(Exception):
            out[mod] = str(importlib.import_module(mod).__version__)
    return out


def _arctic_commit(src: Path) -> Optional[str]:
    import subprocess

    if not (src / ".git").exists():  # an exported checkout (or a folder inside another repository)
        return None
    with contextlib.suppress(Exception):
        r = subprocess.run(["git", "-C", str(src), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10)
        if r.returncode == 0:
            return r.stdout.strip()
    return None


def main(argv: Optional[Sequence[str]] = None) -> int:
    ns = parse_args(argv)
    try:
        src, data, checks, splits = _validate(ns)
    except UsageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2

    import cv2
    import torch

    torch.set_num_threads(max(1, ns.threads))
    cv2.setNumThreads(max(1, ns.threads))
    log = lambda s: print(s, flush=True)  # noqa: E731

    importable = {name: module_imports(name) for name in list(PIP_PACKAGES) + list(STUB_REASONS)}
    stubs, pip_missing = plan_packages(importable, checks)
    if pip_missing:
        print(
            f"error: ARCTIC's code needs packages that are not installed: pip install {' '.join(pip_missing)}",
            file=sys.stderr,
        )
        return 2

    objects = arctic_objects(src)
    entries = required_files(data, objects, splits, _split_imgnames(data, splits), require_smplx=ns.require_smplx)
    notes = Notes()
    report: dict[str, Any] = {
        "arctic_src": str(src),
        "arctic_commit": _arctic_commit(src),
        "data": str(data),
        "versions": _versions(),
        "checks": {},
        "missing_files": [e for e in entries if not e["exists"]],
    }
    workdir = Path(ns.workdir) if ns.workdir else Path(tempfile.mkdtemp(prefix="arctic_crosscheck_"))
    log(f"ARCTIC cross-check: ARCTIC code {src} (commit {report['arctic_commit'] or 'unknown'}), world {data}")
    log(f"work folder {workdir} (data -> {data}; src, common -> {src})")
    status: dict[str, str] = {}
    try:
        with ArcticSession(
            src, data, workdir, notes, stubs, Path(ns.resnet_weights) if ns.resnet_weights else None
        ) as sess:
            for check in checks:
                blocked = blocking_missing(entries, check)
                if blocked:
                    status[check] = "SKIPPED"
                    report["checks"][check] = {"ok": False, "skipped": True, "missing": blocked}
                    log(f"{check}: SKIPPED, {len(blocked)} required files missing")
                    continue
                log(f"{check}: running")
                t0 = time.time()
                try:
                    if check == "dataset":
                        res = run_dataset_check(sess, data, splits, ns.items, ns.seed, ns.img_tol, ns.image_mode, log)
                    elif check == "field":
                        res = run_field_check(sess, data, ns.seed, log)
                    elif check == "train":
                        res = run_train_check(
                            sess,
                            data,
                            src,
                            Path(ns.bundle) if ns.bundle else None,
                            ns.batch,
                            ns.synthetic_ratio,
                            ns.seed,
                            log,
                        )
                    else:
                        standin = any(
                            not e["exists"]
                            and e["path"].startswith("body_models/smplx/")
                            or not e["exists"]
                            and "subject_vtemplates" in e["path"]
                            for e in entries
                        )
                        res = run_processing_check(sess, data, standin, log)
                except Exception as exc:
                    res = {
                        "ok": False,
                        "error": f"{type(exc).__name__}: {exc}",
                        "traceback": traceback.format_exc(limit=12),
                    }
                    log(f"{check}: ERROR {type(exc).__name__}: {exc}")
                res["seconds"] = time.time() - t0
                report["checks"][check] = res
                status[check] = "PASS" if res["ok"] else ("ERROR" if "error" in res else "FAIL")
    finally:
        if not ns.workdir and not ns.keep_workdir:
            shutil.rmtree(workdir, ignore_errors=True)
    report["stubs"], report["patches"] = notes.stubs, notes.patches
    report["status"] = status
    report["ok"] = bool(status) and all(v == "PASS" for v in status.values())

    print()
    print(format_notes(notes, pip_missing))
    print()
    print(format_missing(entries))
    titles = {
        "dataset": "Check 1 - ARCTIC's ArcticDataset vs hogsa_loader ArcticDataset",
        "train": "Check 2 - one ArcticNet-SF training step (ARCTIC's wrapper and compute_loss) on a mixed batch",
        "processing": "Check 3 - ARCTIC's process_seq + build_split vs the world's splits/*.npy",
        "field": "Check 4 - InterField-SF's loss, average error and acceleration error vs ARCTIC's",
    }
    fmt = {"dataset": format_dataset, "train": format_train, "processing": format_processing, "field": format_field}
    for check in checks:
        res = report["checks"].get(check, {})
        print(f"\n{titles[check]}: {status.get(check, '?')}")
        if res.get("skipped"):
            rows = group_missing([e for e in entries if e["path"] in set(res["missing"])])
            print(
                f"  {len(res['missing'])} required files missing (see 'Missing files'): "
                + "; ".join(r["path"] + (f" [{r['detail']}]" if r.get("detail") else "") for r in rows)
            )
            continue
        if "error" in res:
            print(f"  {res['error']}\n" + "\n".join("    " + ln for ln in res["traceback"].splitlines()[-8:]))
            continue
        print(fmt[check](res))
        for note in res.get("notes", []) if check != "processing" else []:
            print(f"note: {note}")
    print("\nSummary: " + ", ".join(f"{c} {s}" for c, s in status.items()) + f" -> exit {0 if report['ok'] else 1}")
    if ns.json:
        out = Path(ns.json)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(report, indent=1, default=_json_default))
        print(f"JSON: {out}")
    return 0 if report["ok"] else 1


def _json_default(x: Any) -> Any:
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.floating,)):
        return float(x)
    if isinstance(x, (np.ndarray,)):
        return x.tolist()
    if isinstance(x, (set, tuple)):
        return list(x)
    if isinstance(x, Path):
        return str(x)
    return str(x)


if __name__ == "__main__":
    sys.exit(main())
