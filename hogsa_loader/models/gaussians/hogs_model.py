"""One HOGS model: the right-hand, left-hand and object Gaussians of one (subject, object).

:class:`HogsModel` is what ``hogsa train hogs`` trains and what everything
downstream (render-quality benchmark, SRM training, the synthetic loader) renders.
:meth:`HogsModel.from_run` loads a trained run folder; :meth:`HogsModel.render` poses and
renders it (the pose keys, :data:`POSE_KEYS`, are listed in :meth:`HogsModel.scene`).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Mapping, Optional

import torch
from torch import Tensor, nn

from hogsa_loader.errors import AssetError, PathLike, read_json
from hogsa_loader.models.gaussians.checkpoint import MANIFEST_FILE, load_part, read_manifest
from hogsa_loader.models.gaussians.gaussian_set import GaussianSet, num_sh_bases
from hogsa_loader.models.gaussians.parts import GaussianPart
from hogsa_loader.models.gaussians.scene import compose, render_scene
from hogsa_loader.models.gaussians.shading import DirectionalLight, load_light

__all__ = ["LIGHT_DIR", "PART_NAMES", "POSE_KEYS", "HogsModel"]

#: Part folder names of a run, in scene order (part ids 0, 1, 2 follow the parts' own ids).
PART_NAMES: tuple[str, ...] = ("hand_right", "hand_left", "object")

#: Sub-folder of a run holding the learned light (optional).
LIGHT_DIR = "light"

#: Pose keys :meth:`HogsModel.scene` reads.
POSE_KEYS: tuple[str, ...] = (
    *(f"{side}_{k}" for side in ("right", "left") for k in ("rot", "pose", "betas", "trans")),
    "obj_arti",
    "obj_rot",
    "obj_trans",
)


class HogsModel(nn.Module):
    """Right hand, left hand and object Gaussians of one (subject, object).

    Args:
        hand_right, hand_left: :class:`~hogsa_loader.models.gaussians.parts.HandGaussians`.
        obj: :class:`~hogsa_loader.models.gaussians.parts.ObjectGaussians`.
        source: free-form description (dataset, subject, sequences) from the manifests.
        light: optional learned :class:`~hogsa_loader.models.gaussians.shading.DirectionalLight`
            (a run folder's ``light/``); None renders the SH colours unshaded.
    """

    def __init__(
        self,
        hand_right: GaussianPart,
        hand_left: GaussianPart,
        obj: GaussianPart,
        source: Optional[Mapping[str, str]] = None,
        light: Optional[DirectionalLight] = None,
    ) -> None:
        super().__init__()
        self.parts = nn.ModuleDict({"hand_right": hand_right, "hand_left": hand_left, "object": obj})
        self.source = dict(source or {})
        self.light = light

    # ------------------------------------------------------------------ loading
    @staticmethod
    def is_run(folder: PathLike) -> bool:
        """True when ``folder`` holds the three part checkpoints of a finished run."""
        folder = Path(folder)
        return all((folder / name / MANIFEST_FILE).is_file() for name in PART_NAMES)

    @classmethod
    def from_run(
        cls,
        folder: PathLike,
        mano_layers: Mapping[str, object],
        object_templates: Mapping[str, object],
        *,
        device: Optional[torch.device | str] = None,
        dtype: torch.dtype = torch.float32,
    ) -> "HogsModel":
        """Load a trained run folder.

        A trained run folder holds one checkpoint per part (``hand_right/``, ``hand_left/``,
        ``object/``, each ``gaussians.safetensors`` + ``manifest.json``);
        :meth:`HogsModel.from_run` rebuilds the parts on the caller's MANO layers and object
        template (their hashes are checked by :func:`~hogsa_loader.models.gaussians.checkpoint.load_part`).

        Args:
            folder: run folder with ``hand_right/``, ``hand_left/`` and ``object/``.
            mano_layers: ``{"right": MANOLayer, "left": MANOLayer}`` (e.g.
                :meth:`ArcticRoot.mano_layers`).
            object_templates: ``{name: ObjectTemplate}``; the object's name is read from
                its manifest.
            device, dtype: where and how to hold the parameters.

        Raises:
            AssetError: a part folder is missing, a checkpoint does not match the
                given templates (names the file and the mismatch), or the run was trained
                with a learned light (``shading`` in its part manifests, or in its
                ``config.json``) and ``light/`` is missing.
        """
        folder = Path(folder)
        missing = [name for name in PART_NAMES if not (folder / name / MANIFEST_FILE).is_file()]
        if missing:
            raise AssetError(folder, f"not a finished HOGS run: missing part checkpoint(s) {missing}")
        manifest = read_manifest(folder / "object")
        obj_name = manifest.get("source", {}).get("object")
        if obj_name is None or obj_name not in object_templates:
            raise AssetError(
                folder / "object" / MANIFEST_FILE,
                f"object {obj_name!r} is not among the given templates {sorted(object_templates)}",
            )
        parts = {
            "hand_right": load_part(
                folder / "hand_right", mano_layers["right"], expected_part_type="hand_right", dtype=dtype
            ),  # type: ignore[arg-type]
            "hand_left": load_part(
                folder / "hand_left", mano_layers["left"], expected_part_type="hand_left", dtype=dtype
            ),  # type: ignore[arg-type]
            "object": load_part(
                folder / "object", object_templates[obj_name], expected_part_type="object", dtype=dtype
            ),  # type: ignore[arg-type]
        }
        source = {k: str(v) for k, v in manifest.get("source", {}).items()}
        source.setdefault("object", obj_name)
        shading = _run_shading(folder, manifest)
        if shading == "lambert" and not (folder / LIGHT_DIR).is_dir():
            raise AssetError(
                folder / LIGHT_DIR,
                "is missing: the run was trained with shading 'lambert' (its colours "
                "were fitted under this learned light), so it would render unshaded",
            )
        light = load_light(folder / LIGHT_DIR) if (folder / LIGHT_DIR).is_dir() else None
        model = cls(parts["hand_right"], parts["hand_left"], parts["object"], source=source, light=light)
        return model.to(device) if device is not None else model

    # ------------------------------------------------------------------ posing
    @property
    def object_name(self) -> str:
        return str(self.source.get("object", getattr(self.parts["object"], "name", "")))

    @property
    def num_gaussians(self) -> int:
        return sum(int(p.num_gaussians) for p in self.parts.values())

    def scene(
        self, poses: Mapping[str, Tensor], sh_degree: Optional[int] = None, keep_normals: bool = False
    ) -> GaussianSet:
        """Posed, composed Gaussians of B frames.

        Poses use the keys of :meth:`hogsa_loader.train.hogs_data.HogsData.poses` — the ARCTIC
        world frame, exactly as ``SequenceData`` stores them:

        * ``{side}_rot`` (B, 3), ``{side}_pose`` (B, 45), ``{side}_betas`` (B, 10),
          ``{side}_trans`` (B, 3) for ``side`` in ``right``/``left``;
        * ``obj_arti`` (B, 1) articulation (rad), ``obj_rot`` (B, 3) axis-angle,
          ``obj_trans`` (B, 3) metres.

        Args:
            poses: the :data:`POSE_KEYS` tensors (see above), batch B.
            sh_degree: keep SH bands up to this degree (default: all).
            keep_normals: keep the shading normals without a learned light too (headlight
                shading needs them; with a light they are always kept).

        Returns:
            (B, N) :class:`GaussianSet` with part ids.
        """
        missing = [k for k in POSE_KEYS if k not in poses]
        if missing:
            raise KeyError(f"HogsModel.scene: missing pose keys {missing}")
        sets = [
            self.parts["hand_right"](
                poses["right_rot"], poses["right_pose"], poses["right_betas"], poses["right_trans"]
            ),
            self.parts["hand_left"](poses["left_rot"], poses["left_pose"], poses["left_betas"], poses["left_trans"]),
            self.parts["object"](poses["obj_arti"], poses["obj_rot"], poses["obj_trans"]),
        ]
        scene = compose(sets)
        if sh_degree is not None and sh_degree < scene.sh_degree:
            scene = replace(scene, sh=scene.sh[..., : num_sh_bases(sh_degree), :], sh_degree=sh_degree)
        return scene if self.light is not None or keep_normals else replace(scene, normals=None)

    def render(
        self,
        poses: Mapping[str, Tensor],
        viewmats: Tensor,
        Ks: Tensor,
        width: int,
        height: int,
        *,
        sh_degree: Optional[int] = None,
        **render_kwargs: object,
    ):  # -> RenderOutput
        """Pose and render B frames from C cameras each.

        Args:
            poses: see :meth:`scene`.
            viewmats: (B, C, 4, 4) world->camera (OpenCV).
            Ks: (B, C, 3, 3) render intrinsics (pixel-centre convention of
                :func:`~hogsa_loader.assets.conventions.render_intrinsics`).
            width, height: image size.
            sh_degree: see :meth:`scene`.
            **render_kwargs: :func:`~hogsa_loader.models.gaussians.scene.render_scene` options
                (``backend``, ``render_mode``, ``backgrounds``, ...). With a learned light
                the colours are shaded by it unless ``colors`` or ``headlight`` is given.

        Returns:
            :class:`~hogsa_loader.render.api.RenderOutput` with ``part_alpha`` of 3 parts.
        """
        scene = self.scene(poses, sh_degree=sh_degree, keep_normals=render_kwargs.get("headlight") is not None)
        render_kwargs.setdefault("num_parts", 3)
        if self.light is not None and "headlight" not in render_kwargs and "colors" not in render_kwargs:
            render_kwargs["colors"] = self.light(scene, viewmats)
        return render_scene(scene, viewmats, Ks, width, height, **render_kwargs)  # type: ignore[arg-type]


def _run_shading(folder: Path, object_manifest: Mapping[str, object]) -> Optional[str]:
    """The shading a run was trained with: its parts' ``extra["shading"]``, else its
    ``config.json``'s ``shading`` (runs checkpointed before the parts recorded it), else None."""
    shading = (
        object_manifest.get("extra", {}).get("shading") if isinstance(object_manifest.get("extra"), dict) else None
    )
    if isinstance(shading, str):
        return shading
    config = folder / "config.json"
    if config.is_file():
        try:
            raw = read_json(config)
        except AssetError:
            return None  # (the run's settings file is not part of the checkpoint)
        if isinstance(raw, dict) and isinstance(raw.get("shading"), str):
            return raw["shading"]
    return None
