"""ArcticNet-SF data augmentation and patch geometry.

Everything that turns an image region plus 2D/3D labels into the 224×224 training patch
of ArcticNet-SF, matching ``zc-alexfan/arctic`` ``common/data_utils.py``: the augmentation
draw (:func:`sample_aug_params`), the image patch (:func:`process_image`), the 2D keypoint
transform (:func:`j2d_processing`), the rotation of global orientations (:func:`rot_aa`)
and the patch intrinsics (:func:`patch_intrinsics`). Pixels follow OpenCV (pixel *i* has
its centre at coordinate *i*).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Sequence

import cv2
import numpy as np
import torch

__all__ = [
    "ArcticConfig",
    "AugParams",
    "sample_aug_params",
    "hmr_transform_matrix",
    "transform_keypoints",
    "normalize_kp2d",
    "unnormalize_kp2d",
    "j2d_processing",
    "patch_warp_matrix",
    "process_image",
    "rot_aa",
    "rotation_z",
    "patch_intrinsics",
    "BLUR_KERNEL",
    "BLUR_SIGMA",
    "ROT_ZERO_PROB",
]

#: Gaussian anti-aliasing kernel applied to the source before the warp (:func:`process_image`).
BLUR_KERNEL: int = 5
BLUR_SIGMA: float = 8.0


def _kernel_std(ksize: int, sigma: float) -> float:
    """Per-axis standard deviation (px) of OpenCV's normalised ``ksize``-tap Gaussian kernel."""
    x = np.arange(ksize, dtype=np.float64) - (ksize - 1) / 2
    w = np.exp(-(x**2) / (2 * sigma**2))
    return float(np.sqrt((w * x**2).sum() / w.sum()))


#: Footprint of ARCTIC's blur (5×5, σ = 8: almost a box filter) as a Gaussian std in
#: source pixels (≈ 1.41 px); :func:`process_image` scales it for smaller sources.
BLUR_PIXEL_STD: float = _kernel_std(BLUR_KERNEL, BLUR_SIGMA)
#: Probability that the sampled rotation is replaced by 0 (:func:`sample_aug_params`).
ROT_ZERO_PROB: float = 0.6


@dataclass(frozen=True)
class ArcticConfig:
    """The ArcticNet-SF settings a sample depends on (defaults: ArcticNet-SF's config).

    Attributes:
        img_res: patch side (px).
        focal_length: focal length of the fixed patch intrinsics (``use_gt_k=False``).
        rot_factor: rotation std (degrees); samples are clipped to ±2·rot_factor.
        noise_factor: colour noise half-range; ``pn ~ U(1 − f, 1 + f)`` per channel.
        scale_factor: scale std; samples are clipped to ``1 ± scale_factor``.
        flip_prob: must be 0 (ARCTIC does not support flipping). A uniform number is
            still drawn for it so that the random stream matches ARCTIC's draw order.
        img_norm_mean, img_norm_std: ImageNet normalisation (RGB order).
        window_size: ``meta_info.window_size``.
        use_gt_k: patch intrinsics from the full-image K (:func:`patch_intrinsics`); forced True for
            egocentric samples regardless of this flag.
        ego_image_scale: egocentric cropped images are the full frame times this factor.
    """

    img_res: int = 224
    focal_length: float = 1000.0
    rot_factor: float = 30.0
    noise_factor: float = 0.4
    scale_factor: float = 0.25
    flip_prob: float = 0.0
    img_norm_mean: tuple[float, float, float] = (0.485, 0.456, 0.406)
    img_norm_std: tuple[float, float, float] = (0.229, 0.224, 0.225)
    window_size: int = 11
    use_gt_k: bool = False
    ego_image_scale: float = 0.3

    def __post_init__(self) -> None:
        if self.flip_prob != 0.0:
            raise ValueError("flip_prob must be 0: ARCTIC does not support flipping")
        if self.img_res <= 0:
            raise ValueError(f"img_res must be positive, got {self.img_res}")


