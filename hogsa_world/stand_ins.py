"""What a world holds where ARCTIC has body (SMPL-X) data, and the record of it.

The subjects of a generated world have hands but no body. ARCTIC's files still carry
SMPL-X fields, so a world writes them with ARCTIC's keys and shapes, filled with NaN
(float32): "undefined", never a posed body. ARCTIC's own split check skips NaN in any key
naming ``smplx`` (src/arctic/split.py ``sanity_check_annot``), and its dataset and training
code never read these keys (src/datasets/arctic_dataset.py reads the MANO, object and
camera keys only).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable

import numpy as np

from hogsa_loader.assets.arctic import read_npy
from hogsa_loader.errors import AssetError, PathLike
from hogsa_loader.io.atomic import atomic_open

__all__ = [
    "SMPLX_PARAMS",
    "SMPLX_JOINTS",
    "SPLIT_VIEWS",
    "NOT_PROVIDED",
    "smplx_raw",
    "smplx_split_keys",
    "add_split_stand_ins",
    "record",
]

#: SMPL-X parameters of ARCTIC's ``.smplx.npy`` and their widths.
SMPLX_PARAMS: dict[str, int] = {
    "transl": 3,
    "global_orient": 3,
    "body_pose": 63,
    "jaw_pose": 3,
    "leye_pose": 3,
    "reye_pose": 3,
    "left_hand_pose": 45,
    "right_hand_pose": 45,
}
#: Joints SMPL-X returns in ARCTIC's processing.
SMPLX_JOINTS = 127
#: Views of the processed ``cam_coord`` / ``2d`` points (ego, 8 allocentric, distorted ego).
SPLIT_VIEWS = 10

_NO_BODY = "the world's subjects have hands but no body model, so there is no SMPL-X pose to give"

#: ARCTIC paths a world leaves out, and why.
NOT_PROVIDED: tuple[dict[str, str], ...] = (
    {
        "path": "body_models/smplx/SMPLX_{MALE,FEMALE,NEUTRAL}.npz",
        "reason": "SMPL-X is licensed and cannot be downloaded or fabricated here; ARCTIC opens it only in its "
        "sequence processing (scripts_data/process_seqs.py, common/body_models.py build_subject_smplx / "
        "construct_layers) and visualiser, not on the dataset or training path, and a world ships its "
        "processed splits",
    },
    {
        "path": "arctic_data/data/meta/subject_vtemplates/<sid>.obj",
        "reason": "SMPL-X template meshes of the subjects, opened only with the SMPL-X model above; " + _NO_BODY,
    },
)


def smplx_raw(num_frames: int) -> dict[str, np.ndarray]:
    """``.smplx.npy`` content: ``{name: (F, width) float32 NaN}``."""
    return {k: np.full((num_frames, w), np.nan, dtype=np.float32) for k, w in SMPLX_PARAMS.items()}


def smplx_split_keys(num_frames: int) -> dict[str, dict[str, np.ndarray]]:
    """Split entries: ``{"cam_coord": {"joints.smplx": (F,10,127,3)}, "2d": {"joints.smplx":
    (F,10,127,2)}, "params": {"smplx_<name>": (F, width)}}``, float32 NaN."""
    shape = (num_frames, SPLIT_VIEWS, SMPLX_JOINTS)
    return {
        "cam_coord": {"joints.smplx": np.full(shape + (3,), np.nan, dtype=np.float32)},
        "2d": {"joints.smplx": np.full(shape + (2,), np.nan, dtype=np.float32)},
        "params": {f"smplx_{k}": v for k, v in smplx_raw(num_frames).items()},
    }


def _add_to_sequence(seq: dict[str, Any]) -> bool:
    """Add the missing stand-in keys to one split sequence; True if any was added."""
    added = False
    for group, arrays in smplx_split_keys(int(seq["params"]["rot_r"].shape[0])).items():
        for key, value in arrays.items():
            if key not in seq[group]:
                seq[group][key] = value
                added = True
    return added


def add_split_stand_ins(paths: Iterable[PathLike]) -> None:
    """Add the SMPL-X stand-in keys to processed split files (in place, atomically).

    Files that already hold every key are left untouched.
    """
    for path in map(Path, paths):
        data = read_npy(path)
        if not isinstance(data, dict) or not isinstance(data.get("data_dict"), dict):
            raise AssetError(path, "expected a split dict with 'data_dict'")
        changed = [_add_to_sequence(seq) for seq in data["data_dict"].values()]
        if any(changed):
            with atomic_open(path) as fh:
                np.save(fh, np.array(data, dtype=object), allow_pickle=True)


def record() -> dict[str, list[dict[str, Any]]]:
    """The ``stand_ins`` and ``not_provided`` fields of ``meta/hogsa_world.json``.

    * ``raw_seqs/<sid>/<seq>.smplx.npy``: ``{transl (F,3), global_orient (F,3), body_pose
      (F,63), jaw_pose (F,3), leye_pose (F,3), reye_pose (F,3), left_hand_pose (F,45),
      right_hand_pose (F,45)}``, all NaN.
    * ``splits/<p>_<split>.npy``: per sequence ``cam_coord["joints.smplx"]`` (F,10,127,3),
      ``2d["joints.smplx"]`` (F,10,127,2) and ``params["smplx_<name>"]`` for every raw key
      above, all NaN.

    Not written at all: the SMPL-X model files and the subjects' SMPL-X template meshes (see
    :data:`NOT_PROVIDED`); :func:`record` lists both in ``meta/hogsa_world.json``.
    """
    raw_keys = list(SMPLX_PARAMS)
    return {
        "stand_ins": [
            {
                "path": "arctic_data/data/raw_seqs/<sid>/<seq>.smplx.npy",
                "keys": raw_keys,
                "content": "float32 NaN with ARCTIC's shapes (F, width)",
                "reason": _NO_BODY + "; ARCTIC's processing opens the file (src/arctic/preprocess_dataset.py)",
            },
            {
                "path": "arctic_data/data/splits/<protocol>_<split>.npy",
                "keys": ["cam_coord/joints.smplx", "2d/joints.smplx"] + [f"params/smplx_{k}" for k in raw_keys],
                "content": f"float32 NaN, (F,{SPLIT_VIEWS},{SMPLX_JOINTS},3), (F,{SPLIT_VIEWS},{SMPLX_JOINTS},2), "
                "(F, width)",
                "reason": _NO_BODY + "; ARCTIC's split check skips NaN in SMPL-X keys and its dataset never reads them",
            },
        ],
        "not_provided": [dict(e) for e in NOT_PROVIDED],
    }
