"""Reader of the real H2O layout::

    <root>/subjectN/<scene>/<seq>/camK/<modality>/<frame:06d>.<ext>
    <root>/subjectN/<scene>/<seq>/camK/cam_intrinsics.txt

with scenes ``h1 h2 k1 k2 o1 o2``, integer sequences, ``cam0``..``cam3`` static third-person
cameras and ``cam4`` the head-mounted (egocentric) one. Text formats are parsed in
:mod:`hogsa_loader.assets.h2o_io`; :meth:`H2ORoot.sequence` returns the
dataset-independent :class:`SequenceData`. All arrays are float64.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Optional, Sequence, TypeVar, Union

import cv2
import numpy as np
import torch

from hogsa_loader.assets.h2o_io import (
    H2O_CAM_INTRINSICS_FILE,
    H2O_EGO_CAMERA,
    H2O_SIDES,
    H2OHandJoints,
    H2OIntrinsics,
    H2OManoHand,
    H2OManoLabels,
    parse_h2o_action_label,
    parse_h2o_cam_intrinsics,
    parse_h2o_cam_pose,
    parse_h2o_hand_pose,
    parse_h2o_hand_pose_mano,
    parse_h2o_obj_pose,
    parse_h2o_obj_pose_rt_strict,
    parse_h2o_verb_label,
    read_h2o_text,
)
from hogsa_loader.assets.hands.mano import MANOLayer
from hogsa_loader.assets.hands.mano_io import ManoModelData, load_mano
from hogsa_loader.assets.objects.rigid import H2O_OBJECT_NAMES
from hogsa_loader.assets.types import CameraTrack, HandTrack, ObjectTrack, SequenceData
from hogsa_loader.errors import AssetError, PathLike
from hogsa_loader.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle

__all__ = [
    "H2ORoot",
    "MODALITY_FOLDERS",
    "ManoModels",
    "SeqId",
    "change_mano_frame",
    "h2o_mano_from_tracks",
    "h2o_mano_to_track",
    "mano_root_joint",
    "read_h2o_rgb",
]

#: Folder names accepted for each modality (the first is the one written).
MODALITY_FOLDERS: dict[str, tuple[str, ...]] = {
    "rgb": ("rgb",),
    "depth": ("depth",),
    "cam_pose": ("cam_pose",),
    "hand_pose": ("hand_pose",),
    "hand_pose_mano": ("hand_pose_mano", "hand_pose_MANO"),
    "obj_pose": ("obj_pose",),
    "obj_pose_rt": ("obj_pose_rt", "obj_pose_RT"),
    "action_label": ("action_label",),
    "verb_label": ("verb_label",),
}
_EXT = {"rgb": ".png", "depth": ".png"}
_FRAME_FILE = re.compile(r"(\d{6,})\.(txt|png)")
#: subject folders: ``subjectN`` (download mode ``all``), ``subjectN_ego`` (``ego``: cam4 only)
#: or ``subjectN_pose`` (``pose``: no RGB-D)
_SUBJECT = re.compile(r"subject(\d+)(?:_ego|_pose)?")
_CAM = re.compile(r"cam(\d+)")

#: A MANO model of one side: a layer (its shape blend shapes are used as configured,
#: e.g. with ``fix_left_shapedirs``) or the raw model arrays.
ModelLike = Union[MANOLayer, ManoModelData]
#: ``{"right": model, "left": model}`` or a folder holding ``MANO_RIGHT/LEFT.pkl``.
ManoModels = Union[PathLike, Mapping[str, ModelLike]]
#: A sequence folder name: ``0`` or ``"0"``.
SeqId = Union[int, str]
_T = TypeVar("_T")


# ----------------------------------------------------------------------------------------
# MANO helpers: root joint, frame change, flat-mean conversion
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _HandModel:
    """The few model arrays the conversions need (float64)."""

    side: str
    hands_mean: np.ndarray  # (45,)
    j0_template: np.ndarray  # (3,) root joint of the template
    j0_dirs: np.ndarray  # (3, 10) root-joint shape blend: J0(β) = j0_template + j0_dirs β


def _hand_model(model: ModelLike, side: str) -> _HandModel:
    if isinstance(model, MANOLayer):
        data = model.data
        if model.num_betas < 10:
            raise ValueError(f"{side} MANO layer uses {model.num_betas} betas; H2O labels hold 10")
        v_template = model.v_template.detach().double().cpu().numpy()
        shapedirs = model.shapedirs.detach().double().cpu().numpy()[:, :, :10]
        j_reg0 = model.J_regressor.detach().double().cpu().numpy()[0]
    elif isinstance(model, ManoModelData):
        data = model
        if model.num_betas < 10:
            raise ValueError(f"{side} MANO model {model.source!r} has {model.num_betas} betas; H2O labels hold 10")
        v_template, shapedirs, j_reg0 = model.v_template, model.shapedirs[:, :, :10], model.J_regressor[0]
    else:
        raise TypeError(f"{side} MANO model must be a MANOLayer or ManoModelData, got {type(model).__name__}")
    if data.side != side:
        raise ValueError(f"the model given for the {side} hand is a {data.side} hand ({data.source or 'in memory'})")
    return _HandModel(
        side=side,
        hands_mean=np.asarray(data.hands_mean, dtype=np.float64).reshape(45),
        j0_template=j_reg0 @ v_template,
        j0_dirs=np.einsum("v,vcs->cs", j_reg0, shapedirs),
    )


def _check_track_layers(mano_layers: Mapping[str, Any]) -> None:
    """The tracks are converted to ARCTIC's convention (articulation minus ``hands_mean``, 45
    axis-angle values): layers given with them must pose that way, or every finger is off by
    ``hands_mean`` without any error."""
    for side, layer in mano_layers.items():
        if isinstance(layer, MANOLayer) and (layer.flat_hand_mean or layer.use_pca):
            raise ValueError(
                f"{side} MANO layer has flat_hand_mean={layer.flat_hand_mean}, use_pca={layer.use_pca}; "
                "H2O tracks are converted for MANOLayer(..., flat_hand_mean=False, use_pca=False)"
            )


def _hand_models(mano_layers: ManoModels) -> dict[str, _HandModel]:
    if isinstance(mano_layers, Mapping):
        missing = [s for s in H2O_SIDES if s not in mano_layers]
        if missing:
            raise ValueError(f"mano_layers needs 'left' and 'right' entries, missing {missing}")
        return {s: _hand_model(mano_layers[s], s) for s in H2O_SIDES}
    return {s: _hand_model(load_mano(mano_layers, side=s), s) for s in H2O_SIDES}


def mano_root_joint(model: ModelLike, betas: np.ndarray) -> np.ndarray:
    """Root joint J0 of the rest pose (before ``transl``): ``J_regressor[0] @ v_shaped(β)``.

    Args:
        model: MANO layer or model of the hand.
        betas: (..., 10) shape.

    Returns:
        (..., 3) float64, metres.
    """
    return _root_joint(_as_hand_model(model), betas)


def _as_hand_model(model: Union[ModelLike, _HandModel]) -> _HandModel:
    if isinstance(model, _HandModel):
        return model
    if isinstance(model, MANOLayer):
        return _hand_model(model, model.data.side)
    if isinstance(model, ManoModelData):
        return _hand_model(model, model.side)
    raise TypeError(f"expected a MANOLayer or ManoModelData, got {type(model).__name__}")


def _root_joint(m: _HandModel, betas: np.ndarray) -> np.ndarray:
    return m.j0_template + np.asarray(betas, dtype=np.float64) @ m.j0_dirs.T


def _aa_to_mat(aa: np.ndarray) -> np.ndarray:
    return axis_angle_to_matrix(torch.from_numpy(np.ascontiguousarray(aa, dtype=np.float64))).numpy()


def _mat_to_aa(mat: np.ndarray) -> np.ndarray:
    return matrix_to_axis_angle(torch.from_numpy(np.ascontiguousarray(mat, dtype=np.float64))).numpy()


def _models_for(mano_layers: Union[ManoModels, Mapping[str, _HandModel]]) -> dict[str, _HandModel]:
    if isinstance(mano_layers, Mapping) and all(isinstance(v, _HandModel) for v in mano_layers.values()):
        return dict(mano_layers)  # type: ignore[arg-type]
    return _hand_models(mano_layers)  # type: ignore[arg-type]


def change_mano_frame(
    rot: np.ndarray,
    trans: np.ndarray,
    betas: np.ndarray,
    transform: np.ndarray,
    model: Union[ModelLike, _HandModel],
    out_betas: Optional[np.ndarray] = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Move MANO global parameters by a rigid transform ``p' = R p + T``.

    MANO rotates about the root joint J0(β), so ``rot' = R·R_g`` and
    ``trans' = R·(J0(β) + t) + T − J0(β')`` where β' = ``out_betas`` (default β): the
    posed hand with β moved by the transform equals the hand posed with ``rot'``,
    ``trans'`` and β (exactly), or with β' up to the shape change (root joint exact).

    Args:
        rot: (F, 3) global orientation (axis-angle).
        trans: (F, 3) translation (m).
        betas: (F, 10) betas the parameters were made with.
        transform: (F, 4, 4) or (4, 4) rigid transform from the parameters' frame.
        model: the hand's MANO layer / model (left model for left hands).
        out_betas: (F, 10) or (10,) betas the result will be posed with.

    Returns:
        ``(rot', trans')``, (F, 3) each, float64. The finger pose does not change.
    """
    m = _as_hand_model(model)
    rot = np.asarray(rot, dtype=np.float64).reshape(-1, 3)
    trans = np.asarray(trans, dtype=np.float64).reshape(-1, 3)
    F = rot.shape[0]
    M = np.broadcast_to(np.asarray(transform, dtype=np.float64), (F, 4, 4))
    R, T = M[:, :3, :3], M[:, :3, 3]
    j0 = _root_joint(m, np.broadcast_to(np.asarray(betas, dtype=np.float64), (F, 10)))
    if out_betas is None:
        j0_out = j0
    else:
        j0_out = _root_joint(m, np.broadcast_to(np.asarray(out_betas, dtype=np.float64), (F, 10)))
    new_rot = _mat_to_aa(R @ _aa_to_mat(rot))
    new_trans = np.einsum("fij,fj->fi", R, j0 + trans) + T - j0_out
    return new_rot, new_trans