@dataclass
class AugParams:
    """Augmentation of one sample (ARCTIC's ``augm_dict``).

    Attributes:
        rot: in-plane rotation in degrees (positive = the image content turns
            counter-clockwise on screen, i.e. keypoints rotate by ``-rot`` in the y-down
            pixel frame).
        sc: scale factor of the crop side (>1 = larger source region, content smaller).
        pn: (3,) per-channel colour multipliers (RGB).
        flip: always 0.
    """

    rot: float = 0.0
    sc: float = 1.0
    pn: np.ndarray = field(default_factory=lambda: np.ones(3))
    flip: int = 0

    def __post_init__(self) -> None:
        self.pn = np.asarray(self.pn, dtype=np.float64).reshape(3)
        if self.flip != 0:
            raise ValueError("flip augmentation is not supported (ARCTIC asserts it off)")

    @classmethod
    def identity(cls) -> "AugParams":
        """No augmentation (evaluation): rot 0, sc 1, pn 1."""
        return cls()


def sample_aug_params(
    rng: np.random.Generator, train: bool, egocentric: bool = False, cfg: ArcticConfig = ArcticConfig()
) -> AugParams:
    """Draw the augmentation of one sample (rotation, scale, colour noise).

    Training draws, in ARCTIC's order: one uniform for the (disabled) flip, three
    colour multipliers ``U(1 − noise, 1 + noise)``, ``rot = clip(N(0,1)·rot_factor,
    ±2·rot_factor)``, ``sc = clip(N(0,1)·scale_factor + 1, 1 ± scale_factor)``, and a
    final uniform ``u``: ``rot = 0`` when ``u <= 0.6``. Evaluation draws nothing and
    returns the identity. Egocentric samples keep ``rot`` and ``pn`` but get ``sc = 1``.

    Args:
        rng: the generator all randomness comes from.
        train: augment (training split) or not.
        egocentric: egocentric view (forces ``sc = 1``).
        cfg: factors.

    Returns:
        The sampled :class:`AugParams`.
    """
    if not train:
        aug = AugParams.identity()
    else:
        flip_u = rng.uniform()
        if flip_u <= cfg.flip_prob and cfg.flip_prob > 0:  # pragma: no cover - cfg forbids it
            raise ValueError("flip augmentation is not supported")
        pn = rng.uniform(1.0 - cfg.noise_factor, 1.0 + cfg.noise_factor, 3)
        rot = min(2 * cfg.rot_factor, max(-2 * cfg.rot_factor, rng.standard_normal() * cfg.rot_factor))
        sc = min(1 + cfg.scale_factor, max(1 - cfg.scale_factor, rng.standard_normal() * cfg.scale_factor + 1))
        if rng.uniform() <= ROT_ZERO_PROB:
            rot = 0.0
        aug = AugParams(rot=float(rot), sc=float(sc), pn=pn)
    if egocentric:
        aug.sc = 1.0
    return aug


# --------------------------------------------------------------------------------------
# 2D keypoints
# --------------------------------------------------------------------------------------


def _rot2d(deg: float) -> np.ndarray:
    """(2, 2) ``[[cos, -sin], [sin, cos]]`` of ``deg`` degrees (y-down pixel frame)."""
    a = deg * np.pi / 180.0
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s], [s, c]])


