"""Articulation of ARCTIC objects (two rigid parts joined by one revolute hinge).

:func:`articulate` poses points, :class:`ArticulatedObjectLayer` a fixed set of objects
with ARCTIC's ``common/object_tensors.py`` conventions (listed on the layer).
"""

from __future__ import annotations

from typing import Mapping, Optional, Sequence, Union

import numpy as np
import torch
from torch import Tensor

from hogsa_loader.assets.objects.template import BOTTOM, TOP, ObjectTemplate
from hogsa_loader.geometry.rotations import axis_angle_to_matrix, rotation_about_axis

__all__ = ["ARTICULATION_AXIS", "articulation_matrix", "articulate", "ArticulatedObjectLayer"]

#: Axis-angle direction of the articulation: the top part rotates by θ·(0,0,-1).
ARTICULATION_AXIS: tuple[float, float, float] = (0.0, 0.0, -1.0)

#: parts_ids value of the articulated (top) part = parts.json 0 + 1.
TOP_ID = TOP + 1
#: parts_ids value of the base (bottom) part = parts.json 1 + 1.
BOTTOM_ID = BOTTOM + 1


def _flat_angle(angle: Tensor) -> Tensor:
    """(B,) or (B, 1) angles -> (B,)."""
    if angle.dim() == 2 and angle.shape[-1] == 1:
        return angle[:, 0]
    if angle.dim() != 1:
        raise ValueError(f"angle must have shape (B,) or (B, 1), got {tuple(angle.shape)}")
    return angle


def articulation_matrix(angle: Tensor) -> Tensor:
    """Rotation of the top part, ``R_z(-θ)`` (axis-angle ``θ·(0,0,-1)``).

    Args:
        angle: (B,) or (B, 1) articulation angles θ in radians.

    Returns:
        (B, 3, 3) rotation matrices.
    """
    return rotation_about_axis(_flat_angle(angle), ARTICULATION_AXIS)


def articulate_parts(points: Tensor, is_top: Tensor, angle: Tensor) -> Tensor:
    """Rotate the top points about the hinge; bottom points are unchanged.

    Args:
        points: (B, N, 3) canonical points.
        is_top: (N,) or (B, N) bool, True for points of the top (articulated) part.
        angle: (B,) or (B, 1) articulation angles θ.

    Returns:
        (B, N, 3) points with ``R_z(-θ) p`` on the top part and ``p`` elsewhere.
    """
    rot = articulation_matrix(angle).to(points.dtype)
    rotated = points @ rot.transpose(-1, -2)
    if is_top.dim() == 1:
        is_top = is_top[None, :]
    return torch.where(is_top[..., None], rotated, points)


def global_transform(points: Tensor, global_orient: Tensor, transl: Optional[Tensor]) -> Tensor:
    """Apply the global rigid pose ``p' = R(ω) p + t``.

    Args:
        points: (B, N, 3) points.
        global_orient: (B, 3) axis-angle ω.
        transl: (B, 3) translation in metres, or None for zero.

    Returns:
        (B, N, 3) posed points.
    """
    rot = axis_angle_to_matrix(global_orient).to(points.dtype)
    out = points @ rot.transpose(-1, -2)
    if transl is not None:
        out = out + transl[:, None, :].to(points.dtype)
    return out


def articulate(
    points: Tensor, is_top: Tensor, angle: Tensor, global_orient: Tensor, transl: Optional[Tensor]
) -> Tensor:
    """Pose canonical object points (ARCTIC's hinge convention).

    ``top: p' = R(ω) R_z(-θ) p + t``, ``bottom: p' = R(ω) p + t``.

    Args:
        points: (B, N, 3) canonical points (metres).
        is_top: (N,) or (B, N) bool mask of the top (articulated) points.
        angle: (B,) or (B, 1) articulation angle θ (radians).
        global_orient: (B, 3) axis-angle ω.
        transl: (B, 3) translation t (metres) or None.

    Returns:
        (B, N, 3) posed points.
    """
    return global_transform(articulate_parts(points, is_top, angle), global_orient, transl)


# --------------------------------------------------------------------------------------
# Stacked templates (ARCTIC ObjectTensors)
# --------------------------------------------------------------------------------------


def _pad_stack(arrays: Sequence[np.ndarray], length: int, fill: float = 0) -> np.ndarray:
    """Stack (n_i, ...) arrays into (K, length, ...) padded with ``fill``."""
    first = arrays[0]
    out = np.full((len(arrays), length) + first.shape[1:], fill, dtype=first.dtype)
    for i, a in enumerate(arrays):
        out[i, : a.shape[0]] = a
    return out


