"""An H2O root read as grasp sequences: what ContactNet and the POM pose bank learn from.

:class:`H2OPoseRoot` answers the calls the pose stages make of an ARCTIC root
(:class:`~hogsa_loader.assets.arctic.ArcticRoot`): ``"sid/seq"`` ids, one
:class:`SequenceData` per id, the MANO layers and the object templates. H2O keeps MANO and
the object meshes outside its root, so both folders are given.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Optional

import torch

from hogsa_loader.assets.h2o import H2O_EGO_CAMERA, H2ORoot
from hogsa_loader.assets.h2o_meshes import find_h2o_mesh, load_h2o_object
from hogsa_loader.assets.hands.mano import MANOLayer
from hogsa_loader.assets.hands.mano_io import load_mano
from hogsa_loader.assets.objects.articulated import ArticulatedObjectLayer
from hogsa_loader.assets.objects.rigid import H2O_OBJECT_NAMES
from hogsa_loader.assets.types import SequenceData
from hogsa_loader.errors import AssetError, PathLike

__all__ = ["H2OPoseRoot", "h2o_sequence_id"]


def h2o_sequence_id(subject: str, scene: str, seq: str, obj: str) -> str:
    """The ``"sid/seq"`` id of an H2O sequence's grasps of one object: ``subject1/book_h1_0``
    (object first, as ARCTIC's ``s01/box_grab_01``)."""
    return f"{subject}/{obj}_{scene}_{seq}"


def _has_mesh(mesh_dir: Path, name: str) -> bool:
    try:
        find_h2o_mesh(mesh_dir, name)
    except AssetError:
        return False
    return True


class H2OPoseRoot:
    """An H2O root with its MANO and object-mesh folders, as grasp sequences.

    * Ids: one per (sequence, object class its ``obj_pose_rt`` labels show), named by
      :func:`h2o_sequence_id`; a sequence showing two objects gives two ids, each with the
      other object's frames marked invalid.
    * Labels are those of the egocentric camera (``cam4``), in H2O's world frame; a subject's
      labels are read when its sequences are first listed (a held-out subject's only when
      asked for).
    * Hands: ``flat_hand_mean=False`` MANO layers of ``mano_dir`` (H2O's poses are turned
      into poses relative to the mean by :meth:`H2ORoot.sequence`).
    * Objects: rigid templates (every face in the bottom part) of the meshes in
      ``object_mesh_dir``.

    Args:
        root: H2O root (``subject1``, ``subject2``, ...).
        mano_dir: folder with ``MANO_RIGHT.pkl`` / ``MANO_LEFT.pkl`` (kept as an absolute path).
        object_mesh_dir: folder of the object meshes (``<name>/<name>.obj|.ply``; absolute too).

    Raises:
        AssetError: a folder does not exist.
    """

    def __init__(self, root: PathLike, mano_dir: Optional[PathLike], object_mesh_dir: Optional[PathLike]) -> None:
        self.h2o = H2ORoot(root)
        self.root = self.data_root = self.h2o.root
        for what, path in (("mano_dir", mano_dir), ("object_mesh_dir", object_mesh_dir)):
            if not path:
                raise AssetError(self.root, f"an H2O root needs {what} (H2O keeps it outside the dataset)")
            if not Path(path).is_dir():
                raise AssetError(path, f"{what} folder not found")
        self.mano_dir = Path(os.path.abspath(mano_dir))  # type: ignore[arg-type]
        self.object_mesh_dir = Path(os.path.abspath(object_mesh_dir))  # type: ignore[arg-type]
        self._ids: dict[str, dict[str, tuple[str, str, str, int]]] = {}
        self._mano_layers: dict[torch.dtype, dict] = {}
        self._templates: Optional[dict] = None

    def __repr__(self) -> str:
        return f"H2OPoseRoot({str(self.root)!r})"

    def _index(self, subject: str) -> dict[str, tuple[str, str, str, int]]:
        """id -> (subject, scene, seq, object class) of one subject (its labels read once)."""
        if subject not in self._ids:
            ids = {}
            for subj, scene, seq in self.h2o.sequences(subject) if subject in self.subjects() else ():
                frames = self.h2o.frames(subj, scene, seq, H2O_EGO_CAMERA)
                cls, _ = self.h2o.read_obj_poses(subj, scene, seq, H2O_EGO_CAMERA, frames)
                for c in sorted(set(cls.tolist()) - {0}):
                    ids[h2o_sequence_id(subj, scene, seq, H2O_OBJECT_NAMES[c])] = (subj, scene, seq, int(c))
            self._ids[subject] = dict(sorted(ids.items()))
        return self._ids[subject]

    def subjects(self) -> list[str]:
        """Subject folders, as :meth:`H2ORoot.subjects`."""
        return self.h2o.subjects()

    def sequences(self, subject: Optional[str] = None) -> list[str]:
        """Sorted ``"sid/seq"`` ids (see the class); reads the object labels of the subjects
        listed (all of them when ``subject`` is None).

        Args:
            subject: restrict to one subject (none are listed for a subject the root lacks).
        """
        subjects = self.subjects() if subject is None else [subject]
        return sorted(k for s in subjects for k in self._index(s))

    def h2o_sequence(self, sid_seq: str) -> tuple[str, str, str, int]:
        """``(subject, scene, seq, object class)`` of an id.

        Raises:
            KeyError: no such id.
        """
        ids = self._index(sid_seq.split("/", 1)[0])
        if sid_seq not in ids:
            raise KeyError(f"{sid_seq!r} is not a sequence of {self.root} (ids: subject/<object>_<scene>_<seq>)")
        return ids[sid_seq]

    def sequence(self, sid: str, seq: str) -> SequenceData:
        """The grasps of id ``sid/seq`` as :class:`SequenceData` (H2O world frame, labels and
        camera of ``cam4`` only; ``name`` is the id's ``seq``)."""
        subj, scene, num, cls = self.h2o_sequence(f"{sid}/{seq}")
        layers = self.mano_layers(torch.float64)
        data = self.h2o.sequence(subj, scene, num, layers, cameras=[H2O_EGO_CAMERA], object_class=cls)
        data.name = seq
        return data

    def mano_layers(self, dtype: torch.dtype = torch.float32) -> dict:
        """``{"right": MANOLayer, "left": MANOLayer}`` of ``mano_dir`` (``flat_hand_mean=False``, cached)."""
        if dtype not in self._mano_layers:
            self._mano_layers[dtype] = {
                side: MANOLayer(load_mano(self.mano_dir, side=side), flat_hand_mean=False, dtype=dtype).eval()
                for side in ("right", "left")
            }
        return self._mano_layers[dtype]

    def object_templates(self, load_texture: bool = True) -> dict:
        """``{name: ObjectTemplate}`` of every H2O object whose mesh ``object_mesh_dir`` holds
        (rigid, metres, cached without texture; ``load_texture`` reads the texture too).

        Raises:
            AssetError: the folder holds no H2O object mesh.
        """
        names = [n for n in H2O_OBJECT_NAMES[1:] if _has_mesh(self.object_mesh_dir, n)]
        if not names:
            raise AssetError(self.object_mesh_dir, f"no H2O object mesh found (objects: {H2O_OBJECT_NAMES[1:]})")
        if load_texture:
            return {n: load_h2o_object(self.object_mesh_dir, n) for n in names}
        if self._templates is None:
            self._templates = {n: load_h2o_object(self.object_mesh_dir, n, load_texture=False) for n in names}
        return self._templates

    def object_layer(self) -> Any:
        """An :class:`ArticulatedObjectLayer` of the templates (θ has no effect on rigid objects)."""
        return ArticulatedObjectLayer(self.object_templates(load_texture=False))