def hmr_transform_matrix(center: Sequence[float], scale: float, rot: float, img_res: int) -> np.ndarray:
    """The HMR crop similarity of 2D keypoints as a 3×3 matrix.

    Maps the square of side ``200·scale`` centred on ``center`` onto the ``img_res``
    patch: ``p' = R(−rot) · (p − center) · img_res / (200·scale) + img_res/2`` where
    ``R(a) = [[cos a, −sin a], [sin a, cos a]]`` acts on y-down pixel coordinates.

    Args:
        center: (2,) crop centre (pixels of the source image).
        scale: crop side / 200 (already multiplied by the augmentation scale).
        rot: augmentation rotation (degrees).
        img_res: patch side.

    Returns:
        (3, 3) float64 homogeneous matrix.
    """
    side = 200.0 * float(scale)
    A = np.eye(3)
    A[0, 0] = A[1, 1] = float(img_res) / side
    A[0, 2] = img_res * (-float(center[0]) / side + 0.5)
    A[1, 2] = img_res * (-float(center[1]) / side + 0.5)
    if rot != 0:
        # rotate by -rot about the patch centre: shift centre to 0, rotate, shift back
        half = img_res / 2.0
        to_origin = np.eye(3)
        to_origin[:2, 2] = -half
        back = np.eye(3)
        back[:2, 2] = half
        R = np.eye(3)
        R[:2, :2] = _rot2d(-rot)
        A = back @ (R @ (to_origin @ A))
    return A


def transform_keypoints(kp: np.ndarray, center: Sequence[float], scale: float, rot: float, img_res: int) -> np.ndarray:
    """HMR keypoint transform into patch pixels, with its integer truncation.

    Reproduces ARCTIC/HMR exactly: the point is shifted by +1 (caller side) and −1
    (callee side), transformed by :func:`hmr_transform_matrix`, truncated towards zero
    (``astype(int)``) and shifted by +1. Non-finite inputs give NaN (ARCTIC would give
    an undefined integer).

    Args:
        kp: (N, 2) pixels of the source image.
        center, scale, rot, img_res: see :func:`hmr_transform_matrix`.

    Returns:
        (N, 2) float64 integer-valued patch pixels.
    """
    kp = np.asarray(kp, dtype=np.float64)[:, :2]
    T = hmr_transform_matrix(center, scale, rot, img_res)
    p = (kp + 1.0) - 1.0
    q = p @ T[:2, :2].T + T[:2, 2]
    finite = np.isfinite(q)
    out = np.full_like(q, np.nan)
    out[finite] = np.trunc(q[finite]) + 1.0
    return out


def _points(kp):
    """float64 numpy array of ``kp``, or ``kp`` itself when it is a tensor (dtype, device and
    autograd kept)."""
    return kp if isinstance(kp, torch.Tensor) else np.asarray(kp, dtype=np.float64)


def normalize_kp2d(kp, img_res: int):
    """Patch pixels → ``2u/img_res − 1`` (≈ [−1, 1] inside the patch); numpy or torch,
    any shape (..., 2)."""
    return 2.0 * _points(kp) / img_res - 1.0


def unnormalize_kp2d(kp_norm, img_res: int):
    """Inverse of :func:`normalize_kp2d`: ``(u + 1) · img_res / 2``; numpy or torch."""
    return (_points(kp_norm) + 1.0) * (img_res / 2.0)


def j2d_processing(kp: np.ndarray, center: Sequence[float], scale: float, aug: AugParams, img_res: int) -> np.ndarray:
    """2D keypoints (source pixels) → normalised patch coordinates.

    The image warp (:func:`patch_warp_matrix`) and this keypoint transform use the same
    similarity (centre → ``img_res/2``, side → ``img_res``, rotation by ``-rot`` degrees
    about the patch centre); the labels are then truncated to integers the HMR way
    (:func:`transform_keypoints`), so a label lies ``[0, 1]`` px right/below of the exact
    patch position for points inside the patch (``[0, 2]`` px where the exact coordinate
    is negative, because truncation goes towards zero).

    Args:
        kp: (N, 2) source-image pixels.
        center: (2,) crop centre; ``scale``: crop side / 200 before augmentation.
        aug: augmentation (uses ``sc`` and ``rot``).
        img_res: patch side.

    Returns:
        (N, 2) float32.
    """
    px = transform_keypoints(kp, center, aug.sc * scale, aug.rot, img_res)
    return normalize_kp2d(px, img_res).astype(np.float32)


