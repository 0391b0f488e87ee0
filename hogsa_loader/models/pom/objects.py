"""Per-object geometry caches used by POM (canonical frame, both parts, any ARCTIC template).

For each :class:`~hogsa_loader.assets.objects.template.ObjectTemplate` (built lazily, cached):

* ``points``: area-weighted surface samples of the whole mesh with their part (ContactNet
  input, GraspTTA's resampled object cloud);
* one SDF grid per part in that part's own frame (penetration loss; sign by ray parity);
* the triangles of each part (ray-parity metrics), dense surface samples of each part in a
  KD-tree (surface distances), and the 5 mm voxel centres inside each part (intersection
  volume).

Frames (ARCTIC's): world ``p_w = R(ω) p_c + t``; the canonical frame of the base
(bottom) part is the object frame; a top-part point ``q`` sits at ``p_c = R_z(-θ) q``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from hogsa_loader.assets.objects.articulated import articulation_matrix
from hogsa_loader.assets.objects.template import BOTTOM, TOP, ObjectTemplate
from hogsa_loader.geometry.rotations import axis_angle_to_matrix
from hogsa_loader.models.pom.geometry import build_sdf_grid, grid_inside, sample_surface

__all__ = ["ABSENT_PART_DISTANCE", "ObjectGeometry", "ObjectSet", "to_canonical", "to_world", "part_frames"]

#: Voxel pitch of GraspTTA's intersection volume (m).
VOLUME_PITCH = 0.005
#: Signed distance of every point to a part an object does not have: infinitely far outside.
ABSENT_PART_DISTANCE = math.inf


def to_canonical(points: Tensor, rot: Tensor, trans: Tensor) -> Tensor:
    """World -> object canonical frame.

    Args:
        points: (B, P, 3) world points; rot: (B, 3) axis-angle ω; trans: (B, 3) metres.

    Returns:
        (B, P, 3) ``R(ω)^T (p - t)``.
    """
    R = axis_angle_to_matrix(rot).to(points.dtype)
    return (points - trans[:, None].to(points.dtype)) @ R


def to_world(points: Tensor, rot: Tensor, trans: Tensor) -> Tensor:
    """Object canonical -> world: ``R(ω) p + t`` for (B, P, 3) points."""
    R = axis_angle_to_matrix(rot).to(points.dtype)
    return points @ R.transpose(-1, -2) + trans[:, None].to(points.dtype)


def part_frames(points_c: Tensor, arti: Tensor) -> dict[int, Tensor]:
    """Canonical points expressed in each part's own frame.

    Args:
        points_c: (B, P, 3) canonical points; arti: (B,) θ.

    Returns:
        ``{BOTTOM: points_c, TOP: R_z(-θ)^T points_c}``.
    """
    Rt = articulation_matrix(arti).to(points_c.dtype)
    return {BOTTOM: points_c, TOP: points_c @ Rt}


@dataclass
class ObjectGeometry:
    """Cached geometry of one template (canonical frame, numpy/torch on CPU).

    Attributes:
        name: object name.
        points: (N, 3) surface samples (whole mesh, canonical, θ = 0).
        points_top: (N,) bool, True for samples on the top part.
        sdf: part -> :class:`SDFGrid` in that part's frame.
        tris: part -> (F_p, 3, 3) triangles.
        trees: part -> cKDTree of dense surface samples of the part.
        voxels: part -> (M_p, 3) 5 mm voxel centres inside the part.
        vox_grid: part -> ((xs, ys, zs), inside (nz, ny, nx) bool): the same voxels as a grid.
        diameter: metres.

    A rigid object (every face in the bottom part, as H2O's) has no top entries: the
    per-part dictionaries hold only the parts that have faces (:attr:`parts`).
    """

    name: str
    points: Tensor
    points_top: Tensor
    sdf: dict
    tris: dict
    trees: dict
    voxels: dict
    vox_grid: dict
    diameter: float

    @property
    def parts(self) -> tuple[int, ...]:
        """The parts with faces: ``(TOP, BOTTOM)``, or ``(BOTTOM,)`` for a rigid object."""
        return tuple(self.sdf)

    @classmethod
    def build(
        cls, template: ObjectTemplate, n_points: int = 2048, sdf_voxel: float = 0.002, seed: int = 0
    ) -> "ObjectGeometry":
        rng = np.random.default_rng(seed)
        pts, fid = sample_surface(template.verts, template.faces, n_points, rng)
        face_part = template.parts[template.faces[:, 0]]
        sdf, tris, trees, voxels, vox_grid = {}, {}, {}, {}, {}
        for part in (TOP, BOTTOM):
            v, f = template.part_mesh(part)
            if len(f) == 0:
                continue
            sdf[part] = build_sdf_grid(v, f, voxel=sdf_voxel, seed=seed + part)
            tris[part] = torch.as_tensor(v[f], dtype=torch.float64)
            dense, _ = sample_surface(v, f, 60_000, rng)
            trees[part] = cKDTree(np.concatenate([dense, v]).astype(np.float64))
            lo, hi = v.min(0), v.max(0)
            axes = [np.arange(lo[i] + VOLUME_PITCH / 2, hi[i], VOLUME_PITCH) for i in range(3)]
            inside = grid_inside(v[f].astype(np.float64), *axes)  # (nz, ny, nx)
            Z, Y, X = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
            grid = np.stack([X, Y, Z], -1)
            voxels[part] = torch.as_tensor(grid[inside])
            vox_grid[part] = (axes, torch.as_tensor(inside))
        return cls(
            name=template.name,
            points=torch.as_tensor(pts),
            points_top=torch.as_tensor(face_part[fid] == TOP),
            sdf=sdf,
            tris=tris,
            trees=trees,
            voxels=voxels,
            vox_grid=vox_grid,
            diameter=float(template.diameter),
        )


class ObjectSet:
    """Lazily built :class:`ObjectGeometry` of a set of templates, with batched queries.

    Args:
        templates: ``{name: ObjectTemplate}`` (e.g. ``ArcticRoot.object_templates(False)``; kept,
            not copied: an object's template is read when its geometry is first built).
        n_points: surface samples per object.
        sdf_voxel: SDF grid spacing (m).
        seed: sampling seed.
    """

    def __init__(
        self, templates: Mapping[str, ObjectTemplate], n_points: int = 2048, sdf_voxel: float = 0.002, seed: int = 0
    ) -> None:
        self.templates = templates
        self.n_points = n_points
        self.sdf_voxel = sdf_voxel
        self.seed = seed
        self._geo: dict[str, ObjectGeometry] = {}

    def geometry(self, name: str) -> ObjectGeometry:
        if name not in self._geo:
            if name not in self.templates:
                raise KeyError(f"unknown object {name!r}; known: {sorted(self.templates)}")
            self._geo[name] = ObjectGeometry.build(self.templates[name], self.n_points, self.sdf_voxel, self.seed)
        return self._geo[name]

    def points(
        self, names: Sequence[str], arti: Tensor, count: int | None = None, generator: torch.Generator | None = None
    ) -> tuple[Tensor, Tensor]:
        """Canonical surface samples articulated by θ.

        Args:
            names: B object names; arti: (B,) θ.
            count: samples per object (<= n_points; None = all); a random subset when a
                ``generator`` is given, else the first ``count`` (a fixed subset).

        Returns:
            points (B, N, 3) in the canonical frame, is_top (B, N) bool.
        """
        dtype, device = arti.dtype, arti.device
        pts, top = [], []
        n = count or self.n_points
        for name in names:
            g = self.geometry(name)
            if generator is not None:
                idx = torch.randperm(g.points.shape[0], generator=generator)[:n]
            else:
                idx = torch.arange(n)
            pts.append(g.points[idx])
            top.append(g.points_top[idx])
        P = torch.stack(pts).to(device, dtype)
        T = torch.stack(top).to(device)
        R = articulation_matrix(arti).to(dtype)
        P = torch.where(T[..., None], P @ R.transpose(-1, -2), P)
        return P, T

    def part_sdf(self, points_c: Tensor, names: Sequence[str], arti: Tensor) -> dict[int, Tensor]:
        """Signed distance to each part of canonical points.

        Loops over the distinct objects of the batch (not over samples).

        Args:
            points_c: (B, P, 3) canonical points; names: B names; arti: (B,) θ.

        Returns:
            ``{TOP: (B, P), BOTTOM: (B, P)}`` signed distances (m, negative inside),
            differentiable in the points; a part an object does not have is
            :data:`ABSENT_PART_DISTANCE` away from every point (no gradient).
        """
        frames = part_frames(points_c, arti)
        names = list(names)
        out = {}
        for part in (TOP, BOTTOM):
            d = torch.empty(points_c.shape[:2], dtype=points_c.dtype, device=points_c.device)
            for name in sorted(set(names)):
                sel = torch.tensor([n == name for n in names], device=points_c.device)
                g = self.geometry(name)
                if part not in g.sdf:
                    d = d.index_put((sel.nonzero().squeeze(-1),), d.new_tensor(ABSENT_PART_DISTANCE))
                    continue
                grid = g.sdf[part]
                if grid.values.device != points_c.device:
                    grid = g.sdf[part] = grid.to(points_c.device)
                d = d.index_put((sel.nonzero().squeeze(-1),), grid.query(frames[part][sel]))
            out[part] = d
        return out

    def sdf(self, points_c: Tensor, names: Sequence[str], arti: Tensor) -> Tensor:
        """Signed distance to the object (union of parts) of canonical points: (B, P) (m,
        negative inside), differentiable in the points; see :meth:`part_sdf`."""
        parts = self.part_sdf(points_c, names, arti)
        return torch.minimum(parts[TOP], parts[BOTTOM])
