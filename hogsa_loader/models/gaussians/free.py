"""Free (original 3DGS) Gaussians skinned by the transform of their nearest template vertex."""

from __future__ import annotations

import math
from typing import Optional, Union

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor, nn

from hogsa_loader.geometry.quaternion import matrix_to_quat, orthonormalize, quat_to_matrix
from hogsa_loader.models.gaussians.gaussian_set import GaussianSet, SplatAppearance
from hogsa_loader.models.gaussians.mesh_bound import (
    DEFAULT_COVERAGE,
    DEFAULT_OPACITY,
    face_frames,
    face_moment_scales,
    spread_barycentrics,
)

__all__ = ["FREE_INITS", "surface_samples", "FreeGaussians"]

#: Where free Gaussians start: one per mesh vertex, or k per face (GaMeS layout).
FREE_INITS = ("vertices", "faces")

ArrayLike = Union[Tensor, np.ndarray]


def surface_samples(faces: Tensor, num_verts: int, init: str = "vertices", k: int = 2) -> tuple[Tensor, Tensor]:
    """Surface points as (face, barycentric) pairs.

    Args:
        faces: (F, 3) int64.
        num_verts: V.
        init: ``"vertices"``: one sample per vertex used by a face, expressed as a corner
            (one-hot weights) of the first face that uses it, in vertex order;
            ``"faces"``: k samples per face at :func:`spread_barycentrics` (face-major).
        k: samples per face for ``"faces"``.

    Returns:
        face_idx (N,) int64 and bary (N, 3) float64.
    """
    if init == "faces":
        F_ = faces.shape[0]
        face_idx = torch.arange(F_, dtype=torch.long).repeat_interleave(k)
        return face_idx, spread_barycentrics(k).repeat(F_, 1)
    if init != "vertices":
        raise ValueError(f"init must be one of {FREE_INITS}, got {init!r}")
    flat = faces.reshape(-1).cpu()
    big = flat.numel()
    first = torch.full((num_verts,), big, dtype=torch.long)
    first = first.scatter_reduce(0, flat, torch.arange(big), reduce="amin")  # first use
    used = torch.nonzero(first < big).squeeze(1)
    pos = first[used]
    bary = torch.zeros(used.numel(), 3, dtype=torch.float64)
    bary[torch.arange(used.numel()), pos % 3] = 1.0
    return pos // 3, bary


def _knn_scale(points: Tensor, n_neighbours: int = 3) -> Tensor:
    """3DGS initial scale: sqrt of the mean squared distance to the 3 nearest others."""
    p = points.detach().cpu().double().numpy()
    kk = min(n_neighbours + 1, p.shape[0])
    d, _ = cKDTree(p).query(p, k=kk)
    d = np.asarray(d).reshape(p.shape[0], kk)[:, 1:]
    msd = (d**2).mean(1) if d.shape[1] else np.ones(p.shape[0])
    return torch.from_numpy(np.sqrt(np.maximum(msd, 1e-14)))