# --------------------------------------------------------------------------------------
# Image
# --------------------------------------------------------------------------------------


def patch_warp_matrix(center: Sequence[float], crop_dim: float, rot: float, img_res: int) -> np.ndarray:
    """The OpenCV affine (2×3, float32) used to warp the source onto the patch.

    The square of side ``crop_dim`` around ``center``, rotated by ``rot`` degrees, maps
    onto the ``img_res`` patch: ``p' = R(−rot)(p − center)·img_res/crop_dim + img_res/2``.
    (ARCTIC builds the same map from three point pairs with ``cv2.getAffineTransform``.)
    """
    k = float(img_res) / float(crop_dim)
    L = _rot2d(-rot) * k
    c = np.array([float(center[0]), float(center[1])])
    M = np.zeros((2, 3))
    M[:, :2] = L
    M[:, 2] = img_res / 2.0 - L @ c
    return M.astype(np.float32)


def process_image(
    image: Optional[np.ndarray],
    center: Sequence[float],
    scale: float,
    aug: AugParams,
    cfg: ArcticConfig = ArcticConfig(),
    source_scale: float = 1.0,
) -> torch.Tensor:
    """Source image → normalised ``(3, img_res, img_res)`` float32 patch.

    Gaussian blur (5×5, σ=8, OpenCV default border) of the float32 source; OpenCV
    bicubic warp (constant-0 border) of the square of side ``int(sc·scale·200)`` around
    ``center`` rotated by ``rot``; channels multiplied by ``pn`` and clipped to [0, 255];
    HWC→CHW; /255; ``(x − mean) / std``.

    Args:
        image: (H, W, 3) RGB, uint8 or float in [0, 255]; None = a zero image (ARCTIC's
            stand-in for an unreadable file).
        center: (2,) crop centre in ``image`` pixels.
        scale: box side / 200 in ``image`` pixels, before augmentation.
        aug: augmentation.
        cfg: ``img_res`` and normalisation.
        source_scale: pixels of ``image`` per pixel of the source ARCTIC reads for such a
            view (its 1000-px cropped image, or the 0.3-scaled egocentric frame). 1 (real
            data) is ARCTIC's blur exactly. A smaller synthetic source (e.g. a 336-px
            render of the same crop: 0.336) gets a Gaussian of std
            ``BLUR_PIXEL_STD · source_scale`` instead, so the blur in the output patch is
            the same as in real samples; ARCTIC's 5-px kernel on it would blur the
            synthetic patch about 3× more than the real ones.

    Returns:
        (3, img_res, img_res) float32 tensor.
    """
    if not source_scale > 0:
        raise ValueError(f"source_scale must be > 0, got {source_scale}")
    res = cfg.img_res
    if image is None:
        # ARCTIC blurs and warps a (2800, 2000, 3) zero image: the patch is all zeros.
        patch = np.zeros((res, res, 3), dtype=np.float32)
    else:
        img = np.asarray(image)
        if img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"image must be (H, W, 3), got {img.shape}")
        img = img.astype(np.float32)
        crop_dim = int(aug.sc * scale * 200)
        M = patch_warp_matrix(center, crop_dim, aug.rot, res)
        if source_scale == 1.0:
            blur = cv2.GaussianBlur(img, (BLUR_KERNEL, BLUR_KERNEL), BLUR_SIGMA)
        else:
            sigma = BLUR_PIXEL_STD * source_scale
            k = 2 * int(np.ceil(3.0 * sigma)) + 1
            blur = cv2.GaussianBlur(img, (k, k), sigma)
        patch = cv2.warpAffine(blur, M, (res, res), flags=cv2.INTER_CUBIC).astype(np.float32)
    for ch in range(3):
        patch[:, :, ch] = np.minimum(255.0, np.maximum(0.0, patch[:, :, ch] * aug.pn[ch]))
    chw = np.transpose(patch, (2, 0, 1)) / np.float32(255.0)
    # torchvision ``Normalize`` arithmetic (float32 subtract, then divide), done in numpy
    # so no torch intra-op thread pool is involved in data-loading workers
    mean = np.asarray(cfg.img_norm_mean, dtype=np.float32)[:, None, None]
    std = np.asarray(cfg.img_norm_std, dtype=np.float32)[:, None, None]
    return torch.from_numpy(np.ascontiguousarray((chw - mean) / std, dtype=np.float32))