def h2o_mano_to_track(hand: H2OManoHand, transform: np.ndarray, model: Union[ModelLike, _HandModel]) -> HandTrack:
    """Turn one hand's stored labels into a :class:`HandTrack` in another frame.

    Args:
        hand: labels as stored (``flat_hand_mean=True``, frame of their camera folder).
        transform: (F, 4, 4) or (4, 4) from the labels' camera frame to the output frame.
        model: MANO layer / model of this side (gives ``hands_mean`` and J0).

    Returns:
        :class:`HandTrack` with finger pose relative to ``hands_mean``, betas = median of the
        valid frames' betas (zeros if none), root joint preserved per frame, zeros at
        invalid frames.
    """
    m = _as_hand_model(model)
    valid = np.asarray(hand.valid, dtype=bool)
    betas = np.median(hand.betas[valid], axis=0) if valid.any() else np.zeros(10)
    rot, trans = change_mano_frame(hand.pose[:, :3], hand.trans, hand.betas, transform, m, out_betas=betas)
    pose = hand.pose[:, 3:] - m.hands_mean
    for arr in (rot, trans, pose):
        arr[~valid] = 0.0
    return HandTrack(rot=rot, pose=pose, trans=trans, betas=np.asarray(betas, dtype=np.float64), valid=valid.copy())


