"""ArcticNet-SF: a re-implementation of ARCTIC's single-frame hand-object baseline.

A ResNet trunk feeds three HMR-style heads (right hand, left hand, object) that refine
their state in 3 iterations. Hands: 16 rotations (6D) + 10 betas + a weak-perspective
camera, posed with :class:`~hogsa_loader.assets.hands.mano.MANOLayer`. Object: axis-angle
rotation, articulation angle + camera, posed with
:class:`~hogsa_loader.assets.objects.articulated.ArticulatedObjectLayer`. Weak-perspective
cameras ``(s, tx, ty)`` become translations ``(tx, ty, 2 f / (img_res · s))`` with the mean
focal length of the patch intrinsics, and 3D points are projected with those intrinsics.

Submodule and output names are ARCTIC's, so a released ArcticNet-SF checkpoint loads with
:func:`load_arctic_checkpoint` and losses written against ARCTIC's keys apply unchanged.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any, Literal, Mapping, Sequence, Union

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from hogsa_loader.assets.hands.mano import MANOLayer
from hogsa_loader.assets.objects.articulated import ArticulatedObjectLayer
from hogsa_loader.baselines.resnet import BACKBONE_CHANNELS, build_backbone, check_state_keys, read_state_dict
from hogsa_loader.errors import AssetError, PathLike, read_json
from hogsa_loader.geometry.rotations import matrix_to_axis_angle
from hogsa_loader.sample.augment import normalize_kp2d

__all__ = [
    "ARCTIC_IGNORED_PREFIXES",
    "ArcticNetSF",
    "ArtiHead",
    "HMRLayer",
    "HandHMR",
    "ManoHead",
    "NETWORK_PREFIXES",
    "ObjectHMR",
    "arctic_key_map",
    "load_arctic_checkpoint",
    "read_arctic_weights",
    "load_saved_model",
    "matrix_to_rotation_6d",
    "patch_intrinsics_wp",
    "perspective_to_weak_perspective",
    "project2d",
    "rotation_6d_to_matrix",
    "weak_perspective_to_perspective",
]

#: Smallest weak-perspective scale used when converting to a translation (ARCTIC's min_s).
MIN_SCALE = 0.1
#: State-dict prefixes of the learned network (what a checkpoint provides).
NETWORK_PREFIXES: tuple[str, ...] = ("backbone.", "head_r.", "head_l.", "head_o.")
#: Checkpoint prefixes (after removing ``model.``) that are not loaded: ARCTIC's smplx MANO
#: parameters/buffers and its object tensors; our layers come from the user's own files.
ARCTIC_IGNORED_PREFIXES: tuple[str, ...] = ("mano_r.", "mano_l.", "arti_head.")


# --------------------------------------------------------------------------------------
# Rotations and cameras
# --------------------------------------------------------------------------------------


def rotation_6d_to_matrix(d6: Tensor) -> Tensor:
    """6D rotation representation (Zhou et al. 2019) to matrices by Gram-Schmidt.

    The two 3-vectors become the first two **rows** of the matrix (the convention of
    ARCTIC's checkpoints), the third row is their cross product.

    Args:
        d6: (..., 6) unnormalised representation.

    Returns:
        (..., 3, 3) rotation matrices.
    """
    a1, a2 = d6[..., :3], d6[..., 3:]
    r1 = F.normalize(a1, dim=-1)
    r2 = F.normalize(a2 - (r1 * a2).sum(-1, keepdim=True) * r1, dim=-1)
    r3 = torch.cross(r1, r2, dim=-1)
    return torch.stack([r1, r2, r3], dim=-2)


def matrix_to_rotation_6d(rot: Tensor) -> Tensor:
    """Inverse of :func:`rotation_6d_to_matrix` on rotations: the first two rows.

    Args:
        rot: (..., 3, 3) rotation matrices.

    Returns:
        (..., 6) representation.
    """
    return rot[..., :2, :].reshape(rot.shape[:-2] + (6,))


def weak_perspective_to_perspective(
    cam_wp: Tensor, focal: Union[Tensor, float], img_res: int, min_s: float = MIN_SCALE
) -> Tensor:
    """Weak-perspective camera ``(s, tx, ty)`` to a translation ``(tx, ty, tz)``.

    ``tz = 2 f / (img_res · max(s, min_s) + 1e-9)``.

    Args:
        cam_wp: (B, 3) ``(s, tx, ty)``.
        focal: (B,) or scalar focal length in patch pixels.
        img_res: patch side in pixels.
        min_s: lower clamp of ``s`` (keeps the depth finite and positive).

    Returns:
        (B, 3) translation.
    """
    s = cam_wp[:, 0].clamp(min=min_s)
    tz = 2.0 * focal / (img_res * s + 1e-9)
    return torch.stack([cam_wp[:, 1], cam_wp[:, 2], tz], dim=-1)


def perspective_to_weak_perspective(cam_t: Tensor, focal: Union[Tensor, float], img_res: int) -> Tensor:
    """Translation ``(tx, ty, tz)`` to ``(s, tx, ty)`` with ``s = 2 f / (img_res · tz + 1e-9)``.

    Args:
        cam_t: (B, 3) translation.
        focal: (B,) or scalar focal length in patch pixels.
        img_res: patch side in pixels.

    Returns:
        (B, 3) weak-perspective camera (no clamp).
    """
    s = 2.0 * focal / (img_res * cam_t[:, 2] + 1e-9)
    return torch.stack([s, cam_t[:, 0], cam_t[:, 1]], dim=-1)


def mean_focal(K: Tensor) -> Tensor:
    """(B, 3, 3) intrinsics -> (B,) ``(fx + fy) / 2``."""
    return 0.5 * (K[:, 0, 0] + K[:, 1, 1])


def patch_intrinsics_wp(focal: float, img_res: int, batch: int, **kw: Any) -> Tensor:
    """ARCTIC's fixed patch camera ``[[f, 0, res//2], [0, f, res//2], [0, 0, 1]]``.

    Args:
        focal: focal length (px); img_res: patch side; batch: B; kw: dtype / device.

    Returns:
        (B, 3, 3) intrinsics.
    """
    K = torch.zeros(3, 3, **kw)
    K[0, 0] = K[1, 1] = focal
    K[0, 2] = K[1, 2] = img_res // 2
    K[2, 2] = 1.0
    return K.expand(batch, 3, 3).clone()


def project2d(K: Tensor, points: Tensor) -> Tensor:
    """Pinhole projection.

    Args:
        K: (B, 3, 3) intrinsics; points: (B, N, 3) camera-frame points.

    Returns:
        (B, N, 2) pixels.
    """
    uvw = points @ K.transpose(1, 2)
    return uvw[..., :2] / uvw[..., 2:3]


# --------------------------------------------------------------------------------------
# Heads
# --------------------------------------------------------------------------------------


class HMRLayer(nn.Module):
    """Iterative regressor: ``state += decoder(refine([feat, state]))``, ``n_iter`` times.

    Args:
        feat_dim: pooled feature size C.
        mid_dim: width of the refine MLP.
        specs: ``{name: size}`` of the regressed vectors (one linear decoder each, in
            ``decoders[name]``; names may contain ``/``, e.g. ARCTIC's ``cam_t/wp``).
    """

    def __init__(self, feat_dim: int, mid_dim: int, specs: Mapping[str, int]):
        super().__init__()
        self.specs = dict(specs)
        in_dim = feat_dim + sum(self.specs.values())
        self.refine = nn.Sequential(
            nn.Linear(in_dim, mid_dim), nn.ReLU(), nn.Dropout(), nn.Linear(mid_dim, mid_dim), nn.ReLU(), nn.Dropout()
        )
        self.decoders = nn.ModuleDict({k: nn.Linear(mid_dim, n) for k, n in self.specs.items()})
        for dec in self.decoders.values():
            nn.init.xavier_uniform_(dec.weight, gain=0.01)

    def forward(self, feat: Tensor, state: dict[str, Tensor], n_iter: int) -> dict[str, Tensor]:
        """Refine ``state``.

        Args:
            feat: (B, C) pooled features.
            state: ``{name: (B, size)}`` initial values; the MLP input is ``feat`` followed
                by the vectors **in this dict's order**.
            n_iter: number of refinement steps.

        Returns:
            a new dict with the refined vectors (same keys and order).
        """
        state = dict(state)
        for _ in range(n_iter):
            h = self.refine(torch.cat([feat, *state.values()], dim=1))
            state = {k: (self.decoders[k](h) + v if k in self.decoders else v) for k, v in state.items()}
        return state


def _cam_init_mlp(feat_dim: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(feat_dim, 512), nn.ReLU(), nn.Linear(512, 512), nn.ReLU(), nn.Linear(512, 3))


class _HMRHead(nn.Module, ABC):
    """Regressor of the state vectors ``SPECS``: an initial state made from the pooled
    features (the camera by ``cam_init``), refined by :class:`HMRLayer`.

    Args:
        feat_dim: backbone channels C; n_iter: refinement steps.
    """

    SPECS: dict[str, int] = {}

    def __init__(self, feat_dim: int, n_iter: int = 3):
        super().__init__()
        self.hmr_layer = HMRLayer(feat_dim, 1024, self.SPECS)
        self.cam_init = _cam_init_mlp(feat_dim)
        self.n_iter = n_iter

    @abstractmethod
    def initial_state(self, feat: Tensor, cam0: Tensor) -> dict[str, Tensor]:
        """``{name: (B, size)}`` start of the refinement, in the refine input order."""
        raise NotImplementedError

    def refine(self, features: Tensor) -> tuple[dict[str, Tensor], Tensor]:
        """features: (B, C, h, w) -> the refined state and the initial camera (B, 3)."""
        feat = features.mean(dim=(2, 3))
        cam0 = self.cam_init(feat)
        return self.hmr_layer(feat, self.initial_state(feat, cam0), self.n_iter), cam0


class HandHMR(_HMRHead):
    """Hand regressor: 16 joint rotations (6D), 10 betas, weak-perspective camera.

    The initial state is the identity pose, zero betas and ``cam_init(feat)``; the
    refine input order is pose, betas, camera.

    Args:
        feat_dim: backbone channels C; n_iter: refinement steps.
    """

    SPECS = {"pose_6d": 6 * 16, "cam_t/wp": 3, "shape": 10}

    def initial_state(self, feat: Tensor, cam0: Tensor) -> dict[str, Tensor]:
        B = feat.shape[0]
        eye6 = torch.tensor([1.0, 0.0, 0.0, 0.0, 1.0, 0.0], dtype=feat.dtype, device=feat.device)
        return {"pose_6d": eye6.repeat(B, 16), "shape": feat.new_zeros(B, 10), "cam_t/wp": cam0}

    def forward(self, features: Tensor) -> dict[str, Tensor]:
        """features: (B, C, h, w) -> ``pose`` (B, 16, 3, 3), ``pose_6d`` (B, 96),
        ``shape`` (B, 10), ``cam_t.wp`` (B, 3), ``cam_t.wp.init`` (B, 3)."""
        out, cam0 = self.refine(features)
        pose = rotation_6d_to_matrix(out["pose_6d"].reshape(features.shape[0], 16, 6))
        return {
            "pose_6d": out["pose_6d"],
            "shape": out["shape"],
            "cam_t.wp": out["cam_t/wp"],
            "pose": pose,
            "cam_t.wp.init": cam0,
        }


class ObjectHMR(_HMRHead):
    """Object regressor: axis-angle rotation (3), articulation angle (1), camera (3).

    The initial state is zero rotation and angle and ``cam_init(feat)``; the refine
    input order is rotation, angle, camera.

    Args:
        feat_dim: backbone channels C; n_iter: refinement steps.
    """

    SPECS = {"rot": 3, "cam_t/wp": 3, "radian": 1}

    def initial_state(self, feat: Tensor, cam0: Tensor) -> dict[str, Tensor]:
        B = feat.shape[0]
        return {"rot": feat.new_zeros(B, 3), "radian": feat.new_zeros(B, 1), "cam_t/wp": cam0}

    def forward(self, features: Tensor) -> dict[str, Tensor]:
        """features: (B, C, h, w) -> ``rot`` (B, 3), ``radian`` (B, 1), ``cam_t.wp`` (B, 3),
        ``cam_t.wp.init`` (B, 3)."""
        out, cam0 = self.refine(features)
        return {"rot": out["rot"], "radian": out["radian"], "cam_t.wp": out["cam_t/wp"], "cam_t.wp.init": cam0}


class ManoHead(nn.Module):
    """Poses a MANO layer from rotation matrices and places it with a weak-perspective camera.

    Args:
        mano: a :class:`~hogsa_loader.assets.hands.mano.MANOLayer` (10 betas, axis-angle mode).
        img_res: patch side in pixels.
    """

    def __init__(self, mano: MANOLayer, img_res: int):
        super().__init__()
        if getattr(mano, "use_pca", False) or getattr(mano, "num_betas", 10) != 10:
            raise ValueError("ArcticNet-SF needs a MANO layer with use_pca=False and num_betas=10")
        self.mano = mano
        self.img_res = img_res

    def forward(self, rotmat: Tensor, betas: Tensor, cam_wp: Tensor, K: Tensor) -> dict[str, Tensor]:
        """Pose and project one hand.

        Args:
            rotmat: (B, 16, 3, 3) root then finger rotations (fingers relative to the
                layer's mean pose when ``flat_hand_mean=False``).
            betas: (B, 10); cam_wp: (B, 3) ``(s, tx, ty)``; K: (B, 3, 3) patch intrinsics.

        Returns:
            ``cam_t.wp``, ``cam_t`` (B, 3), ``joints3d`` (B, J, 3), ``vertices`` (B, V, 3),
            ``j3d.cam`` / ``v3d.cam`` (translated), ``j2d.norm`` (B, J, 2), ``beta``,
            ``pose`` (B, 16, 3, 3).
        """
        B = rotmat.shape[0]
        aa = matrix_to_axis_angle(rotmat.reshape(-1, 3, 3)).reshape(B, -1)
        out = self.mano(global_orient=aa[:, :3], hand_pose=aa[:, 3:], betas=betas)
        cam_t = weak_perspective_to_perspective(cam_wp, mean_focal(K), self.img_res)
        j3d_cam = out.joints + cam_t[:, None]
        v3d_cam = out.vertices + cam_t[:, None]
        j2d = normalize_kp2d(project2d(K, j3d_cam), self.img_res)
        return {
            "cam_t.wp": cam_wp,
            "cam_t": cam_t,
            "joints3d": out.joints,
            "vertices": out.vertices,
            "j3d.cam": j3d_cam,
            "v3d.cam": v3d_cam,
            "j2d.norm": j2d,
            "beta": betas,
            "pose": rotmat,
        }


class ArtiHead(nn.Module):
    """Poses the articulated objects and places them with a weak-perspective camera.

    Args:
        object_tensors: an :class:`~hogsa_loader.assets.objects.articulated.ArticulatedObjectLayer`.
        img_res: patch side in pixels.
    """

    def __init__(self, object_tensors: ArticulatedObjectLayer, img_res: int):
        super().__init__()
        self.object_tensors = object_tensors
        self.img_res = img_res

    def forward(
        self, rot: Tensor, radian: Tensor, names: Sequence[str], cam_wp: Tensor, K: Tensor
    ) -> dict[str, Tensor]:
        """Pose and project B objects.

        Args:
            rot: (B, 3) axis-angle; radian: (B, 1) articulation; names: B object names;
            cam_wp: (B, 3) ``(s, tx, ty)``; K: (B, 3, 3) patch intrinsics.

        Returns:
            ARCTIC's object outputs (keys without the ``object.`` prefix); ``kp3d``
            (B, 32, 3) = 16 top + 16 bottom, ``bbox3d`` (B, 16, 3) = 8 top + 8 bottom,
            ``v.cam`` (B, L, 3) padded to the longest object of the batch.
        """
        out = self.object_tensors(angles=radian.reshape(-1, 1), global_orient=rot, transl=None, names=list(names))
        cam_t = weak_perspective_to_perspective(cam_wp, mean_focal(K), self.img_res)
        kp3d_cam = out["kp3d"] + cam_t[:, None]
        bbox3d_cam = out["bbox3d"] + cam_t[:, None]
        kp2d = normalize_kp2d(project2d(K, kp3d_cam), self.img_res)
        bbox2d = normalize_kp2d(project2d(K, bbox3d_cam), self.img_res)
        nk, nb = kp2d.shape[1] // 2, bbox2d.shape[1] // 2
        return {
            "rot": rot,
            "cam_t.wp": cam_wp,
            "cam_t": cam_t,
            "kp3d": out["kp3d"],
            "bbox3d": out["bbox3d"],
            "bbox3d.cam": bbox3d_cam,
            "kp3d.cam": kp3d_cam,
            "kp2d.norm": kp2d,
            "kp2d.norm.t": kp2d[:, :nk],
            "kp2d.norm.b": kp2d[:, nk:],
            "bbox2d.norm.t": bbox2d[:, :nb],
            "bbox2d.norm.b": bbox2d[:, nb:],
            "radian": radian,
            "v.cam": out["v"] + cam_t[:, None],
            "v_len": out["v_len"],
            "f": out["f"],
            "f_len": out["f_len"],
            "parts_ids": out["parts_ids"],
        }


# --------------------------------------------------------------------------------------
# The model
# --------------------------------------------------------------------------------------


class ArcticNetSF(nn.Module):
    """ArcticNet-SF (single frame): image -> two MANO hands + one articulated object.

    Args:
        backbone: ``"resnet18"`` or ``"resnet50"`` (ARCTIC's release uses ResNet-50),
            randomly initialised; load ImageNet weights with
            :func:`~hogsa_loader.baselines.resnet.load_backbone_weights` on ``.backbone``.
        mano_r: right :class:`~hogsa_loader.assets.hands.mano.MANOLayer` (ARCTIC:
            ``flat_hand_mean=False``); stored as ``mano_r.mano``.
        mano_l: the left one; stored as ``mano_l.mano``.
        object_layer: :class:`~hogsa_loader.assets.objects.articulated.ArticulatedObjectLayer`
            holding every object of ``query_names``; stored as ``arti_head.object_tensors``.
        focal_length: focal length (px) of the fixed patch camera used when
            ``meta_info`` has no ``intrinsics`` (ARCTIC: 1000).
        img_res: patch side in pixels (ARCTIC: 224).

    ``state_dict()`` also holds the object layer's template buffers;
    :meth:`network_state_dict` holds the learned weights only.
    """

    def __init__(
        self,
        backbone: Literal["resnet18", "resnet50"],
        mano_r: MANOLayer,
        mano_l: MANOLayer,
        object_layer: ArticulatedObjectLayer,
        *,
        focal_length: float = 1000.0,
        img_res: int = 224,
    ):
        super().__init__()
        for layer, side in ((mano_r, "right"), (mano_l, "left")):
            if getattr(layer, "side", side) != side:
                raise ValueError(f"mano_{side[0]} must be a {side} MANO layer, got side={layer.side!r}")
        self.backbone = build_backbone(backbone)
        feat_dim = BACKBONE_CHANNELS[backbone]
        self.head_r = HandHMR(feat_dim, n_iter=3)
        self.head_l = HandHMR(feat_dim, n_iter=3)
        self.head_o = ObjectHMR(feat_dim, n_iter=3)
        self.mano_r = ManoHead(mano_r, img_res)
        self.mano_l = ManoHead(mano_l, img_res)
        self.arti_head = ArtiHead(object_layer, img_res)
        self.backbone_name = backbone
        self.focal_length = float(focal_length)
        self.img_res = int(img_res)

    def _intrinsics(self, meta_info: Mapping[str, Any], ref: Tensor) -> Tensor:
        B = ref.shape[0]
        K = meta_info.get("intrinsics")
        if K is None:
            return patch_intrinsics_wp(self.focal_length, self.img_res, B, dtype=ref.dtype, device=ref.device)
        K = torch.as_tensor(K).to(dtype=ref.dtype, device=ref.device)
        if K.shape != (B, 3, 3):
            raise ValueError(f"meta_info['intrinsics'] must be ({B}, 3, 3), got {tuple(K.shape)}")
        return K

    def forward(self, inputs: Mapping[str, Tensor], meta_info: Mapping[str, Any]) -> dict[str, Tensor]:
        """Predict hands and object.

        Args:
            inputs: ``img`` (B, 3, H, W) normalised patches.
            meta_info: ``query_names`` (B object names) and ``intrinsics`` (B, 3, 3)
                patch intrinsics (optional, see ``focal_length``).

        Returns:
            dict with ARCTIC's keys: ``mano.*.r``, ``mano.*.l`` (see :class:`ManoHead`,
            plus ``mano.cam_t.wp.init.{r,l}``), ``object.*`` (see :class:`ArtiHead`,
            plus ``object.cam_t.wp.init``) and ``feat_vec`` (B, C) detached spatial sum
            of the features.
        """
        images = inputs["img"]
        names = meta_info["query_names"]
        names = [names] if isinstance(names, str) else list(names)
        if len(names) != images.shape[0]:
            raise ValueError(f"{len(names)} query_names for a batch of {images.shape[0]} images")
        features = self.backbone(images)
        K = self._intrinsics(meta_info, features)
        out: dict[str, Tensor] = {}
        for s, head, mano in (("r", self.head_r, self.mano_r), ("l", self.head_l, self.mano_l)):
            hmr = head(features)
            hand = mano(rotmat=hmr["pose"], betas=hmr["shape"], cam_wp=hmr["cam_t.wp"], K=K)
            hand["cam_t.wp.init"] = hmr["cam_t.wp.init"]
            out.update({f"mano.{k}.{s}": v for k, v in hand.items()})
        hmr_o = self.head_o(features)
        obj = self.arti_head(rot=hmr_o["rot"], radian=hmr_o["radian"], names=names, cam_wp=hmr_o["cam_t.wp"], K=K)
        obj["cam_t.wp.init"] = hmr_o["cam_t.wp.init"]
        out.update({f"object.{k}": v for k, v in obj.items()})
        out["feat_vec"] = features.flatten(2).sum(dim=2).detach()
        return out

    @torch.no_grad()
    def init_cameras(self, mean_wp: Mapping[str, Tensor]) -> None:
        """Start the three weak-perspective cameras at a prior (HMR's mean-parameter start).

        Each ``cam_init`` MLP's last layer gets the prior as its bias and a small weight
        (Xavier, gain 0.01, as the refine decoders), so a new model predicts
        ``cam_t.wp.init`` close to the prior for any image. Without it a randomly
        initialised model starts near ``s = 0``, below ARCTIC's clamp ``s >= 0.1``, where
        translations are tens of metres: the contact-deviation loss, whose gradient in
        ``s`` grows as ``1/s^2``, then outweighs the camera loss and keeps ``s`` there.

        Args:
            mean_wp: ``{"r": (3,), "l": (3,), "o": (3,)}`` prior ``(s, tx, ty)`` per head,
                e.g. the mean training target (:func:`~hogsa_loader.baselines.engine.mean_cameras`).
        """
        missing = {"r", "l", "o"} - set(mean_wp)
        if missing:
            raise ValueError(f"init_cameras needs priors for heads {sorted(missing)} (keys r, l, o)")
        for side, head in (("r", self.head_r), ("l", self.head_l), ("o", self.head_o)):
            prior = torch.as_tensor(mean_wp[side], dtype=torch.float32).reshape(-1)
            if prior.shape != (3,) or not torch.isfinite(prior).all():
                raise ValueError(f"init_cameras: prior {side!r} must be 3 finite numbers, got {prior.tolist()}")
            last = head.cam_init[-1]
            nn.init.xavier_uniform_(last.weight, gain=0.01)
            last.bias.copy_(prior.to(last.bias))

    def network_state_dict(self) -> dict[str, Tensor]:
        """The learned weights only (backbone and heads; no MANO / object templates)."""
        return {k: v for k, v in self.state_dict().items() if k.startswith(NETWORK_PREFIXES)}


# --------------------------------------------------------------------------------------
# ARCTIC checkpoints
# --------------------------------------------------------------------------------------


def arctic_key_map(state_dict: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """Map an ARCTIC ArcticNet-SF state dict onto :class:`ArcticNetSF`'s network keys.

    * A Lightning checkpoint's ``model.`` prefix is removed; entries without it (the
      training wrapper's own ``mano_r.*`` / ``mano_l.*`` smplx layers) are dropped.
    * Entries under :data:`ARCTIC_IGNORED_PREFIXES` are dropped: ARCTIC's smplx MANO
      parameters and buffers (``betas``, ``global_orient``, ``body_pose``, ``hand_pose``,
      ``v_template``, ``shapedirs``, ``posedirs``, ``J_regressor``, ``parents``,
      ``lbs_weights``, ``faces_tensor``, ``hand_mean``, ``pose_mean``,
      ``vertex_joint_selector.extra_joints_idxs``) and anything under ``arti_head``
      (ARCTIC's object tensors are a plain dict, not part of the state dict).
    * Every other name is kept as is: backbone and head names are identical, including
      the decoder keys ``cam_t/wp`` (``/`` is a valid module name).

    Args:
        state_dict: ARCTIC's ``{name: tensor}`` (Lightning ``state_dict`` or the model's).

    Returns:
        ``{name: tensor}`` for :meth:`ArcticNetSF.load_state_dict` (``strict=False``).
    """
    lightning = any(k.startswith("model.") for k in state_dict)
    out: dict[str, Tensor] = {}
    for key, value in state_dict.items():
        if lightning:
            if not key.startswith("model."):
                continue
            key = key[len("model.") :]
        if not key.startswith(ARCTIC_IGNORED_PREFIXES):
            out[key] = value
    return out


def read_arctic_weights(path: PathLike, weights_only: bool = True) -> dict[str, Tensor]:
    """The network weights of an ARCTIC model file, keyed as this package's models name them.

    Args:
        path: a Lightning ``.ckpt`` (its ``state_dict``), a ``torch.save`` state dict or a
            ``.safetensors`` file.
        weights_only: see :func:`~hogsa_loader.baselines.resnet.read_state_dict`.

    Returns:
        ``{name: tensor}`` after :func:`arctic_key_map`.
    """
    raw = read_state_dict(path, weights_only=weights_only)
    if isinstance(raw.get("state_dict"), Mapping):
        raw = raw["state_dict"]
    return arctic_key_map(raw)


def load_arctic_checkpoint(model: ArcticNetSF, path: PathLike, weights_only: bool = True) -> None:
    """Load ARCTIC's ArcticNet-SF weights (backbone and heads) into ``model``.

    Args:
        model: the :class:`ArcticNetSF` (its backbone must be the checkpoint's).
        path: a Lightning ``.ckpt`` (its ``state_dict``), a ``torch.save`` state dict or
            a ``.safetensors`` file.
        weights_only: see :func:`~hogsa_loader.baselines.resnet.read_state_dict`.

    Raises:
        AssetError: naming the file and the missing / unexpected / mis-shaped keys.
    """
    state = read_arctic_weights(path, weights_only)
    own = model.network_state_dict()
    check_state_keys(path, own, state, f"an ArcticNet-SF with a {model.backbone_name} backbone")
    result = model.load_state_dict(state, strict=False)
    left = [k for k in result.missing_keys if k.startswith(NETWORK_PREFIXES) and not k.endswith("num_batches_tracked")]
    if left or result.unexpected_keys:
        raise AssetError(path, f"incomplete load: missing {left}, unexpected {result.unexpected_keys}")


def load_saved_model(
    path: PathLike, mano_r: MANOLayer, mano_l: MANOLayer, objects: ArticulatedObjectLayer
) -> tuple[ArcticNetSF, dict[str, Any]]:
    """The ArcticNet-SF a training run saved, in eval mode, and the run's settings.

    Args:
        path: ``model.safetensors`` of a run, its manifest ``model.json`` beside it (written
            with :func:`~hogsa_loader.io.tensors.write_tensors_and_manifest`; ``settings.model``
            names the backbone and the patch side ``img_res``).
        mano_r, mano_l, objects: the layers the model is built on (those it was trained with).

    Returns:
        ``(model, settings)``; the focal length is ARCTIC's 1000 px.

    Raises:
        AssetError: naming ``model.json`` when it names another model kind (``kind``) or
            lacks ``settings.model.backbone`` / ``img_res``, or the weights file when a tensor
            is missing or mis-shaped.
    """
    manifest = Path(path).with_name("model.json")
    raw = read_json(manifest)
    kind = raw.get("kind", "arcticnet_sf") if isinstance(raw, dict) else "arcticnet_sf"
    if kind != "arcticnet_sf":
        raise AssetError(manifest, f"holds a {kind!r} model, not an ArcticNet-SF")
    try:
        settings = dict(raw["settings"])  # type: ignore[index]
        backbone, img_res = str(settings["model"]["backbone"]), int(settings["model"]["img_res"])
    except (KeyError, TypeError, ValueError) as exc:
        raise AssetError(manifest, f"no settings.model.backbone / img_res ({exc!r})") from exc
    model = ArcticNetSF(backbone, mano_r, mano_l, objects, focal_length=1000.0, img_res=img_res)
    load_arctic_checkpoint(model, path)
    return model.eval(), settings