# --------------------------------------------------------------------------------------
# 3D rotation and intrinsics
# --------------------------------------------------------------------------------------


def rotation_z(deg: float) -> np.ndarray:
    """(3, 3) rotation by ``deg`` degrees about the camera z (optical) axis."""
    R = np.eye(3)
    R[:2, :2] = _rot2d(deg)
    return R


def rot_aa(aa: np.ndarray, rot: float) -> np.ndarray:
    """Left-multiply a camera-frame orientation by ``R_z(−rot)``.

    ``R_z(−rot)`` turns camera-frame points exactly like the 2D keypoint transform turns
    their projections about the principal point (both use ``R(−rot)`` in the y-down
    frame), so the rotated orientation stays consistent with the rotated labels.

    Args:
        aa: (3,) axis-angle.
        rot: augmentation rotation (degrees).

    Returns:
        (3,) float64 axis-angle of ``R_z(−rot) · R(aa)`` (OpenCV Rodrigues, as ARCTIC).
    """
    R = rotation_z(-rot)
    per, _ = cv2.Rodrigues(np.asarray(aa, dtype=np.float64).reshape(3, 1))
    out, _ = cv2.Rodrigues(R @ per)
    return out.reshape(3)


def patch_intrinsics(
    K_full: np.ndarray, image_size: Sequence[float], sc: float, use_gt_k: bool, cfg: ArcticConfig = ArcticConfig()
) -> np.ndarray:
    """Intrinsics of the patch (ARCTIC's ``get_aug_intrix``).

    * ``use_gt_k=False``: ``[[f, 0, res/2], [0, f, res/2], [0, 0, 1]]`` with
      ``f = cfg.focal_length`` (``res // 2`` exactly as ARCTIC).
    * ``use_gt_k=True``: the full-image K under a virtual square crop of side
      ``d = sc · max(W, H)`` centred on the image centre ``(W/2, H/2)``:
      ``k = res/d``; ``fx' = k fx``, ``fy' = k fy``, ``cx' = k (cx − (W/2 − d/2))``,
      ``cy' = k (cy − (H/2 − d/2))`` (2800×2000 ego image: d = 2800, k = 0.08). This is
      the patch camera for egocentric samples (whole-image box, sc = 1); for
      allocentric samples it ignores the object-centred box, exactly as ARCTIC does.

    Args:
        K_full: (3, 3) full-resolution intrinsics.
        image_size: (W, H) of the full-resolution image.
        sc: augmentation scale.
        use_gt_k: which rule.
        cfg: ``img_res``, ``focal_length``.

    Returns:
        (3, 3) float64.
    """
    res = cfg.img_res
    if not use_gt_k:
        K = np.zeros((3, 3))
        K[0, 0] = K[1, 1] = cfg.focal_length
        K[0, 2] = K[1, 2] = res // 2
        K[2, 2] = 1.0
        return K
    W, H = float(image_size[0]), float(image_size[1])
    K = np.array(K_full, dtype=np.float64).copy()
    dim = sc * (max(W, H) / 200.0) * 200.0
    k = float(res) / dim
    K[0, 0] *= k
    K[1, 1] *= k
    K[0, 2] -= W / 2.0 - dim / 2.0
    K[1, 2] -= H / 2.0 - dim / 2.0
    K[0, 2] *= k
    K[1, 2] *= k
    return K