class FreeGaussians(SplatAppearance):
    """Free Gaussians bound to template vertices.

    The ablation of HOGS's mesh-bound Gaussians: every Gaussian has its own canonical mean,
    rotation and scale (gsplat's parameterisation: raw quaternion, log scale, opacity logit,
    SH ``sh_dc``/``sh_rest``), bound at initialisation to the nearest vertex of the template
    (for a Gaussian started on a face: the nearest corner of that face; for one started at a
    vertex: that vertex).
    Posing applies that vertex's transform:

    mu' = A_v (mu + d_v) + t_v,     R' = orth(A_v) R,     s' = s

    where ``(A_v, t_v)`` maps the vertex's rest position to its posed one (hands: the LBS
    blend ``sum_j w_vj G_j``; objects: the rigid transform of the vertex's part), ``d_v`` is
    the vertex's rest-pose displacement before skinning (hands: shape + pose blend shapes;
    objects: 0) and ``orth`` is :func:`~hogsa_loader.geometry.quaternion.orthonormalize`.
    A Gaussian initialised at a vertex therefore moves exactly like that vertex.

    Notation: B samples, V template vertices, N Gaussians, K SH coefficients.

    Learnable parameters (checkpoint names): ``means`` (N, 3) canonical, ``quats`` (N, 4)
    wxyz (normalised when used), ``log_scales`` (N, 3), ``sh_dc`` (N, 1, 3), ``sh_rest``
    (N, K - 1, 3), ``opacity_logits`` (N,); buffer ``binding`` (N,) int64 vertex index
    (saved too); ``normals0`` (N, 3) canonical surface normals (not saved, derived).

    Args:
        verts: (V, 3) canonical template vertices.
        faces: (F, 3) triangles.
        init: ``"vertices"`` (one isotropic Gaussian per vertex, scale = RMS distance to
            the 3 nearest other vertices, identity rotation: the 3DGS initialisation) or
            ``"faces"`` (k per face with the GaMeS initial rotation and scales, so that
            both variants start from the same Gaussians).
        k: Gaussians per face for ``init="faces"``.
        sh_degree: 0..3.
        colors: initial RGB, (N, 3) or (3,); default mid grey. Use
            :func:`surface_samples` to know where the N Gaussians are.
        init_opacity: initial opacity.
        normal_eps: thickness for ``init="faces"``.
        dtype: parameter dtype.
    """

    binding: Tensor

    def __init__(
        self,
        verts: ArrayLike,
        faces: ArrayLike,
        *,
        init: str = "vertices",
        k: int = 2,
        sh_degree: int = 3,
        colors: Optional[ArrayLike] = None,
        init_opacity: float = DEFAULT_OPACITY,
        normal_eps: float = 1e-8,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        super().__init__()
        v = torch.as_tensor(np.asarray(verts) if not isinstance(verts, Tensor) else verts.detach()).double()
        f = torch.as_tensor(np.asarray(faces) if not isinstance(faces, Tensor) else faces.detach()).long()
        self.init = init
        self.k = int(k)
        self.num_verts = int(v.shape[0])
        face_idx, bary = surface_samples(f, v.shape[0], init, self.k)
        tri = v[f[face_idx]]  # (N, 3, 3)
        means = torch.einsum("nc,ncd->nd", bary, tri)
        corner = ((tri - means[:, None]) ** 2).sum(-1).argmin(-1)
        binding = f[face_idx, corner]
        N = means.shape[0]
        fn = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)  # area-weighted
        if init == "vertices":
            all_fn = torch.linalg.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]], dim=-1)
            vn = torch.zeros_like(v).index_add_(0, f.reshape(-1), all_fn.repeat_interleave(3, 0))
            fn = vn[binding]
        normals0 = fn / fn.norm(dim=-1, keepdim=True).clamp(min=1e-20)
        if init == "vertices":
            quats = torch.zeros(N, 4, dtype=torch.float64)
            quats[:, 0] = 1.0
            scales = _knn_scale(means)[:, None].expand(N, 3)
        else:
            rot, _ = face_frames(tri)
            sig = face_moment_scales(tri, rot)
            rho = DEFAULT_COVERAGE / math.sqrt(self.k)
            scales = torch.cat([sig * rho, torch.zeros(N, 1, dtype=torch.float64)], -1) + normal_eps
            quats = matrix_to_quat(rot)
        self.means = nn.Parameter(means.to(dtype))
        self.quats = nn.Parameter(quats.to(dtype))
        self.log_scales = nn.Parameter(torch.log(scales).to(dtype))
        self.register_buffer("binding", binding)
        self.register_buffer("normals0", normals0.to(dtype), persistent=False)
        rgb = None if colors is None else torch.as_tensor(colors, dtype=dtype)
        self._init_appearance(N, sh_degree, init_opacity, rgb, dtype)

    def offset_regulariser(self) -> Tensor:
        """Free Gaussians have no vertex offsets: a zero scalar (uniform part API)."""
        return self.means.new_zeros(())

    def gaussians(
        self, vertex_rot: Tensor, vertex_trans: Tensor, vertex_disp: Optional[Tensor] = None, part_id: int = 0
    ) -> GaussianSet:
        """Skin the Gaussians with per-vertex transforms.

        Args:
            vertex_rot: (B, V, 3, 3) linear part ``A_v`` (need not be orthonormal).
            vertex_trans: (B, V, 3) translation ``t_v``.
            vertex_disp: (B, V, 3) rest-pose displacement ``d_v`` or None (zero).
            part_id: part index of every Gaussian.

        Returns:
            :class:`GaussianSet`; normals = the template's surface normal at each
            Gaussian's initial position (vertex normal, or face normal for
            ``init="faces"``) turned by ``orth(A_v)`` (an isotropic Gaussian has no
            shortest axis to take a normal from).
        """
        if vertex_rot.dim() != 4 or vertex_rot.shape[1:] != (self.num_verts, 3, 3):
            raise ValueError(f"vertex_rot must be (B, {self.num_verts}, 3, 3), got {tuple(vertex_rot.shape)}")
        B, N = vertex_rot.shape[0], self.num_gaussians
        A = vertex_rot[:, self.binding]  # (B, N, 3, 3)
        x = self.means[None].to(A.dtype)
        if vertex_disp is not None:
            x = x + vertex_disp[:, self.binding]
        means = torch.einsum("bnij,bnj->bni", A, x) + vertex_trans[:, self.binding]
        R_skin = orthonormalize(A)
        rot = R_skin @ quat_to_matrix(self.quats.to(A.dtype))[None]
        scales = torch.exp(self.log_scales)[None].expand(B, N, 3)
        normals = torch.einsum("bnij,nj->bni", R_skin, self.normals0.to(A.dtype))
        return self._gaussian_set(means, matrix_to_quat(rot), scales, part_id, normals)

    forward = gaussians

    def extra_repr(self) -> str:
        return f"init={self.init}, V={self.num_verts}, N={self.num_gaussians}, sh_degree={self.sh_degree}"
