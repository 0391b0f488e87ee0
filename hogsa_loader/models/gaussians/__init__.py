"""HOGS Gaussian models: mesh-bound (GaMeS / GaussianAvatars) and free (3DGS) Gaussians of
hands and articulated objects, scene composition and checkpoints.

Data flow: part template + :class:`BindingConfig` -> :class:`HandGaussians` /
:class:`ObjectGaussians` (posed for B samples) -> :class:`GaussianSet` -> :func:`compose` ->
:func:`render_scene` (:func:`hogsa_loader.render.gaussians.render_gaussians` with per-part
alpha).
"""

from hogsa_loader.geometry.quaternion import matrix_to_quat, quat_multiply, quat_to_matrix
from hogsa_loader.models.gaussians.binding import ALL_VARIANTS, BindingConfig
from hogsa_loader.models.gaussians.checkpoint import (
    MANIFEST_FILE,
    SCHEMA_VERSION,
    TENSORS_FILE,
    load_part,
    load_state,
    read_manifest,
    save_part,
)
from hogsa_loader.models.gaussians.free import FREE_INITS, FreeGaussians, surface_samples
from hogsa_loader.models.gaussians.gaussian_set import GaussianSet, SplatAppearance, num_sh_bases, rgb_to_sh, sh_to_rgb
from hogsa_loader.models.gaussians.mesh_bound import (
    DEFAULT_COVERAGE,
    DEFAULT_OPACITY,
    VARIANTS,
    FaceGaussians,
    MeshGaussians,
    avatar_gaussians_from_faces,
    face_frames,
    gaussians_from_faces,
    spread_barycentrics,
)
from hogsa_loader.models.gaussians.parts import (
    DEFAULT_PART_IDS,
    PART_TYPES,
    GaussianPart,
    HandGaussians,
    HandSkinning,
    ObjectGaussians,
    mano_skinning,
    template_hash,
)
from hogsa_loader.models.gaussians.scene import compose, headlight_colors, pad_sh, render_scene

__all__ = [
    "ALL_VARIANTS",
    "BindingConfig",
    "DEFAULT_COVERAGE",
    "DEFAULT_OPACITY",
    "DEFAULT_PART_IDS",
    "FREE_INITS",
    "FaceGaussians",
    "FreeGaussians",
    "GaussianPart",
    "GaussianSet",
    "HandGaussians",
    "HandSkinning",
    "MANIFEST_FILE",
    "MeshGaussians",
    "ObjectGaussians",
    "PART_TYPES",
    "SCHEMA_VERSION",
    "SplatAppearance",
    "TENSORS_FILE",
    "VARIANTS",
    "avatar_gaussians_from_faces",
    "compose",
    "face_frames",
    "gaussians_from_faces",
    "headlight_colors",
    "load_part",
    "load_state",
    "mano_skinning",
    "matrix_to_quat",
    "num_sh_bases",
    "pad_sh",
    "quat_multiply",
    "quat_to_matrix",
    "read_manifest",
    "render_scene",
    "rgb_to_sh",
    "save_part",
    "sh_to_rgb",
    "spread_barycentrics",
    "surface_samples",
    "template_hash",
]
