"""Gaussian models of the scene parts: a MANO(-HD) hand and an ARCTIC articulated object.

Every part wraps one Gaussian model (``BindingConfig.variant``):

* ``"games"`` / ``"avatars"``: :class:`~hogsa_loader.models.gaussians.mesh_bound.MeshGaussians`
  on a *binding mesh*; posing = posing the binding mesh (its template plus the learnable
  canonical offsets), then recomputing every Gaussian from the posed faces;
* ``"free"``: :class:`~hogsa_loader.models.gaussians.free.FreeGaussians` skinned by the
  transform of their nearest binding-mesh vertex.

and returns a :class:`~hogsa_loader.models.gaussians.gaussian_set.GaussianSet` for B poses.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Any, Callable, Optional, Sequence, Union

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor, nn

from hogsa_loader.assets.hands.mano import MANOLayer
from hogsa_loader.assets.hands.mano_io import ManoModelData
from hogsa_loader.assets.hands.manohd import subdivide_mesh, subdivide_model
from hogsa_loader.assets.objects.articulated import articulate, articulation_matrix
from hogsa_loader.assets.objects.template import TOP, ObjectTemplate
from hogsa_loader.geometry.rotations import axis_angle_to_matrix
from hogsa_loader.geometry.texture import sample_texture
from hogsa_loader.models.gaussians.binding import ALL_VARIANTS, BindingConfig
from hogsa_loader.models.gaussians.free import FreeGaussians, surface_samples
from hogsa_loader.models.gaussians.gaussian_set import GaussianSet
from hogsa_loader.models.gaussians.mesh_bound import MeshGaussians

__all__ = [
    "PART_TYPES",
    "ALL_VARIANTS",
    "BindingConfig",
    "DEFAULT_PART_IDS",
    "DEFAULT_SKIN_RGB",
    "DEFAULT_OBJECT_RGB",
    "template_hash",
    "HandSkinning",
    "mano_skinning",
    "GaussianPart",
    "HandGaussians",
    "ObjectGaussians",
]

#: Part types written to checkpoints.
PART_TYPES = ("hand_right", "hand_left", "object")
#: Default part index of each part type in a composed scene.
DEFAULT_PART_IDS = {"hand_right": 0, "hand_left": 1, "object": 2}
#: Skin colour used when a hand model has no vertex colours (the synthetic hand's tone).
DEFAULT_SKIN_RGB = (0.80, 0.60, 0.50)
#: Colour used when an object has no texture.
DEFAULT_OBJECT_RGB = (0.60, 0.60, 0.60)

ColorFn = Callable[[Tensor, Tensor], Tensor]  # (face_idx (N,), bary (N, 3)) -> rgb (N, 3)


def template_hash(verts: Union[np.ndarray, Tensor], faces: Union[np.ndarray, Tensor]) -> str:
    """sha256 (hex) of a mesh: vertices as little-endian float32 bytes, then faces as
    little-endian int64 bytes (C order)."""
    if isinstance(verts, Tensor):
        verts = verts.detach().cpu().numpy()
    if isinstance(faces, Tensor):
        faces = faces.detach().cpu().numpy()
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(np.asarray(verts), dtype="<f4").tobytes())
    h.update(np.ascontiguousarray(np.asarray(faces), dtype="<i8").tobytes())
    return h.hexdigest()


# --------------------------------------------------------------------------------------
# Hand skinning (MANO LBS with the per-vertex transforms exposed)
# --------------------------------------------------------------------------------------


@dataclass
class HandSkinning:
    """MANO posing of a template, with the per-vertex LBS transforms.

    Attributes:
        vertices: (B, V, 3) posed vertices (+ transl): ``rot @ (v_template + disp) + trans``.
        joints: (B, 16, 3) posed MANO joints (+ transl).
        rot: (B, V, 3, 3) blended linear part ``sum_j w_vj R_j`` of each vertex.
        trans: (B, V, 3) blended translation (+ transl).
        disp: (B, V, 3) rest-pose displacement (shape + pose blend shapes).
        full_pose: (B, 48) axis-angle pose applied.
    """

    vertices: Tensor
    joints: Tensor
    rot: Tensor
    trans: Tensor
    disp: Tensor
    full_pose: Tensor


def mano_skinning(
    layer: MANOLayer,
    v_template: Tensor,
    global_orient: Optional[Tensor] = None,
    hand_pose: Optional[Tensor] = None,
    betas: Optional[Tensor] = None,
    transl: Optional[Tensor] = None,
) -> HandSkinning:
    """:class:`MANOLayer` posing of an arbitrary template (:meth:`MANOLayer.skin`).

    Args:
        layer: provides blend shapes, regressor, weights, tree and pose conventions
            (mean pose, PCA).
        v_template: (V, 3) rest template replacing ``layer.v_template`` (e.g. template +
            offsets).
        global_orient, hand_pose, betas, transl: as :meth:`MANOLayer.forward`.

    Returns:
        :class:`HandSkinning`.
    """
    full_pose, betas = layer.full_pose_and_betas(global_orient, hand_pose, betas, transl)
    out = layer.skin(full_pose, betas, v_template)
    verts, joints, trans = out.vertices, out.joints, out.vertex_trans
    if transl is not None:
        verts = verts + transl[:, None]
        joints = joints + transl[:, None]
        trans = trans + transl[:, None]
    return HandSkinning(verts, joints, out.vertex_rot, trans, out.v_posed - v_template[None], full_pose)


# --------------------------------------------------------------------------------------
# Colour initialisation
# --------------------------------------------------------------------------------------


def _vertex_color_fn(faces: Tensor, colors: Tensor) -> ColorFn:
    def fn(face_idx: Tensor, bary: Tensor) -> Tensor:
        return torch.einsum("nc,ncd->nd", bary.to(colors.dtype), colors[faces[face_idx]])

    return fn


def _texture_color_fn(faces: Tensor, uv: Tensor, texture: Tensor) -> ColorFn:
    def fn(face_idx: Tensor, bary: Tensor) -> Tensor:
        uvs = torch.einsum("nc,ncd->nd", bary.to(uv.dtype), uv[faces[face_idx]])
        return sample_texture(texture, uvs)

    return fn


# --------------------------------------------------------------------------------------
# Common part machinery
# --------------------------------------------------------------------------------------


class GaussianPart(nn.Module):
    """Base class of :class:`HandGaussians` and :class:`ObjectGaussians`.

    Attributes:
        splats: the Gaussian model (:class:`MeshGaussians` or :class:`FreeGaussians`);
            its ``state_dict`` is what checkpoints store.
        binding: the :class:`BindingConfig` the part was built with.
        variant, k, sh_degree: those of ``binding`` (the checkpoint's top-level settings).
        part_type: ``"hand_right"``, ``"hand_left"`` or ``"object"``.
        part_id: index given to this part's Gaussians in a scene.
        template_hash: :func:`template_hash` of the caller's template mesh.
        binding_hash: :func:`template_hash` of the binding mesh.
        binding_mesh: how the binding mesh was made, in words.
    """

    splats: Union[MeshGaussians, FreeGaussians]
    binding: BindingConfig
    variant: str
    k: int
    sh_degree: int
    binding_verts: Tensor
    binding_faces: Tensor
    _extra_config: dict[str, Any]
    part_type: str
    part_id: int
    template_hash: str
    binding_hash: str
    binding_mesh: str

    def __init__(self, binding: BindingConfig) -> None:
        super().__init__()
        self.binding = binding
        self.variant, self.k, self.sh_degree = binding.variant, binding.k, binding.sh_degree

    def _build_splats(self, verts: Tensor, faces: Tensor, color_fn: ColorFn, dtype: torch.dtype) -> None:
        """Gaussians of :attr:`binding` on the binding mesh ``verts`` (V, 3), ``faces`` (F, 3),
        coloured by ``color_fn`` at each Gaussian's surface point."""
        b = self.binding
        self.binding_hash = template_hash(verts, faces)
        common = dict(k=b.k, sh_degree=b.sh_degree, init_opacity=b.init_opacity, normal_eps=b.normal_eps, dtype=dtype)
        if b.variant == "free":
            face_idx, bary = surface_samples(faces, verts.shape[0], b.free_init, b.k)
            colors = color_fn(face_idx, bary).clamp(0.0, 1.0)
            self.splats = FreeGaussians(verts, faces, init=b.free_init, colors=colors, **common)
        else:
            self.splats = MeshGaussians(verts, faces, variant=b.variant, weld_seams=b.weld_seams, **common)
            face_idx, bary = surface_samples(faces, verts.shape[0], "faces", b.k)  # = init_bary, float64
            colors = color_fn(face_idx, bary).clamp(0.0, 1.0)
            self.splats.set_colors_(colors)

    @property
    def num_gaussians(self) -> int:
        return self.splats.num_gaussians

    @property
    def is_mesh_bound(self) -> bool:
        return self.variant != "free"

    def offset_regulariser(self) -> Tensor:
        """L_R of the canonical offsets (0 for free Gaussians)."""
        return self.splats.offset_regulariser()

    def config(self) -> dict[str, Any]:
        """JSON-able constructor settings (stored in checkpoints to rebuild the part):
        :meth:`BindingConfig.recorded` then the part's own settings."""
        return self.binding.recorded() | self._extra_config

    def canonical_vertices(self) -> Tensor:
        """(V, 3) binding-mesh template (+ offsets for mesh-bound variants)."""
        if isinstance(self.splats, MeshGaussians):
            return self.splats.canonical_vertices()
        return self.binding_verts

    def binding_counts(self) -> dict[str, int]:
        """Sizes recorded in checkpoints: binding-mesh vertices/faces and Gaussians."""
        return {
            "num_verts": int(self.binding_verts.shape[0]),
            "num_faces": int(self.binding_faces.shape[0]),
            "num_gaussians": self.num_gaussians,
        }


# --------------------------------------------------------------------------------------
# Hands
# --------------------------------------------------------------------------------------


class HandGaussians(GaussianPart):
    """Gaussians of one MANO-schema hand.

    The binding mesh is the model's mesh or its MANO-HD subdivision
    (:func:`~hogsa_loader.assets.hands.manohd.subdivide_model`, ``binding.subdivide_levels``).
    Posing is MANO's LBS (:mod:`hogsa_loader.assets.hands.lbs`) with the offsets added to
    ``v_template`` *before* shape blend shapes, joint regression, pose correctives and
    skinning (so the offsets also move the regressed joints), exactly like a
    :class:`~hogsa_loader.assets.hands.mano.MANOLayer` built on a model whose ``v_template`` is
    ``template + offsets``. Initial colours: the model's ``vertex_colors`` (skin albedo)
    interpolated at each Gaussian, else a constant skin tone.

    Args:
        model: a :class:`ManoModelData` or a :class:`MANOLayer` (its settings are kept;
            a new layer is built when subdividing).
        binding: the Gaussian model and its binding (:class:`BindingConfig`).
        part_id: scene part index; default 0 for a right hand, 1 for a left hand.
        albedo: initial colour, (3,) or (V, 3) on the *original* model's vertices;
            default the model's ``vertex_colors``, else :data:`DEFAULT_SKIN_RGB`.
        flat_hand_mean, use_pca, num_pca_comps, num_betas, fix_left_shapedirs: the
            :class:`MANOLayer` settings when ``model`` is a :class:`ManoModelData`.
        dtype: parameter dtype (a given :class:`MANOLayer` imposes its own).
    """

    def __init__(
        self,
        model: Union[ManoModelData, MANOLayer],
        binding: BindingConfig = BindingConfig(),
        *,
        part_id: Optional[int] = None,
        albedo: Optional[Union[Sequence[float], np.ndarray, Tensor]] = None,
        flat_hand_mean: bool = False,
        use_pca: bool = False,
        num_pca_comps: int = 45,
        num_betas: int = 10,
        fix_left_shapedirs: bool = False,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        super().__init__(binding)
        if isinstance(model, MANOLayer):
            data = model.data
            dtype = model.v_template.dtype  # the layer's buffers set the dtype
            settings = dict(
                flat_hand_mean=model.flat_hand_mean,
                use_pca=model.use_pca,
                num_pca_comps=model.num_pca_comps if model.use_pca else 45,
                num_betas=model.num_betas,
                fix_left_shapedirs=model.fix_left_shapedirs,
            )
        else:
            data = model
            settings = dict(
                flat_hand_mean=flat_hand_mean,
                use_pca=use_pca,
                num_pca_comps=num_pca_comps,
                num_betas=num_betas,
                fix_left_shapedirs=fix_left_shapedirs,
            )
        self._extra_config: dict[str, Any] = dict(settings)
        self.part_type = f"hand_{data.side}"
        self.part_id = DEFAULT_PART_IDS[self.part_type] if part_id is None else int(part_id)
        self.template_hash = template_hash(data.v_template, data.faces)

        levels = binding.subdivide_levels
        colors = self._albedo(data, albedo)
        if levels:
            bind = subdivide_model(data.replace(vertex_colors=colors), levels=levels)
            colors = bind.vertex_colors
            self.binding_mesh = f"subdivide_model levels={levels}"
        else:
            bind = data
            self.binding_mesh = "model mesh"
        if isinstance(model, MANOLayer) and not levels:
            self.layer = model
        else:
            self.layer = MANOLayer(bind, dtype=dtype, **settings)
        verts = self.layer.v_template.detach().clone()
        faces = torch.as_tensor(bind.faces, dtype=torch.long)
        self.register_buffer("binding_verts", verts, persistent=False)
        self.register_buffer("binding_faces", faces, persistent=False)
        color_fn = _vertex_color_fn(faces, torch.as_tensor(colors, dtype=torch.float64))
        self._build_splats(verts, faces, color_fn, dtype)

    @staticmethod
    def _albedo(data: ManoModelData, albedo: Any) -> np.ndarray:
        """(V, 3) initial colours on the original model."""
        if albedo is None:
            if data.vertex_colors is not None:
                return np.asarray(data.vertex_colors, dtype=np.float64)
            albedo = DEFAULT_SKIN_RGB
        a = np.asarray(albedo.detach().cpu() if isinstance(albedo, Tensor) else albedo, dtype=np.float64)
        if a.shape == (3,):
            return np.tile(a, (data.num_verts, 1))
        if a.shape != (data.num_verts, 3):
            raise ValueError(f"albedo must be (3,) or ({data.num_verts}, 3), got {a.shape}")
        return a

    def skinning(
        self,
        global_orient: Optional[Tensor] = None,
        hand_pose: Optional[Tensor] = None,
        betas: Optional[Tensor] = None,
        transl: Optional[Tensor] = None,
    ) -> HandSkinning:
        """MANO posing of the (offset) binding mesh; arguments as :meth:`MANOLayer.forward`."""
        return mano_skinning(self.layer, self.canonical_vertices(), global_orient, hand_pose, betas, transl)

    def posed_vertices(self, *args: Optional[Tensor], **kwargs: Optional[Tensor]) -> Tensor:
        """(B, V, 3) posed binding-mesh vertices (offsets included)."""
        return self.skinning(*args, **kwargs).vertices

    def forward(
        self,
        global_orient: Optional[Tensor] = None,
        hand_pose: Optional[Tensor] = None,
        betas: Optional[Tensor] = None,
        transl: Optional[Tensor] = None,
    ) -> GaussianSet:
        """Posed Gaussians for B hand poses (arguments as :meth:`MANOLayer.forward`)."""
        sk = self.skinning(global_orient, hand_pose, betas, transl)
        if isinstance(self.splats, MeshGaussians):
            return self.splats.gaussians(sk.vertices, self.part_id)
        return self.splats.gaussians(sk.rot, sk.trans, sk.disp, self.part_id)


# --------------------------------------------------------------------------------------
# Objects
# --------------------------------------------------------------------------------------


class ObjectGaussians(GaussianPart):
    """Gaussians of one ARCTIC-style articulated object.

    The binding mesh is the textured mesh (``tex_verts``/``tex_faces``, charts not
    welded) when the template has one, optionally midpoint-subdivided
    (:func:`~hogsa_loader.assets.hands.manohd.subdivide_mesh`, ``binding.subdivide_levels``) for
    texture detail; the original ``verts``/``faces`` stay the geometry (hash,
    :meth:`ObjectGaussians.posed_geometry`).
    The top part (``parts == 0``) articulates by ``R_z(-theta)`` and then every point gets the
    global pose (:func:`~hogsa_loader.assets.objects.articulated.articulate`). Initial colours: the
    texture sampled at each Gaussian's uv (bilinear, OBJ convention), else a constant grey.

    Args:
        template: the object template (metres, canonical frame, hinge = z axis).
        binding: the Gaussian model and its binding (:class:`BindingConfig`).
        use_texture_mesh: bind to the textured mesh when the template has one.
        part_id: scene part index (default 2).
        color: colour used without a texture (default :data:`DEFAULT_OBJECT_RGB`).
        dtype: parameter dtype.
    """

    binding_is_top: Tensor
    geometry_verts: Tensor
    geometry_faces: Tensor
    geometry_is_top: Tensor

    def __init__(
        self,
        template: ObjectTemplate,
        binding: BindingConfig = BindingConfig(),
        *,
        use_texture_mesh: bool = True,
        part_id: Optional[int] = None,
        color: Sequence[float] = DEFAULT_OBJECT_RGB,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        super().__init__(binding)
        self.name = template.name
        self.part_type = "object"
        self.part_id = DEFAULT_PART_IDS["object"] if part_id is None else int(part_id)
        self.template_hash = template_hash(template.verts, template.faces)
        textured = bool(use_texture_mesh and template.has_texture)
        self._extra_config = {"use_texture_mesh": bool(use_texture_mesh)}
        if textured:
            verts = np.asarray(template.tex_verts, dtype=np.float64)
            faces = np.asarray(template.tex_faces, dtype=np.int64)
            uv = np.asarray(template.tex_uv, dtype=np.float64)
            if template.tex_parts is not None:
                is_top = np.asarray(template.tex_parts) == TOP
            else:
                _, nearest = cKDTree(template.verts).query(verts)
                is_top = template.parts[nearest] == TOP
        else:
            verts = np.asarray(template.verts, dtype=np.float64)
            faces = np.asarray(template.faces, dtype=np.int64)
            uv = np.zeros((verts.shape[0], 2))
            is_top = template.parts == TOP
        levels = binding.subdivide_levels
        for _ in range(levels):
            faces, op = subdivide_mesh(faces, verts.shape[0])
            verts, uv = op @ verts, op @ uv
            is_top = (op @ is_top.astype(np.float64)) > 0.75  # a midpoint is top if both ends are
        source = "mesh_tex" if textured else "mesh"
        how = f"subdivide_mesh levels={levels}" if levels else "as is"
        self.binding_mesh = f"{source} {how}"

        verts_t = torch.as_tensor(verts, dtype=dtype)
        faces_t = torch.as_tensor(faces, dtype=torch.long)
        self.register_buffer("binding_verts", verts_t, persistent=False)
        self.register_buffer("binding_faces", faces_t, persistent=False)
        self.register_buffer("binding_is_top", torch.as_tensor(is_top, dtype=torch.bool), persistent=False)
        self.register_buffer("geometry_verts", torch.as_tensor(template.verts, dtype=dtype), persistent=False)
        self.register_buffer("geometry_faces", torch.as_tensor(template.faces, dtype=torch.long), persistent=False)
        self.register_buffer("geometry_is_top", torch.as_tensor(template.parts == TOP), persistent=False)
        if textured:
            tex = torch.as_tensor(np.asarray(template.texture), dtype=torch.float64) / 255.0
            color_fn = _texture_color_fn(faces_t, torch.as_tensor(uv, dtype=torch.float64), tex)
        else:
            const = torch.tensor(color, dtype=torch.float64).expand(verts.shape[0], 3)
            color_fn = _vertex_color_fn(faces_t, const)
        self._build_splats(verts_t, faces_t, color_fn, dtype)

    def posed_vertices(self, angle: Tensor, global_orient: Tensor, transl: Optional[Tensor] = None) -> Tensor:
        """(B, V, 3) posed binding-mesh vertices (offsets included)."""
        v = self.canonical_vertices()
        B = global_orient.shape[0]
        return articulate(v[None].expand(B, *v.shape), self.binding_is_top, angle, global_orient, transl)

    def posed_geometry(self, angle: Tensor, global_orient: Tensor, transl: Optional[Tensor] = None) -> Tensor:
        """(B, Vg, 3) the original template mesh (``verts``) posed the same way."""
        v = self.geometry_verts.to(global_orient.dtype)
        B = global_orient.shape[0]
        return articulate(v[None].expand(B, *v.shape), self.geometry_is_top, angle, global_orient, transl)

    def vertex_transforms(
        self, angle: Tensor, global_orient: Tensor, transl: Optional[Tensor] = None
    ) -> tuple[Tensor, Tensor]:
        """Rigid transform of every binding vertex: rot (B, V, 3, 3), trans (B, V, 3);
        ``R(omega) R_z(-theta)`` on the top part, ``R(omega)`` on the bottom."""
        B = global_orient.shape[0]
        V = self.binding_verts.shape[0]
        r_glob = axis_angle_to_matrix(global_orient)  # (B, 3, 3)
        r_top = r_glob @ articulation_matrix(angle).to(r_glob.dtype)
        rot = torch.where(self.binding_is_top[None, :, None, None], r_top[:, None], r_glob[:, None])
        trans = torch.zeros(B, V, 3, dtype=r_glob.dtype, device=r_glob.device)
        if transl is not None:
            trans = trans + transl[:, None, :]
        return rot, trans

    def forward(self, angle: Tensor, global_orient: Tensor, transl: Optional[Tensor] = None) -> GaussianSet:
        """Posed Gaussians for B object poses.

        Args:
            angle: (B,) or (B, 1) articulation angle theta (radians).
            global_orient: (B, 3) axis-angle omega.
            transl: (B, 3) translation (metres) or None.
        """
        if isinstance(self.splats, MeshGaussians):
            return self.splats.gaussians(self.posed_vertices(angle, global_orient, transl), self.part_id)
        rot, trans = self.vertex_transforms(angle, global_orient, transl)
        return self.splats.gaussians(rot, trans, None, self.part_id)