def h2o_mano_from_tracks(
    left: HandTrack, right: HandTrack, transform: np.ndarray, mano_layers: ManoModels
) -> H2OManoLabels:
    """Inverse of :func:`h2o_mano_to_track` for both hands: H2O labels of one camera.

    Args:
        left, right: hand tracks (finger pose relative to the mean, ``flat_hand_mean=False``).
        transform: (F, 4, 4) or (4, 4) from the tracks' frame to the camera frame
            (``world2cam`` of that camera when the tracks are in the world frame).
        mano_layers: models of both sides.

    Returns:
        :class:`H2OManoLabels` (``flat_hand_mean=True``, the track's betas repeated per
        frame, invalid frames written as zeros with valid = 0).
    """
    models = _models_for(mano_layers)
    out = {}
    for side, track in (("left", left), ("right", right)):
        m = models[side]
        valid = np.asarray(track.valid, dtype=bool)
        F = valid.shape[0]
        betas = np.broadcast_to(np.asarray(track.betas, dtype=np.float64), (F, 10)).copy()
        rot, trans = change_mano_frame(track.rot, track.trans, betas, transform, m)
        pose = np.concatenate([rot, np.asarray(track.pose, dtype=np.float64) + m.hands_mean], axis=1)
        pose[~valid] = 0.0
        trans[~valid] = 0.0
        betas[~valid] = 0.0
        out[side] = H2OManoHand(valid=valid.copy(), trans=trans, pose=pose, betas=betas)
    return H2OManoLabels(left=out["left"], right=out["right"])


