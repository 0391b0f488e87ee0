"""Rendering a world's cropped images and masks with the project mesh rasteriser."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from hogsa_loader.assets.conventions import (
    BBOX_PIXELS_PER_SCALE,
    CROP_ENLARGE,
    EGO_IMAGE_SIZE,
    MASK_IDS,
    allocentric_bbox,
    cropped_intrinsics,
    project,
    render_intrinsics,
    transform,
    undistort_map,
)
from hogsa_loader.assets.objects.articulated import articulate
from hogsa_loader.assets.objects.template import BOTTOM, TOP, ObjectTemplate
from hogsa_loader.render.mesh_raster import MeshPart, render_meshes
from hogsa_world.hand import HandSpec
from hogsa_world.stage import light_for_camera

__all__ = [
    "HAND_BASE_SKIN",
    "PosedSequence",
    "pose_sequence",
    "crop_boxes",
    "object_meshes",
    "foreground",
    "SubjectRenderer",
]

#: Skin colour the synthetic hand's albedo was painted with; a subject's tone rescales it.
HAND_BASE_SKIN = np.asarray(HandSpec().skin_rgb, dtype=np.float64)
_F32 = torch.float32


@dataclass
class PosedSequence:
    """World-space geometry of every frame of a sequence.

    Attributes:
        hands: side -> (F, V, 3) float32 vertices.
        joints: side -> (F, 21, 3) float64 joints.
        obj_tex: part (TOP/BOTTOM) -> (F, Vp, 3) float32 textured-mesh vertices.
        obj_mesh: (F, V, 3) float64 ``mesh.obj`` vertices (for the crop boxes).
    """

    hands: dict
    joints: dict
    obj_tex: dict
    obj_mesh: np.ndarray


def pose_sequence(layers: dict, mano: dict, obj_params: np.ndarray, template: ObjectTemplate) -> PosedSequence:
    """Pose hands (MANO forward) and object (ARCTIC articulation) from raw parameters.

    Args:
        layers: side -> MANOLayer (flat_hand_mean=False).
        mano: the ``.mano.npy`` dict.
        obj_params: (F, 7) ``.object.npy`` (translation in mm).
        template: the object template.
    """
    hands, joints = {}, {}
    for side, layer in layers.items():
        p = mano[side]
        dt = layer.v_template.dtype
        F = p["rot"].shape[0]
        out = layer(
            global_orient=torch.as_tensor(p["rot"], dtype=dt),
            hand_pose=torch.as_tensor(p["pose"], dtype=dt),
            betas=torch.as_tensor(np.repeat(p["shape"][None], F, 0), dtype=dt),
            transl=torch.as_tensor(p["trans"], dtype=dt),
        )
        hands[side] = out.vertices.to(_F32)
        joints[side] = out.joints.double().numpy()
    op = torch.as_tensor(np.asarray(obj_params, np.float64))
    angle, orient, transl = op[:, 0], op[:, 1:4], op[:, 4:7] / 1000.0

    def pose(points: np.ndarray, is_top: np.ndarray) -> torch.Tensor:
        pts = torch.as_tensor(points, dtype=torch.float64)[None].expand(op.shape[0], -1, -1)
        return articulate(pts, torch.as_tensor(is_top), angle, orient, transl)

    obj_tex = {}
    for part in (TOP, BOTTOM):
        sel = template.tex_parts == part
        obj_tex[part] = pose(template.tex_verts[sel], np.full(int(sel.sum()), part == TOP)).to(_F32)
    obj_mesh = pose(template.verts, template.parts == TOP).numpy()
    return PosedSequence(hands=hands, joints=joints, obj_tex=obj_tex, obj_mesh=obj_mesh)


def crop_boxes(rig, obj_mesh: np.ndarray, size: int) -> np.ndarray:
    """Crop boxes of every allocentric view and frame.

    Args:
        rig: :class:`~hogsa_world.cameras.AlloRig`.
        obj_mesh: (F, V, 3) posed ``mesh.obj`` vertices.

    Returns:
        (8, F, 3) ``(cx, cy, scale)`` (index = view - 1).
    """
    return np.stack([allocentric_bbox(project(transform(rig.world2cam[k], obj_mesh), rig.K[k])) for k in range(8)])


def object_meshes(template: ObjectTemplate) -> dict:
    """Per part (TOP/BOTTOM): faces re-indexed into the part's textured vertices, uv, and
    the shared texture (float tensor in [0, 1])."""
    out: dict = {"texture": torch.as_tensor(template.texture, dtype=_F32) / 255.0}
    for part in (TOP, BOTTOM):
        sel = template.tex_parts == part
        new = np.cumsum(sel) - 1
        keep = sel[template.tex_faces].all(1)
        out[part] = (torch.as_tensor(new[template.tex_faces[keep]]), torch.as_tensor(template.tex_uv[sel], dtype=_F32))
    return out


def foreground(posed: PosedSequence, i: int, hand_faces: dict, hand_colors: dict, meshes: dict) -> list:
    """MeshParts of frame i: right hand, left hand, object top, object bottom (mask ids as part ids)."""
    parts = []
    for side in ("right", "left"):
        parts.append(MeshPart(posed.hands[side][i], hand_faces[side], MASK_IDS[side], vertex_colors=hand_colors[side]))
    for part, key in ((TOP, "object_top"), (BOTTOM, "object_bottom")):
        faces, uv = meshes[part]
        parts.append(MeshPart(posed.obj_tex[part][i], faces, MASK_IDS[key], uv=uv, texture=meshes["texture"]))
    return parts


class SubjectRenderer:
    """Renders the frames of one subject's sequences (cameras, skin and stage fixed).

    ARCTIC's cropped images (``cropped_images/``) are produced directly, without rendering
    full-resolution frames:

    * allocentric views 1..8: the object-centred box of the projected ``mesh.obj`` vertices
      (:func:`~hogsa_loader.assets.conventions.allocentric_bbox`), enlarged 1.5x, rendered at
      ``size x size`` with :func:`~hogsa_loader.assets.conventions.cropped_intrinsics`. The
      static table/room is rendered once per camera at (a fraction of) full resolution and
      warped into each crop; hands and object are rasterised over it. Crop pixels outside the
      full-resolution image are black (as ``cv2.warpAffine`` padding makes them in ARCTIC).
    * egocentric view 0: the whole 2800x2000 frame scaled by the ego scale, rendered
      undistorted (with a margin) and then warped through the lens distortion
      (:func:`~hogsa_loader.assets.conventions.undistort_map` + ``cv2.remap``).

    Masks use ``MASK_IDS`` and share the geometry of their image.

    Args:
        rig: the subject's :class:`~hogsa_world.cameras.AlloRig`.
        ego_K: (3, 3) full-res ego intrinsics; ego_dist: (8,) distortion.
        stage: static MeshParts (table, room).
        hand_faces: side -> (Fh, 3) faces; hand_colors: side -> (V, 3) albedo of this subject.
        cropped_size: allocentric crop side; ego_scale: ego image scale; supersample: s.
    """

    def __init__(
        self,
        rig,
        ego_K: np.ndarray,
        ego_dist: np.ndarray,
        stage: list,
        hand_faces: dict,
        hand_colors: dict,
        cropped_size: int,
        ego_scale: float,
        supersample: int = 1,
    ) -> None:
        self.rig, self.stage, self.size, self.ss = rig, stage, cropped_size, supersample
        self.hand_faces, self.hand_colors = hand_faces, hand_colors
        self.lights = [light_for_camera(w) for w in rig.world2cam]
        # ego: scaled K, distortion maps, and the margin the undistorted render needs
        w, h = EGO_IMAGE_SIZE
        self.ego_w, self.ego_h = int(round(w * ego_scale)), int(round(h * ego_scale))
        self.ego_K = np.diag([ego_scale, ego_scale, 1.0]) @ ego_K
        mx, my = undistort_map(self.ego_K, ego_dist, self.ego_w, self.ego_h)
        self.pad_x = int(np.ceil(max(0.0, -mx.min(), mx.max() - (self.ego_w - 1)))) + 2
        self.pad_y = int(np.ceil(max(0.0, -my.min(), my.max() - (self.ego_h - 1)))) + 2
        self.map_x, self.map_y = mx + self.pad_x, my + self.pad_y
        self.ego_K_pad = self.ego_K.copy()
        self.ego_K_pad[0, 2] += self.pad_x
        self.ego_K_pad[1, 2] += self.pad_y
        self.ego_K_pad = render_intrinsics(self.ego_K_pad)  # cv2.remap below is integer-centred
        self._bg: dict[int, tuple[np.ndarray, float]] = {}

    # ----------------------------------------------------------------------------------
    def background(self, view: int, max_density: float) -> tuple[np.ndarray, float]:
        """Stage image of an allocentric view (1..8) at scale b >= the crops' pixel density."""
        if view not in self._bg:
            b = float(min(1.0, np.ceil(20 * 1.15 * max_density) / 20))
            w, h = self.rig.sizes[view - 1]
            wb, hb = int(round(w * b)), int(round(h * b))
            K = render_intrinsics(np.diag([b, b, 1.0]) @ self.rig.K[view - 1])
            w2c = self.rig.world2cam[view - 1]
            out = render_meshes(
                self.stage,
                torch.as_tensor(w2c, dtype=_F32),
                torch.as_tensor(K, dtype=_F32),
                hb,
                wb,
                light=self.lights[view - 1],
                background=(0.1, 0.1, 0.1),
                supersample=1,
            )
            self._bg[view] = (np.ascontiguousarray(out.rgb.numpy()), b)
        return self._bg[view]

    def render_allo(self, view: int, bbox: np.ndarray, fg: list, max_density: float) -> tuple[np.ndarray, np.ndarray]:
        """Cropped image (size, size, 3) uint8 RGB and mask (size, size) uint8 of one view."""
        size = self.size
        K = self.rig.K[view - 1]
        Kc = render_intrinsics(cropped_intrinsics(K, bbox, size))
        bg, b = self.background(view, max_density)
        side = CROP_ENLARGE * bbox[2] * BBOX_PIXELS_PER_SCALE
        k = size / side
        ox, oy = bbox[0] - side / 2, bbox[1] - side / 2
        # crop pixel i shows label coordinate ox + i / k; background pixel q shows q / b
        M = np.array([[b / k, 0.0, b * ox], [0.0, b / k, b * oy]])
        crop_bg = cv2.warpAffine(
            bg,
            M,
            (size, size),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=(0, 0, 0),
        )
        w2c = torch.as_tensor(self.rig.world2cam[view - 1], dtype=_F32)
        out = render_meshes(
            fg,
            w2c,
            torch.as_tensor(Kc, dtype=_F32),
            size,
            size,
            light=self.lights[view - 1],
            background=torch.from_numpy(crop_bg),
            supersample=self.ss,
        )
        rgb = out.rgb.numpy()
        mask = out.part_id.numpy().astype(np.uint8)
        # crop pixels whose centre lies outside the full-resolution image are padding (black);
        # full-image pixel i covers label coordinates [i - 0.5, i + 0.5]
        w, h = self.rig.sizes[view - 1]
        c = np.arange(size) / k
        inside_x = ((ox + c) >= -0.5) & ((ox + c) <= w - 0.5)
        inside_y = ((oy + c) >= -0.5) & ((oy + c) <= h - 0.5)
        inside = inside_y[:, None] & inside_x[None, :]
        rgb = rgb * inside[..., None]
        mask = mask * inside
        return _to_uint8(rgb), mask

    def render_ego(self, world2cam: np.ndarray, fg: list) -> tuple[np.ndarray, np.ndarray]:
        """Distorted egocentric image (h, w, 3) uint8 RGB and mask (h, w) uint8."""
        W = self.ego_w + 2 * self.pad_x
        H = self.ego_h + 2 * self.pad_y
        out = render_meshes(
            self.stage + fg,
            torch.as_tensor(world2cam, dtype=_F32),
            torch.as_tensor(self.ego_K_pad, dtype=_F32),
            H,
            W,
            light=light_for_camera(world2cam),
            background=(0.1, 0.1, 0.1),
            supersample=self.ss,
        )
        rgb = _to_uint8(out.rgb.numpy())
        pid = out.part_id.numpy()
        mask = np.where(pid <= max(MASK_IDS.values()), pid, 0).astype(np.uint8)
        rgb = cv2.remap(rgb, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        mask = cv2.remap(mask, self.map_x, self.map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT)
        return rgb, mask


def _to_uint8(rgb: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8)