def _sub_part_ids(template: ObjectTemplate) -> np.ndarray:
    """parts_ids of the 600 sub-points: part of the nearest mesh vertex, plus 1."""
    from scipy.spatial import cKDTree  # deferred: scipy.spatial adds ~1 s to every process importing objects

    sub = np.concatenate([template.sub_top, template.sub_bottom], axis=0)
    _, nearest = cKDTree(template.verts.astype(np.float64)).query(sub.astype(np.float64))
    return template.parts[nearest] + 1


class ArticulatedObjectLayer(torch.nn.Module):
    """Poses a fixed set of ARCTIC-style articulated objects, batched.

    Conventions (ARCTIC's ``common/object_tensors.py``):

    * An object pose is 7 numbers: the articulation angle θ (radians), a global rotation ω
      (axis-angle, 3) and a translation t (metres, 3).
    * The hinge is the **z axis of the canonical frame through the canonical origin**. The top
      part (``parts.json`` value 0, ``parts_ids == 1``) is first rotated by
      ``R_z(-θ)`` = axis-angle ``θ · (0, 0, -1)``; then every point gets the global pose:

      - top point:    ``p' = R(ω) · R_z(-θ) · p + t``
      - bottom point: ``p' = R(ω) · p + t``

    * Keypoints (``kp3d``: 16 top then 16 bottom), box corners (``bbox3d``: 8 top then 8
      bottom) and the 600 sub-sampled points (``v_sub``: 300 top then 300 bottom) are the
      fixed template points posed with the same transforms; they are not recomputed from the
      vertices.
    * Vertex buffers are zero-padded to the longest object (``mask``/``v_len`` tell the real
      vertices; ``parts_ids`` = ``parts.json + 1`` with 0 on padding).

    Buffers follow ARCTIC's ``ObjectTensors``: for K objects and the longest vertex count
    ``Vmax``,

    * ``v`` (K, Vmax, 3), ``v_len`` (K,), ``f`` (K, Fmax, 3) faces padded with 0,
      ``f_len`` (K,), ``mask`` (K, Vmax) bool,
    * ``parts_ids`` (K, Vmax) = ``parts.json + 1`` (1 = top, 2 = bottom, 0 = padding),
    * ``v_sub`` (K, 600, 3) = 300 top then 300 bottom samples, ``parts_sub_ids`` (K, 600)
      = part of the nearest mesh vertex + 1,
    * ``kp`` (K, 32, 3) = 16 top then 16 bottom keypoints, ``bbox`` (K, 16, 3) = 8 top
      then 8 bottom corners, ``diameter`` (K,) metres.

    Templates are stored in float32; ``.to(dtype/device)`` moves them. Posing is
    differentiable with respect to angles, orientation and translation.

    Args:
        templates: the objects; a name's index in this list is its object index.
    """

    v: Tensor
    v_len: Tensor
    f: Tensor
    f_len: Tensor
    mask: Tensor
    parts_ids: Tensor
    v_sub: Tensor
    parts_sub_ids: Tensor
    kp: Tensor
    bbox: Tensor
    diameter: Tensor

    def __init__(self, templates: Union[Sequence[ObjectTemplate], Mapping[str, ObjectTemplate]]):
        super().__init__()
        if isinstance(templates, Mapping):
            templates = list(templates.values())
        templates = list(templates)
        if not templates:
            raise ValueError("ArticulatedObjectLayer needs at least one template")
        self.names: list[str] = [t.name for t in templates]
        if len(set(self.names)) != len(self.names):
            raise ValueError(f"duplicate object names: {self.names}")
        self.name_to_index: dict[str, int] = {n: i for i, n in enumerate(self.names)}

        v_len = np.array([t.verts.shape[0] for t in templates], dtype=np.int64)
        f_len = np.array([t.faces.shape[0] for t in templates], dtype=np.int64)
        vmax, fmax = int(v_len.max()), int(f_len.max())
        self.register_buffer("v", torch.from_numpy(_pad_stack([t.verts for t in templates], vmax)))
        self.register_buffer("v_len", torch.from_numpy(v_len))
        self.register_buffer("f", torch.from_numpy(_pad_stack([t.faces for t in templates], fmax)))
        self.register_buffer("f_len", torch.from_numpy(f_len))
        self.register_buffer("mask", torch.arange(vmax)[None, :] < torch.from_numpy(v_len)[:, None])
        self.register_buffer("parts_ids", torch.from_numpy(_pad_stack([t.parts + 1 for t in templates], vmax)))
        self.register_buffer(
            "v_sub", torch.from_numpy(np.stack([np.concatenate([t.sub_top, t.sub_bottom]) for t in templates]))
        )
        self.register_buffer("parts_sub_ids", torch.from_numpy(np.stack([_sub_part_ids(t) for t in templates])))
        self.register_buffer(
            "kp", torch.from_numpy(np.stack([np.concatenate([t.kp_top, t.kp_bottom]) for t in templates]))
        )
        self.register_buffer(
            "bbox", torch.from_numpy(np.stack([np.concatenate([t.bbox_top, t.bbox_bottom]) for t in templates]))
        )
        self.register_buffer("diameter", torch.tensor([t.diameter for t in templates], dtype=torch.float32))
        n_kp = templates[0].kp_top.shape[0]
        n_bb = templates[0].bbox_top.shape[0]
        self.register_buffer("kp_is_top", torch.arange(self.kp.shape[1]) < n_kp, persistent=False)
        self.register_buffer("bbox_is_top", torch.arange(self.bbox.shape[1]) < n_bb, persistent=False)

    # ----------------------------------------------------------------------------------

    def indices(self, names: Sequence[str]) -> Tensor:
        """(B,) long object indices of ``names`` (KeyError for unknown names)."""
        try:
            idx = [self.name_to_index[n] for n in names]
        except KeyError as exc:
            raise KeyError(f"unknown object {exc.args[0]!r}; known: {self.names}") from None
        return torch.tensor(idx, dtype=torch.long, device=self.v.device)

    def forward_template(self, names: Sequence[str]) -> dict[str, Tensor]:
        """Unposed (canonical) data of ``names``; same keys as :meth:`forward`.

        Args:
            names: B object names.

        Returns:
            dict with ``v`` (B, L, 3) (L = longest ``v_len`` in the batch), ``v_len``,
            ``f`` (B, Lf, 3), ``f_len``, ``mask`` (B, L), ``parts_ids`` (B, L),
            ``v_sub`` (B, 600, 3), ``parts_sub_ids`` (B, 600), ``kp3d`` (B, 32, 3),
            ``bbox3d`` (B, 16, 3), ``diameter`` (B,).
        """
        idx = self.indices(names)
        v_len = self.v_len[idx]
        f_len = self.f_len[idx]
        length = int(v_len.max())
        flength = int(f_len.max())
        return {
            "v": self.v[idx, :length],
            "v_len": v_len,
            "f": self.f[idx, :flength],
            "f_len": f_len,
            "mask": self.mask[idx, :length],
            "parts_ids": self.parts_ids[idx, :length],
            "v_sub": self.v_sub[idx],
            "parts_sub_ids": self.parts_sub_ids[idx],
            "kp3d": self.kp[idx],
            "bbox3d": self.bbox[idx],
            "diameter": self.diameter[idx],
        }

    def forward(
        self, angles: Tensor, global_orient: Tensor, transl: Optional[Tensor], names: Sequence[str]
    ) -> dict[str, Tensor]:
        """Pose a batch of objects (ARCTIC ``ObjectTensors.forward``).

        Args:
            angles: (B, 1) or (B,) articulation angles θ (radians).
            global_orient: (B, 3) axis-angle ω.
            transl: (B, 3) translation in metres, or None.
            names: B object names.

        Returns:
            the dict of :meth:`forward_template` with ``v``, ``v_sub``, ``kp3d`` and
            ``bbox3d`` posed; padded vertices are zero.
        """
        out = self.forward_template(names)
        batch = len(names)
        angles = _flat_angle(angles)
        if angles.shape[0] != batch or global_orient.shape != (batch, 3):
            raise ValueError(
                f"batch of {batch} names needs angles (B,1) and global_orient (B,3), got "
                f"{tuple(angles.shape)} and {tuple(global_orient.shape)}"
            )
        dtype = global_orient.dtype
        pose = dict(angle=angles, global_orient=global_orient, transl=transl)
        v = articulate(out["v"].to(dtype), out["parts_ids"] == TOP_ID, **pose)
        out["v"] = v * out["mask"][..., None].to(dtype)
        out["v_sub"] = articulate(out["v_sub"].to(dtype), out["parts_sub_ids"] == TOP_ID, **pose)
        out["kp3d"] = articulate(out["kp3d"].to(dtype), self.kp_is_top, **pose)
        out["bbox3d"] = articulate(out["bbox3d"].to(dtype), self.bbox_is_top, **pose)
        out["diameter"] = out["diameter"].to(dtype)
        return out

    def extra_repr(self) -> str:
        return f"objects={self.names}, Vmax={self.v.shape[1]}"