# ----------------------------------------------------------------------------------------
# Reading
# ----------------------------------------------------------------------------------------
def _num_key(name: str) -> tuple[int, str]:
    digits = re.sub(r"\D", "", name)
    return (int(digits) if digits else -1, name)


def _subdirs(path: Path) -> list[str]:
    try:
        return sorted((e.name for e in os.scandir(path) if e.is_dir() and not e.name.startswith(".")), key=_num_key)
    except OSError as exc:
        raise AssetError(path, f"cannot list folder ({exc})") from None


def _parse_world(world: str) -> Optional[int]:
    """``"world"`` -> None, ``"camK"`` -> K."""
    if world == "world":
        return None
    m = _CAM.fullmatch(world) if isinstance(world, str) else None
    if m is None:
        raise ValueError(f"world must be 'world' or 'cam<K>', got {world!r}")
    return int(m.group(1))


def _class_records(
    recs: Sequence[tuple[int, np.ndarray]], item_shape: tuple[int, ...]
) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame ``(class id, array)`` records → class ids (F,) int64 and arrays (F, *item_shape)."""
    cls = np.array([c for c, _ in recs], dtype=np.int64)
    arrays = np.stack([a for _, a in recs]) if recs else np.zeros((0, *item_shape))
    return cls, arrays


class H2ORoot:
    """An H2O dataset root (the folder holding ``subject1``, ``subject2``...).

    Conventions of :meth:`sequence`:

    * **Label camera.** MANO and object labels are stored in every camera folder, each
      in that camera's frame. They are read from one camera folder, ``label_cam``
      (default ``4``, the egocentric view that HACO and the official pose lists use).
      ``hand_pose_mano`` / ``obj_pose_rt`` folders are found under these lower-case
      names or the README's ``hand_pose_MANO`` / ``obj_pose_RT``.
    * **Output frame** (``world``): ``"world"`` moves labels with the label camera's
      ``cam_pose`` (camera-to-world, per frame) into H2O's world frame, like
      h2oplayer. ``"camK"`` expresses everything in camera K's frame instead (for the
      moving ``cam4`` this frame changes every frame; camera K then has identity
      extrinsics).
    * **MANO frame change** rotates about the root joint J0 (depends on betas), not
      about the origin: global rotation ``R·R_g``, translation ``R·(J0 + t) + T − J0``
      (:func:`change_mano_frame`).
    * **Mean pose.** H2O poses use ``flat_hand_mean=True``; :class:`HandTrack` wants
      the finger pose relative to the MANO mean, so ``pose_rel = pose_flat −
      hands_mean`` of the given model of each side.
    * **Betas.** H2O stores betas per frame; :class:`HandTrack` has one vector per
      sequence: the per-hand **median over valid frames** (zeros when a hand is never
      valid). The translation keeps the root joint exactly where the per-frame betas
      put it (``trans = R·(J0(β_f) + t) + T − J0(β_median)``); other joints move by
      the (small) shape difference. :meth:`read_mano` gives the exact per-frame labels.
    * **Validity.** Per frame and hand from the ``valid`` flag; invalid frames hold
      zeros in ``rot``/``pose``/``trans``. The object is invalid where the class id is
      0 (its ``rot``/``trans`` are zeros there); ``arti`` is always 0 (H2O objects are
      rigid). The object name comes from the class id (``H2O_OBJECT_NAMES``).
    * **Cameras.** Every ``camK`` folder (or the ones asked for) with per-frame
      ``world2cam`` = inverse of ``cam_pose`` (composed with the output frame), ``K``
      from ``cam_intrinsics.txt`` (static, repeated per frame), no distortion,
      ``egocentric`` for ``cam4``. ``image_paths`` point to ``rgb/<frame>.png`` (None
      where missing).
    * **Frames** are the files of the label camera's ``hand_pose_mano`` folder; every
      other per-frame file read must exist for each of them.

    Args:
        root: dataset root.

    Raises:
        AssetError: the folder does not exist.
    """

    def __init__(self, root: PathLike) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise AssetError(self.root, "H2O root folder not found")

    # -- listing ---------------------------------------------------------------------------
    def subjects(self) -> list[str]:
        """Subject folders (``subjectN``, or ``subjectN_ego`` / ``subjectN_pose`` of the
        ``ego`` / ``pose`` downloads), in numeric order; one per subject: where several
        downloads of a subject are unpacked side by side, the fullest (``subjectN``, then
        ``_ego``, then ``_pose``: no RGB-D) is listed, so sequences are not counted twice."""
        best: dict[int, tuple[int, str]] = {}
        for d in _subdirs(self.root):
            m = _SUBJECT.fullmatch(d)
            if m:
                num, rank = int(m.group(1)), 2 if d.endswith("_pose") else 1 if d.endswith("_ego") else 0
                if num not in best or rank < best[num][0]:
                    best[num] = (rank, d)
        return [best[n][1] for n in sorted(best)]

    def sequences(self, subject: Optional[str] = None) -> list[tuple[str, str, str]]:
        """All ``(subject, scene, seq)`` with at least one ``camK`` folder.

        Args:
            subject: restrict to one subject.
        """
        out = []
        for subj in [subject] if subject is not None else self.subjects():
            sdir = self._dir(self.root / subj, "subject folder not found")
            for scene in _subdirs(sdir):
                for seq in _subdirs(sdir / scene):
                    if seq.isdigit() and any(_CAM.fullmatch(c) for c in _subdirs(sdir / scene / seq)):
                        out.append((subj, scene, seq))
        return out

    def sequence_dir(self, subject: str, scene: str, seq: SeqId) -> Path:
        """``<root>/subject/scene/seq`` (must exist)."""
        return self._dir(self.root / subject / scene / str(seq), "sequence folder not found")

    def cameras(self, subject: str, scene: str, seq: SeqId) -> list[int]:
        """Camera indices K of the ``camK`` folders of a sequence, sorted."""
        d = self.sequence_dir(subject, scene, seq)
        return sorted(int(m.group(1)) for m in map(_CAM.fullmatch, _subdirs(d)) if m)

    def camera_dir(self, subject: str, scene: str, seq: SeqId, cam: int) -> Path:
        """``.../camK`` (must exist)."""
        return self._dir(self.sequence_dir(subject, scene, seq) / f"cam{int(cam)}", "camera folder not found")

    def modality_dir(self, subject: str, scene: str, seq: SeqId, cam: int, modality: str) -> Path:
        """The folder of one modality, accepting the README's upper-case spellings.

        Raises:
            AssetError: no such folder, or two spellings present at once.
        """
        if modality not in MODALITY_FOLDERS:
            raise ValueError(f"unknown H2O modality {modality!r}; known: {sorted(MODALITY_FOLDERS)}")
        cdir = self.camera_dir(subject, scene, seq, cam)
        names = set(_subdirs(cdir))
        found = [n for n in MODALITY_FOLDERS[modality] if n in names]
        if not found:
            raise AssetError(cdir / MODALITY_FOLDERS[modality][0], f"{modality} folder not found")
        if len(found) > 1:
            raise AssetError(cdir, f"both {found[0]}/ and {found[1]}/ exist; keep one")
        return cdir / found[0]

    def frames(
        self, subject: str, scene: str, seq: SeqId, cam: int = H2O_EGO_CAMERA, modality: str = "hand_pose_mano"
    ) -> list[int]:
        """Frame numbers present in one modality folder (files ``NNNNNN.txt`` / ``.png``), sorted."""
        d = self.modality_dir(subject, scene, seq, cam, modality)
        ext = _EXT.get(modality, ".txt")[1:]
        try:
            names = [e.name for e in os.scandir(d) if e.is_file()]
        except OSError as exc:
            raise AssetError(d, f"cannot list folder ({exc})") from None
        return sorted(int(m.group(1)) for m in map(_FRAME_FILE.fullmatch, names) if m and m.group(2) == ext)

    def frame_path(self, subject: str, scene: str, seq: SeqId, cam: int, modality: str, frame: int) -> Path:
        """Path of one per-frame file (not checked for existence)."""
        d = self.modality_dir(subject, scene, seq, cam, modality)
        return d / f"{int(frame):06d}{_EXT.get(modality, '.txt')}"

    # -- per-camera readers ------------------------------------------------------------------
    def read_intrinsics(self, subject: str, scene: str, seq: SeqId, cam: int) -> H2OIntrinsics:
        """Parse ``camK/cam_intrinsics.txt``."""
        p = self.camera_dir(subject, scene, seq, cam) / H2O_CAM_INTRINSICS_FILE
        return parse_h2o_cam_intrinsics(read_h2o_text(p), path=p)

    def _read_frames(
        self,
        subject: str,
        scene: str,
        seq: SeqId,
        cam: int,
        modality: str,
        frames: Sequence[int],
        parse: Callable[[str, Path], _T],
    ) -> list[_T]:
        d = self.modality_dir(subject, scene, seq, cam, modality)
        out = []
        for f in frames:
            p = d / f"{int(f):06d}.txt"
            out.append(parse(read_h2o_text(p), p))
        return out

    def read_cam_poses(self, subject: str, scene: str, seq: SeqId, cam: int, frames: Sequence[int]) -> np.ndarray:
        """(F, 4, 4) camera-to-world matrices of the given frames."""
        mats = self._read_frames(subject, scene, seq, cam, "cam_pose", frames, parse_h2o_cam_pose)
        return np.stack(mats) if mats else np.zeros((0, 4, 4))

    def read_mano(self, subject: str, scene: str, seq: SeqId, cam: int, frames: Sequence[int]) -> H2OManoLabels:
        """Stored MANO labels (flat mean, per-frame betas, camera-K frame) of the given frames."""
        rows = self._read_frames(
            subject,
            scene,
            seq,
            cam,
            "hand_pose_mano",
            frames,
            lambda text, path: parse_h2o_hand_pose_mano(text, path).to_array()[0],
        )
        return H2OManoLabels.from_array(np.stack(rows) if rows else np.zeros((0, 124)))

    def read_obj_poses(
        self, subject: str, scene: str, seq: SeqId, cam: int, frames: Sequence[int]
    ) -> tuple[np.ndarray, np.ndarray]:
        """``obj_pose_rt`` of the given frames: class ids (F,) int64 and (F, 4, 4) object-to-camera."""
        recs = self._read_frames(subject, scene, seq, cam, "obj_pose_rt", frames, parse_h2o_obj_pose_rt_strict)
        return _class_records(recs, (4, 4))

    def read_hand_joints(self, subject: str, scene: str, seq: SeqId, cam: int, frames: Sequence[int]) -> H2OHandJoints:
        """``hand_pose`` of the given frames: valid (F, 2) and joints (F, 2, 21, 3), left first."""
        recs = self._read_frames(subject, scene, seq, cam, "hand_pose", frames, parse_h2o_hand_pose)
        valid = np.stack([r.valid for r in recs]) if recs else np.zeros((0, 2), dtype=bool)
        joints = np.stack([r.joints for r in recs]) if recs else np.zeros((0, 2, 21, 3))
        return H2OHandJoints(valid=valid, joints=joints)

    def read_obj_boxes(
        self, subject: str, scene: str, seq: SeqId, cam: int, frames: Sequence[int]
    ) -> tuple[np.ndarray, np.ndarray]:
        """``obj_pose`` of the given frames: class ids (F,) and box points (F, 21, 3)."""
        recs = self._read_frames(subject, scene, seq, cam, "obj_pose", frames, parse_h2o_obj_pose)
        return _class_records(recs, (21, 3))

    def read_labels(
        self, subject: str, scene: str, seq: SeqId, cam: int, frames: Sequence[int], kind: str = "action_label"
    ) -> np.ndarray:
        """``action_label`` (cam4 only) or ``verb_label`` of the given frames, (F,) int64."""
        parsers = {"action_label": parse_h2o_action_label, "verb_label": parse_h2o_verb_label}
        if kind not in parsers:
            raise ValueError(f"kind must be 'action_label' or 'verb_label', got {kind!r}")
        vals = self._read_frames(subject, scene, seq, cam, kind, frames, parsers[kind])
        return np.array(vals, dtype=np.int64)

    # -- the sequence ------------------------------------------------------------------------
    def sequence(
        self,
        subject: str,
        scene: str,
        seq: SeqId,
        mano_layers: ManoModels,
        world: str = "world",
        label_cam: int = H2O_EGO_CAMERA,
        cameras: Optional[Sequence[int]] = None,
        frames: Optional[Sequence[int]] = None,
        object_class: Optional[int] = None,
    ) -> SequenceData:
        """Read one sequence as :class:`SequenceData` (conventions on :class:`H2ORoot`).

        Args:
            subject, scene, seq: e.g. ``"subject1", "h1", 0``.
            mano_layers: ``{"left": ..., "right": ...}`` MANO layers or models, or a folder
                with ``MANO_LEFT/RIGHT.pkl`` (gives ``hands_mean`` and the root joint).
            world: ``"world"`` (H2O world via ``cam_pose``) or ``"camK"`` (camera K's frame).
            label_cam: camera folder the MANO and object labels are read from.
            cameras: camera indices to include (default: every ``camK`` folder).
            frames: frame numbers to read (default: those of the label camera's
                ``hand_pose_mano`` folder).
            object_class: the object to track (1..8). Default: the single non-zero class
                of the sequence (several classes raise). When given, frames showing
                another class are marked invalid for the object.

        Returns:
            :class:`SequenceData` with ``dataset="h2o"``, ``name="<scene>/<seq>"``.

        Raises:
            AssetError: a folder or file is missing or malformed (message names it), or
                the sequence shows more than one object class and ``object_class`` is None.
        """
        if isinstance(mano_layers, Mapping):
            _check_track_layers(mano_layers)
        models = _hand_models(mano_layers)
        target = _parse_world(world)
        seq = str(seq)
        cams = self.cameras(subject, scene, seq) if cameras is None else sorted({int(c) for c in cameras})
        frame_ids = self._sequence_frames(subject, scene, seq, label_cam, frames)
        c2w, out2world, label_to_out = self._output_frames(subject, scene, seq, cams, label_cam, target, frame_ids)

        mano = self.read_mano(subject, scene, seq, label_cam, frame_ids)
        tracks = {s: h2o_mano_to_track(mano.hand(s), label_to_out, models[s]) for s in H2O_SIDES}
        obj = self._object_track(subject, scene, seq, label_cam, frame_ids, label_to_out, object_class)
        camera_tracks = {c: self._camera_track(subject, scene, seq, c, c2w, out2world, target) for c in cams}
        image_paths = {c: self._image_paths(subject, scene, seq, c, frame_ids) for c in cams}
        return SequenceData(
            dataset="h2o",
            subject=subject,
            name=f"{scene}/{seq}",
            right=tracks["right"],
            left=tracks["left"],
            object=obj,
            cameras=camera_tracks,
            frame_ids=np.asarray(frame_ids, dtype=np.int64),
            image_paths=image_paths,
            root=self.root,
        )

    def _sequence_frames(
        self, subject: str, scene: str, seq: str, label_cam: int, frames: Optional[Sequence[int]]
    ) -> list[int]:
        """The frame numbers to read: ``frames``, or those of the label camera's MANO folder."""
        frame_ids = self.frames(subject, scene, seq, label_cam) if frames is None else [int(f) for f in frames]
        if not frame_ids:
            raise AssetError(
                self.modality_dir(subject, scene, seq, label_cam, "hand_pose_mano"), "no frame files (NNNNNN.txt)"
            )
        return frame_ids

    def _output_frames(
        self,
        subject: str,
        scene: str,
        seq: str,
        cams: Sequence[int],
        label_cam: int,
        target: Optional[int],
        frame_ids: Sequence[int],
    ) -> tuple[dict[int, np.ndarray], np.ndarray, np.ndarray]:
        """Per-frame (F, 4, 4) transforms between the cameras, the world and the output frame.

        Returns:
            ``c2w`` camera-to-world of every camera needed, ``out2world`` output frame →
            world (identity for ``"world"``, ``cam_pose`` of camera K for ``"camK"``), and
            ``label_to_out`` label camera → output frame.
        """
        needed = {*cams, label_cam} | ({target} if target is not None else set())
        c2w = {c: self.read_cam_poses(subject, scene, seq, c, frame_ids) for c in sorted(needed)}
        out2world = np.broadcast_to(np.eye(4), (len(frame_ids), 4, 4)) if target is None else c2w[target]
        if target == label_cam:
            label_to_out = np.repeat(np.eye(4)[None], len(frame_ids), axis=0)
        else:
            label_to_out = np.linalg.inv(out2world) @ c2w[label_cam]
        return c2w, out2world, label_to_out

    def _object_class(
        self, subject: str, scene: str, seq: str, label_cam: int, cls: np.ndarray, object_class: Optional[int]
    ) -> list[int]:
        """The tracked object class as a one-element list (empty when no frame shows an object)."""
        classes = sorted(set(cls[cls > 0].tolist()))
        if object_class is not None:
            if not 1 <= int(object_class) < len(H2O_OBJECT_NAMES):
                raise ValueError(f"object_class must be in 1..{len(H2O_OBJECT_NAMES) - 1}, got {object_class}")
            return [int(object_class)]
        if len(classes) > 1:
            raise AssetError(
                self.modality_dir(subject, scene, seq, label_cam, "obj_pose_rt"),
                f"sequence shows several object classes {[H2O_OBJECT_NAMES[c] for c in classes]}; "
                "pass object_class to pick one",
            )
        return classes

    def _object_track(
        self,
        subject: str,
        scene: str,
        seq: str,
        label_cam: int,
        frame_ids: Sequence[int],
        label_to_out: np.ndarray,
        object_class: Optional[int],
    ) -> ObjectTrack:
        """The object's pose (F,) in the output frame; zeros and invalid where another class shows."""
        cls, obj_cam = self.read_obj_poses(subject, scene, seq, label_cam, frame_ids)
        classes = self._object_class(subject, scene, seq, label_cam, cls, object_class)
        obj_valid = (cls > 0) & (cls == (classes[0] if classes else 0))
        obj_out = label_to_out @ obj_cam
        obj_rot = _mat_to_aa(obj_out[:, :3, :3])
        obj_trans = obj_out[:, :3, 3].copy()
        obj_rot[~obj_valid] = 0.0
        obj_trans[~obj_valid] = 0.0
        return ObjectTrack(
            name=H2O_OBJECT_NAMES[classes[0] if classes else 0],
            arti=np.zeros(len(frame_ids)),
            rot=obj_rot,
            trans=obj_trans,
            valid=obj_valid,
        )

    def _camera_track(
        self,
        subject: str,
        scene: str,
        seq: str,
        cam: int,
        c2w: Mapping[int, np.ndarray],
        out2world: np.ndarray,
        target: Optional[int],
    ) -> CameraTrack:
        """Camera ``cam`` seen from the output frame: (F, 4, 4) ``world2cam`` and (F, 3, 3) ``K``."""
        intr = self.read_intrinsics(subject, scene, seq, cam)
        n = len(out2world)
        if target == cam:
            w2c = np.repeat(np.eye(4)[None], n, axis=0)
        else:
            w2c = np.linalg.inv(c2w[cam]) @ out2world
        return CameraTrack(
            view=cam,
            world2cam=w2c,
            K=np.repeat(intr.K[None], n, axis=0),
            width=intr.width,
            height=intr.height,
            dist=None,
            egocentric=cam == H2O_EGO_CAMERA,
        )

    def _image_paths(self, subject: str, scene: str, seq: str, cam: int, frames: Sequence[int]) -> list[Optional[Path]]:
        try:
            d = self.modality_dir(subject, scene, seq, cam, "rgb")
        except AssetError:
            return [None] * len(frames)
        paths = [d / f"{int(f):06d}.png" for f in frames]
        return [p if p.is_file() else None for p in paths]

    @staticmethod
    def _dir(path: Path, problem: str) -> Path:
        if not path.is_dir():
            raise AssetError(path, problem)
        return path


def read_h2o_rgb(path: PathLike, expected_size: Optional[tuple[int, int]] = None) -> np.ndarray:
    """Read an ``rgb/`` PNG as (H, W, 3) uint8 RGB.

    Args:
        path: the image.
        expected_size: (width, height) to check, e.g. from ``cam_intrinsics.txt``.

    Raises:
        AssetError: missing or undecodable file, or a size other than ``expected_size``.
    """
    p = Path(path)
    if not p.is_file():
        raise AssetError(p, "image file is missing")
    img = cv2.imread(str(p), cv2.IMREAD_COLOR)
    if img is None:
        raise AssetError(p, "cannot decode image")
    if expected_size is not None and (img.shape[1], img.shape[0]) != tuple(expected_size):
        raise AssetError(p, f"image is {img.shape[1]}x{img.shape[0]}, expected {expected_size[0]}x{expected_size[1]}")
    return np.ascontiguousarray(img[:, :, ::-1])
