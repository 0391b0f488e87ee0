"""How a part's Gaussians are bound to its mesh: the settings hand and object parts share."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any, Mapping

from hogsa_loader.models.gaussians.free import FREE_INITS
from hogsa_loader.models.gaussians.mesh_bound import DEFAULT_OPACITY
from hogsa_loader.models.gaussians.mesh_bound import VARIANTS as MESH_VARIANTS

__all__ = ["ALL_VARIANTS", "BindingConfig"]

#: Gaussian model variants of a part.
ALL_VARIANTS = MESH_VARIANTS + ("free",)
#: Binding settings not written to checkpoints (they only shape the initial state).
_NOT_RECORDED = ("init_opacity",)


@dataclass(frozen=True)
class BindingConfig:
    """The Gaussian model of a part and how it sits on the binding mesh.

    Attributes:
        variant: ``"games"`` / ``"avatars"`` (Gaussians computed from the posed faces of the
            binding mesh) or ``"free"`` (3DGS points skinned by their nearest binding vertex).
        k: Gaussians per face (mesh-bound, and free with ``free_init="faces"``).
        sh_degree: spherical-harmonics degree of the colours, 0..3.
        subdivide_levels: subdivisions of the binding mesh, 0, 1 or 2 (MANO-HD for hands,
            midpoint subdivision of the textured mesh for objects).
        free_init: ``"vertices"`` (one point per vertex) or ``"faces"`` (k per face); free
            variant only.
        init_opacity: initial opacity of every Gaussian.
        normal_eps: thickness of mesh-bound Gaussians along the face normal.
        weld_seams: coincident binding vertices share one canonical offset (see
            :class:`~hogsa_loader.models.gaussians.mesh_bound.MeshGaussians`).
    """

    variant: str = "games"
    k: int = 2
    sh_degree: int = 3
    subdivide_levels: int = 0
    free_init: str = "vertices"
    init_opacity: float = DEFAULT_OPACITY
    normal_eps: float = 1e-8
    weld_seams: bool = True

    def __post_init__(self) -> None:
        if self.subdivide_levels not in (0, 1, 2):
            raise ValueError(f"subdivide_levels must be 0, 1 or 2, got {self.subdivide_levels}")
        if self.variant not in ALL_VARIANTS:
            raise ValueError(f"variant must be one of {ALL_VARIANTS}, got {self.variant!r}")
        if self.free_init not in FREE_INITS:
            raise ValueError(f"free_init must be one of {FREE_INITS}, got {self.free_init!r}")
        for name, cast in (("k", int), ("sh_degree", int), ("subdivide_levels", int), ("normal_eps", float)):
            object.__setattr__(self, name, cast(getattr(self, name)))
        object.__setattr__(self, "weld_seams", bool(self.weld_seams))

    def recorded(self) -> dict[str, Any]:
        """The settings a checkpoint's ``config`` records, flat and in its key order."""
        return {key: val for key, val in asdict(self).items() if key not in _NOT_RECORDED}

    @classmethod
    def from_recorded(cls, config: Mapping[str, Any]) -> tuple["BindingConfig", dict[str, Any]]:
        """Split a checkpoint's flat ``config`` into the binding settings and the part's own
        settings (the rest)."""
        names = {f.name for f in fields(cls)}
        binding = cls(**{key: val for key, val in config.items() if key in names})
        return binding, {key: val for key, val in config.items() if key not in names}
