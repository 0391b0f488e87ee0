"""An H2O root read as grasp sequences: what ContactNet and the POM pose bank learn from.

:class:`H2OPoseRoot` answers the calls the pose stages make of an ARCTIC root
(:class:`~hogsa_loader.assets.arctic.ArcticRoot`): ``"sid/seq"`` ids, one
:class:`SequenceData` per id, the MANO layers and the object templates. H2O keeps MANO and
the object meshes outside its root, so both folders are given.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import torch

from hogsa_loader.assets.h2o import H2O_EGO_CAMERA, H2ORoot
from hogsa_loader.assets.h2o_meshes import load_h2o_object
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


class H2OPoseRoot:
    """An H2O root with its MANO and object-mesh folders, as grasp sequences.

    * Ids: one per (sequence, object class its ``obj_pose_rt`` labels show), named by
      :func:`h2o_sequence_id`; a sequence showing two objects gives two ids, each with the
      other object's frames marked invalid.
    * Labels are those of the egocentric camera (``cam4``), in H2O's world frame.
    * Hands: ``flat_hand_mean=False`` MANO layers of ``mano_dir`` (H2O's poses are turned
      into poses relative to the mean by :meth:`H2ORoot.sequence`).
    * Objects: rigid templates (every face in the bottom part) of ``object_mesh_dir``.

    Args:
        root: H2O root (``subject1``, ``subject2``, ...).
        mano_dir: folder with ``MANO_RIGHT.pkl`` / ``MANO_LEFT.pkl``.
        object_mesh_dir: folder of the object meshes (``<name>/<name>.obj|.ply``).

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
        self.mano_dir, self.object_mesh_dir = Path(mano_dir), Path(object_mesh_dir)  # type: ignore[arg-type]
        self._ids: Optional[dict[str, tuple[str, str, str, int]]] = None
        self._mano_layers: dict[torch.dtype, dict] = {}
        self._templates: Optional[dict] = None

    def __repr__(self) -> str:
        return f"H2OPoseRoot({str(self.root)!r})"

    def _index(self) -> dict[str, tuple[str, str, str, int]]:
        """id -> (subject, scene, seq, object class)."""
        if self._ids is None:
            ids = {}
            for subj, scene, seq in self.h2o.sequences():
                frames = self.h2o.frames(subj, scene, seq, H2O_EGO_CAMERA)
                cls, _ = self.h2o.read_obj_poses(subj, scene, seq, H2O_EGO_CAMERA, frames)
                for c in sorted(set(cls.tolist()) - {0}):
                    ids[h2o_sequence_id(subj, scene, seq, H2O_OBJECT_NAMES[c])] = (subj, scene, seq, int(c))
            self._ids = dict(sorted(ids.items()))
        return self._ids

    def subjects(self) -> list[str]:
        """Subject folders, as :meth:`H2ORoot.subjects`."""
        return self.h2o.subjects()

    def sequences(self, subject: Optional[str] = None) -> list[str]:
        """Sorted ``"sid/seq"`` ids (see the class).

        Args:
            subject: restrict to one subject.
        """
        return [k for k, v in self._index().items() if subject is None or v[0] == subject]

    def h2o_sequence(self, sid_seq: str) -> tuple[str, str, str, int]:
        """``(subject, scene, seq, object class)`` of an id.

        Raises:
            KeyError: no such id.
        """
        if sid_seq not in self._index():
            raise KeyError(f"{sid_seq!r} is not a sequence of {self.root} (ids: subject/<object>_<scene>_<seq>)")
        return self._index()[sid_seq]

    def sequence(self, sid: str, seq: str) -> SequenceData:
        """The grasps of id ``sid/seq`` as :class:`SequenceData` (H2O world frame, labels of
        ``cam4``, every camera folder; ``name`` is the id's ``seq``)."""
        subj, scene, num, cls = self.h2o_sequence(f"{sid}/{seq}")
        data = self.h2o.sequence(subj, scene, num, self.mano_layers(torch.float64), object_class=cls)
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
        """``{name: ObjectTemplate}`` of the objects the ids show (rigid, metres, cached without
        texture; ``load_texture`` reads the texture too)."""
        names = sorted({seq.split("/", 1)[1].split("_", 1)[0] for seq in self._index()})
        if load_texture:
            return {n: load_h2o_object(self.object_mesh_dir, n) for n in names}
        if self._templates is None:
            self._templates = {n: load_h2o_object(self.object_mesh_dir, n, load_texture=False) for n in names}
        return self._templates

    def object_layer(self) -> Any:
        """An :class:`ArticulatedObjectLayer` of the templates (θ has no effect on rigid objects)."""
        return ArticulatedObjectLayer(self.object_templates(load_texture=False))
