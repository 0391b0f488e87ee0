"""Batched MANO hand layer (right and left) on top of :mod:`hogsa_loader.assets.hands.lbs`.

:class:`MANOLayer` follows ARCTIC's MANO conventions (listed on the class).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Union

import numpy as np
import torch
from torch import Tensor, nn

from hogsa_loader.assets.hands.lbs import Skinning, skin_template
from hogsa_loader.assets.hands.mano_io import ManoModelData, load_mano
from hogsa_loader.errors import PathLike

__all__ = ["MANOLayer", "ManoOutput", "NUM_MANO_JOINTS"]

#: Joints of MANO's kinematic tree (checked against each model file).
NUM_MANO_JOINTS = 16


@dataclass
class ManoOutput:
    """Result of :meth:`MANOLayer.forward`.

    Attributes:
        vertices: (B, V, 3) posed vertices (+ transl), metres.
        joints: (B, 21, 3) 16 MANO joints then 5 fingertips (thumb..pinky), metres.
        full_pose: (B, 48) axis-angle pose actually applied (mean added, PCA expanded).
        rot_mats: (B, 16, 3, 3) local joint rotations.
    """

    vertices: Tensor
    joints: Tensor
    full_pose: Tensor
    rot_mats: Tensor


class MANOLayer(nn.Module):
    """Differentiable, batched MANO layer.

    Conventions (ARCTIC's MANO):
    - pose = 3 global + 45 articulation axis-angle values; with ``flat_hand_mean=False`` the
      45 values are offsets from the model's ``hands_mean`` (ARCTIC's setting), with ``True`` a
      zero vector is the flat hand (H2O's setting).
    - PCA mode: ``hand_pose`` holds ``num_pca_comps`` coefficients of ``hands_components``.
    - Outputs are in metres. Joints: 16 MANO joints (wrist, index, middle, pinky, ring, thumb;
      3 each) followed by 5 fingertip vertices thumb, index, middle, ring, pinky = 21 joints.
    - The known left-MANO ``shapedirs[:, 0, :]`` sign issue (smplx issue #48: in the official
      left model the x component of the shape blend shapes is not mirrored) is left as in the
      file by default, as ARCTIC and smplx do; ``fix_left_shapedirs=True`` negates it.

    Args:
        model: a :class:`ManoModelData` or a path accepted by :func:`load_mano`.
        side: hand side when ``model`` is a folder path.
        use_pca: interpret ``hand_pose`` as PCA coefficients.
        num_pca_comps: number of PCA components used when ``use_pca``.
        flat_hand_mean: if False, add the model's ``hands_mean`` to the articulation.
        fix_left_shapedirs: negate ``shapedirs[:, 0, :]`` of a left model (see above).
        num_betas: number of shape coefficients used (<= those in the file).
        dtype: float32 or float64 buffers.
    """

    def __init__(
        self,
        model: Union[ManoModelData, PathLike],
        side: Optional[str] = None,
        use_pca: bool = False,
        num_pca_comps: int = 45,
        flat_hand_mean: bool = False,
        fix_left_shapedirs: bool = False,
        num_betas: int = 10,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        super().__init__()
        data = model if isinstance(model, ManoModelData) else load_mano(model, side=side)
        if data.num_joints != NUM_MANO_JOINTS:
            raise ValueError(f"{data.source}: MANO needs {NUM_MANO_JOINTS} joints, file has {data.num_joints}")
        if num_betas > data.num_betas:
            raise ValueError(f"{data.source}: asked for {num_betas} betas, file has {data.num_betas}")
        n_art = 3 * (NUM_MANO_JOINTS - 1)
        if use_pca and not 1 <= num_pca_comps <= data.hands_components.shape[0]:
            raise ValueError(f"num_pca_comps must be in [1, {data.hands_components.shape[0]}], got {num_pca_comps}")
        self.data = data
        self.side = data.side
        self.use_pca = use_pca
        self.num_pca_comps = num_pca_comps if use_pca else n_art
        self.flat_hand_mean = flat_hand_mean
        self.fix_left_shapedirs = fix_left_shapedirs and data.side == "left"
        self.num_betas = num_betas

        shapedirs = data.shapedirs[:, :, :num_betas].copy()
        if self.fix_left_shapedirs:
            shapedirs[:, 0, :] *= -1.0

        def buf(name: str, arr: np.ndarray, dt: torch.dtype = dtype) -> None:
            self.register_buffer(name, torch.as_tensor(np.ascontiguousarray(arr), dtype=dt), persistent=False)

        buf("v_template", data.v_template)
        buf("shapedirs", shapedirs)
        buf("posedirs", data.posedirs)
        buf("J_regressor", data.J_regressor)
        buf("lbs_weights", data.weights)
        buf("parents", data.parents, torch.long)
        buf("faces", data.faces, torch.long)
        buf("tip_ids", data.tip_vertex_ids, torch.long)
        buf("hand_components", data.hands_components[: self.num_pca_comps])
        mean = np.zeros(n_art) if flat_hand_mean else data.hands_mean
        buf("hand_mean", mean)

    @property
    def num_verts(self) -> int:
        return int(self.v_template.shape[0])

    def articulation(self, hand_pose: Tensor) -> Tensor:
        """Turn the user's ``hand_pose`` into the 45-D articulation applied (mean included).

        Args:
            hand_pose: (B, 45) axis-angle or (B, num_pca_comps) PCA coefficients.

        Returns:
            (B, 45) axis-angle articulation.
        """
        if self.use_pca:
            hand_pose = hand_pose @ self.hand_components
        return hand_pose + self.hand_mean

    def full_pose_and_betas(
        self,
        global_orient: Optional[Tensor] = None,
        hand_pose: Optional[Tensor] = None,
        betas: Optional[Tensor] = None,
        transl: Optional[Tensor] = None,
    ) -> tuple[Tensor, Tensor]:
        """Fill in defaults and expand the hand pose (mean pose, PCA).

        Args:
            global_orient, hand_pose, betas, transl: as :meth:`forward` (``transl`` only
                sets the batch size when it is the only argument given).

        Returns:
            full_pose: (B, 3 + 45) axis-angle, root first; betas: (B, num_betas).
        """
        given = [t for t in (global_orient, hand_pose, betas, transl) if t is not None]
        B = given[0].shape[0] if given else 1
        kw = dict(dtype=self.v_template.dtype, device=self.v_template.device)
        if global_orient is None:
            global_orient = torch.zeros(B, 3, **kw)
        if hand_pose is None:
            hand_pose = torch.zeros(B, self.num_pca_comps, **kw)
        if betas is None:
            betas = torch.zeros(B, self.num_betas, **kw)
        if hand_pose.shape[-1] != self.num_pca_comps:
            raise ValueError(f"hand_pose must have {self.num_pca_comps} values, got {tuple(hand_pose.shape)}")
        return torch.cat([global_orient, self.articulation(hand_pose)], dim=-1), betas

    def skin(self, full_pose: Tensor, betas: Tensor, v_template: Optional[Tensor] = None) -> Skinning:
        """LBS of a template with this layer's blend shapes, joint regressor, tree and weights.

        Args:
            full_pose: (B, 48) axis-angle, root first (:meth:`full_pose_and_betas`).
            betas: (B, S) shape, S <= ``num_betas``.
            v_template: (V, 3) rest template; default the model's.

        Returns:
            :class:`~hogsa_loader.assets.hands.lbs.Skinning` without translation.
        """
        return skin_template(
            betas,
            full_pose,
            self.v_template if v_template is None else v_template,
            self.shapedirs[..., : betas.shape[-1]],
            self.posedirs,
            self.J_regressor,
            self.parents,
            self.lbs_weights,
        )

    def forward(
        self,
        global_orient: Optional[Tensor] = None,
        hand_pose: Optional[Tensor] = None,
        betas: Optional[Tensor] = None,
        transl: Optional[Tensor] = None,
    ) -> ManoOutput:
        """Pose the hand.

        Args:
            global_orient: (B, 3) root axis-angle (zeros when None).
            hand_pose: (B, 45) or (B, num_pca_comps) (zeros when None).
            betas: (B, num_betas) shape (zeros when None).
            transl: (B, 3) translation added to vertices and joints (zeros when None).

        Returns:
            :class:`ManoOutput`.
        """
        full_pose, betas = self.full_pose_and_betas(global_orient, hand_pose, betas, transl)
        out = self.skin(full_pose, betas)
        verts = out.vertices
        joints = torch.cat([out.joints, verts[:, self.tip_ids]], dim=1)
        if transl is not None:
            verts = verts + transl[:, None]
            joints = joints + transl[:, None]
        return ManoOutput(vertices=verts, joints=joints, full_pose=full_pose, rot_mats=out.rot_mats)
