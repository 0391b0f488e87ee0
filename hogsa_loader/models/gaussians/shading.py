"""A learned directional light for HOGS models (optional Lambertian shading)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from hogsa_loader.errors import AssetError, PathLike
from hogsa_loader.io.tensors import ManifestFormat, read_manifest, read_tensors, save_checkpoint
from hogsa_loader.models.gaussians.gaussian_set import GaussianSet
from hogsa_loader.render.gaussians import sh_colors

__all__ = [
    "LIGHT_FORMAT",
    "LIGHT_SCHEMA_VERSION",
    "LIGHT_TENSORS",
    "LIGHT_MANIFEST",
    "DirectionalLight",
    "save_light",
    "load_light",
]

LIGHT_FORMAT = "hogsa-light"
LIGHT_SCHEMA_VERSION = 1
LIGHT_TENSORS = "light.safetensors"
LIGHT_MANIFEST = "manifest.json"
#: The shared checkpoint header of a light (no tensor list, no library version).
LIGHT_CHECKPOINT = ManifestFormat(
    LIGHT_FORMAT,
    LIGHT_SCHEMA_VERSION,
    "a light checkpoint",
    LIGHT_TENSORS,
    specs=None,
    library_version=False,
    manifest_file=LIGHT_MANIFEST,
)


def _inv_softplus(x: float) -> float:
    return float(torch.log(torch.expm1(torch.tensor(float(x)))))


class DirectionalLight(nn.Module):
    """One directional light plus ambient term, in the world frame.

    Hands and objects move under the fixed lights of a capture studio, so one surface point
    looks brighter or darker depending on how it is turned. Plain Gaussian colours are fixed
    to the surface and cannot follow that. :class:`DirectionalLight` adds one directional
    light, shared by every part and fixed in the world frame, learnt with the Gaussians:

    ``rgb = c_SH(view dir) · (ambient + diffuse · max(0, n · (−d)))``

    with ``n`` each Gaussian's shading normal (:meth:`MeshGaussians.shading_normals`, or the
    skinned surface normal of free Gaussians; no gradient flows into the geometry through it),
    ``d`` the unit direction the light travels, and ``c_SH`` the Gaussian's SH colour (+0.5,
    clamped at 0, as the rasteriser does).
    Setting ``diffuse = 0, ambient = 1`` recovers unshaded rendering. At sampling time the
    light can be changed (relighting augmentation).

    Checkpoint: ``light/`` inside a run folder, ``light.safetensors`` + ``manifest.json``
    (the shared checkpoint header of :mod:`hogsa_loader.io.tensors`: format ``hogsa-light``,
    schema version 1, ``tensors_file``, ``tensors_sha256``; plus ``model`` and the light's values).

    Args:
        direction: (3,) direction the light travels (world frame; normalised).
        ambient, diffuse: initial weights (> 0).

    Parameters: ``direction`` (3,) (unnormalised), ``ambient_raw`` and ``diffuse_raw``
    (softplus-activated scalars).
    """

    def __init__(
        self, direction: Sequence[float] = (0.0, 0.0, 1.0), ambient: float = 0.5, diffuse: float = 0.5
    ) -> None:
        super().__init__()
        d = torch.as_tensor(direction, dtype=torch.float32).reshape(3)
        if not torch.isfinite(d).all() or float(d.norm()) < 1e-8:
            raise ValueError(f"light direction must be a finite non-zero 3-vector, got {d.tolist()}")
        if ambient <= 0 or diffuse <= 0:
            raise ValueError("ambient and diffuse must be > 0")
        self.direction = nn.Parameter(d / d.norm())
        self.ambient_raw = nn.Parameter(torch.tensor(_inv_softplus(ambient)))
        self.diffuse_raw = nn.Parameter(torch.tensor(_inv_softplus(diffuse)))

    def unit_direction(self) -> Tensor:
        return self.direction / self.direction.norm().clamp(min=1e-12)

    def ambient(self) -> Tensor:
        return F.softplus(self.ambient_raw)

    def diffuse(self) -> Tensor:
        return F.softplus(self.diffuse_raw)

    def shade(self, normals: Tensor) -> Tensor:
        """(..., 1) shading factor of unit normals (..., 3)."""
        cos = (normals * -self.unit_direction().to(normals.dtype)).sum(-1, keepdim=True)
        return self.ambient().to(normals.dtype) + self.diffuse().to(normals.dtype) * cos.clamp_min(0.0)

    def forward(self, scene: GaussianSet, viewmats: Tensor) -> Tensor:
        """Per-camera shaded colours.

        Args:
            scene: (B, N) Gaussians with ``normals``.
            viewmats: (B, C, 4, 4) world->camera (OpenCV).

        Returns:
            (B, C, N, 3) colours (pass with ``sh_degree=None`` to the renderer).
        """
        if scene.normals is None:
            raise ValueError("DirectionalLight needs GaussianSet.normals")
        campos = torch.linalg.inv(viewmats)[..., :3, 3]  # (B, C, 3)
        dirs = scene.means[:, None] - campos[:, :, None, :]  # (B, C, N, 3)
        C = viewmats.shape[1]
        sh = scene.sh[:, None].expand(-1, C, -1, -1, -1)
        base = torch.clamp_min(sh_colors(scene.sh_degree, dirs, sh) + 0.5, 0.0)
        return base * self.shade(scene.normals)[:, None]

    @torch.no_grad()
    def describe(self) -> dict[str, object]:
        return {
            "direction": [round(float(x), 6) for x in self.unit_direction()],
            "ambient": float(self.ambient()),
            "diffuse": float(self.diffuse()),
        }


def save_light(light: DirectionalLight, folder: PathLike) -> Path:
    """Write ``light.safetensors`` + ``manifest.json`` into ``folder`` (atomically)."""
    folder = Path(folder)
    tensors = {k: v.detach().cpu().float().contiguous() for k, v in light.state_dict().items()}
    save_checkpoint(folder, LIGHT_CHECKPOINT, tensors, {"model": "directional", **light.describe()})
    return folder


def load_light(folder: PathLike, into: Optional[DirectionalLight] = None) -> DirectionalLight:
    """Read a light checkpoint (into ``into`` when given).

    Raises:
        AssetError: missing files, wrong format/schema, or bad tensors (names the file).
    """
    folder = Path(folder)
    tensors = read_tensors(folder, read_manifest(folder, LIGHT_CHECKPOINT), LIGHT_CHECKPOINT)  # (finite)
    tpath = folder / LIGHT_TENSORS
    light = into if into is not None else DirectionalLight()
    want = {k: tuple(v.shape) for k, v in light.state_dict().items()}
    have = {k: tuple(v.shape) for k, v in tensors.items()}
    if want != have:
        raise AssetError(tpath, f"light tensors {have} do not match {want}")
    with torch.no_grad():
        for k, v in light.state_dict().items():
            v.copy_(tensors[k].to(v.dtype))
    return light
