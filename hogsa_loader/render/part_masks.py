"""Part masks rendered from the annotated meshes, for datasets that ship no masks.

Real ARCTIC and H2O have no per-image hand/object masks (only the generated world writes
``masks/``). HOGS training (where the photometric loss applies) and the background plates
(which pixels show background) need one per (frame, view): :func:`pose_meshes` poses the
annotated meshes and :func:`render_part_mask` rasterises them. Part ids are
:data:`~hogsa_loader.assets.conventions.MASK_IDS` (1 right hand, 2 left hand, 3 object
top, 4 object bottom, 0 background).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from hogsa_loader.assets.conventions import MASK_IDS
from hogsa_loader.assets.objects.articulated import articulate
from hogsa_loader.assets.objects.template import BOTTOM, TOP, ObjectTemplate
from hogsa_loader.assets.types import CameraTrack, SequenceData
from hogsa_loader.render.mesh_raster import MeshPart, render_meshes

__all__ = ["PosedMeshes", "object_part_meshes", "pose_meshes", "render_part_mask", "render_camera_mask", "inside_image"]

_F32 = torch.float32


@dataclass
class PosedMeshes:
    """World-space meshes of the hands and object over some frames of a sequence.

    Attributes:
        frames: (N,) frame indices of the sequence, in the order of the vertex arrays.
        meshes: ``(part id, verts (N, V, 3) float32, faces (Fm, 3) int64)`` per mesh.
    """

    frames: np.ndarray
    meshes: list[tuple[int, Tensor, Tensor]]

    def index(self, frame: int) -> int:
        """Position of sequence frame ``frame`` in :attr:`frames`."""
        hit = np.nonzero(self.frames == frame)[0]
        if hit.size == 0:
            raise KeyError(f"frame {frame} was not posed (posed frames: {self.frames.tolist()})")
        return int(hit[0])

    def points(self, i: int) -> np.ndarray:
        """(P, 3) float64 every mesh vertex of posed frame ``i`` (crop boxes)."""
        return np.concatenate([v[i].double().numpy() for _, v, _ in self.meshes])

    def parts(self, i: int) -> list[MeshPart]:
        """MeshParts of posed frame ``i`` (flat colour; only the part ids matter)."""
        out = []
        for pid, verts, faces in self.meshes:
            grey = torch.full((verts.shape[1], 3), 0.5, dtype=_F32)
            out.append(MeshPart(verts[i], faces, pid, vertex_colors=grey))
        return out


def object_part_meshes(template: ObjectTemplate) -> list[tuple[int, np.ndarray, np.ndarray, bool]]:
    """The object's meshes by part: ``(mask id, verts (Vp, 3), faces (Fp, 3), is_top)``.

    The textured mesh (``tex_*``, labelled by ``tex_parts``) when the template has one,
    else ``verts``/``faces``/``parts``. Parts without a face (the top of a rigid object)
    are left out.
    """
    if template.has_texture and template.tex_parts is not None:
        verts, faces, labels = template.tex_verts, template.tex_faces, template.tex_parts
    else:
        verts, faces, labels = template.verts, template.faces, template.parts
    out = []
    for part, key in ((TOP, "object_top"), (BOTTOM, "object_bottom")):
        sel = labels == part
        keep = sel[faces].all(1)
        if not keep.any():
            continue
        new = np.cumsum(sel) - 1
        out.append((MASK_IDS[key], np.asarray(verts)[sel], new[faces[keep]], part == TOP))
    return out


def pose_meshes(
    seq: SequenceData, frames: Sequence[int], mano_layers: Mapping[str, torch.nn.Module], template: ObjectTemplate
) -> PosedMeshes:
    """Pose both hands and the object at the given frames of a sequence (world frame).

    Hands: the MANO layers (``flat_hand_mean=False``, the
    :class:`~hogsa_loader.assets.types.HandTrack` convention) posed with the frame's
    parameters. Object: the template's textured mesh when it has one (the mesh the world
    renders), else ``verts``/``faces``, split into its top and bottom parts by the part
    labels (a face belongs to a part when its three vertices do, as the world does), posed
    by :func:`~hogsa_loader.assets.objects.articulated.articulate`. A rigid (H2O) template has
    every vertex in the bottom part, so it is all part id 4.

    Args:
        seq: annotations (hands relative to the MANO mean, object θ / axis-angle / metres).
        frames: frame indices into the sequence.
        mano_layers: ``{"right": MANOLayer, "left": MANOLayer}`` with ``flat_hand_mean=False``.
        template: the object's template.
    """
    idx = np.asarray(list(frames), dtype=np.int64)
    meshes: list[tuple[int, Tensor, Tensor]] = []
    with torch.no_grad():
        for side in ("right", "left"):
            layer, h = mano_layers[side], getattr(seq, side)
            dt = layer.v_template.dtype  # type: ignore[union-attr]
            out = layer(
                global_orient=torch.as_tensor(h.rot[idx], dtype=dt),
                hand_pose=torch.as_tensor(h.pose[idx], dtype=dt),
                betas=torch.as_tensor(np.repeat(np.asarray(h.betas)[None], len(idx), 0), dtype=dt),
                transl=torch.as_tensor(h.trans[idx], dtype=dt),
            )
            faces = layer.faces.detach().cpu().long()  # type: ignore[union-attr]
            meshes.append((MASK_IDS[side], out.vertices.to(_F32), faces))
        o = seq.object
        f64 = torch.float64
        angle = torch.as_tensor(o.arti[idx], dtype=f64)
        rot, trans = torch.as_tensor(o.rot[idx], dtype=f64), torch.as_tensor(o.trans[idx], dtype=f64)
        for pid, verts, faces, is_top in object_part_meshes(template):
            pts = torch.as_tensor(verts, dtype=f64)[None].expand(len(idx), -1, -1)
            top = torch.full((verts.shape[0],), bool(is_top))
            meshes.append((pid, articulate(pts, top, angle, rot, trans).to(_F32), torch.as_tensor(faces)))
    return PosedMeshes(frames=idx, meshes=meshes)


def inside_image(K_render: np.ndarray, K_full: np.ndarray, width: int, height: int, size: int) -> np.ndarray:
    """(size, size) bool: pixels whose centre falls inside the full original image.

    Args:
        K_render: (3, 3) render intrinsics of the (size × size) image (pixel centres at
            i + 0.5).
        K_full: (3, 3) label (OpenCV-convention) intrinsics of the full image, same camera.
        width, height: full image size.
    """
    c = np.arange(size) + 0.5
    pix = np.stack(np.broadcast_arrays(c[None, :], c[:, None], np.ones((size, size))), -1)  # (y, x, [u, v, 1])
    full = pix @ (np.asarray(K_full, np.float64) @ np.linalg.inv(np.asarray(K_render, np.float64))).T
    x, y = full[..., 0] / full[..., 2], full[..., 1] / full[..., 2]
    return (x >= -0.5) & (x <= width - 0.5) & (y >= -0.5) & (y <= height - 0.5)


def render_part_mask(
    posed: PosedMeshes,
    frame: int,
    world2cam: np.ndarray,
    K_render: np.ndarray,
    size: int,
    *,
    K_full: np.ndarray,
    full_size: tuple[int, int],
    supersample: int = 1,
) -> np.ndarray:
    """(size, size) uint8 part mask of one (frame, view).

    The meshes are rasterised with :func:`~hogsa_loader.render.mesh_raster.render_meshes`
    (z-buffer, nearest surface wins); with ``supersample`` s a pixel takes the part of the
    nearest of its s×s samples, so every pixel with partial coverage gets a part id (like
    resized mask files dilated by one pixel). Pixels whose centre lies outside the full
    original image are set to 0, as the world does for crop padding (full-image pixel i
    covers label coordinates [i − 0.5, i + 0.5]).

    Args:
        posed: meshes from :func:`pose_meshes`.
        frame: sequence frame index (must be among the posed frames).
        world2cam: (4, 4) extrinsics.
        K_render: (3, 3) render intrinsics at (size, size).
        K_full, full_size: label intrinsics and (width, height) of the full original image.
        supersample: s ≥ 1 samples per pixel side (a pixel gets the nearest sample's part).
    """
    out = render_meshes(
        posed.parts(posed.index(frame)),
        torch.as_tensor(world2cam, dtype=_F32),
        torch.as_tensor(K_render, dtype=_F32),
        size,
        size,
        supersample=supersample,
    )
    mask = out.part_id.numpy().astype(np.uint8)
    return mask * inside_image(K_render, K_full, full_size[0], full_size[1], size)


def render_camera_mask(
    posed: PosedMeshes, cam: CameraTrack, frame: int, K_render: np.ndarray, size: int, supersample: int = 1
) -> np.ndarray:
    """(size, size) uint8 part mask of ``frame`` seen by the dataset camera ``cam``.

    :func:`render_part_mask` with the camera's extrinsics, full-image intrinsics and size
    of that frame.

    Args:
        posed: meshes from :func:`pose_meshes`.
        cam: the view's camera track.
        frame: sequence frame index (must be among the posed frames).
        K_render: (3, 3) render intrinsics at (size, size).
        size: side of the square mask in pixels.
        supersample: s ≥ 1 samples per pixel side.
    """
    return render_part_mask(
        posed,
        frame,
        cam.world2cam[frame],
        K_render,
        size,
        K_full=cam.K[frame],
        full_size=(cam.width, cam.height),
        supersample=supersample,
    )
