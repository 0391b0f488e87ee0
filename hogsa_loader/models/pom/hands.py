"""What POM needs of each hand model: the layer, a closed mesh, prior contact vertices.

Works for any MANO-schema model (MANO, MANO-HD, the synthetic hand): vertex counts come
from the model, the wrist opening is capped from the faces' boundary loops, and the prior
finger-pad/palm vertices come from the model's ``contact_vertex_ids`` metadata when it has
them, else from :func:`hogsa_loader.assets.hands.anatomy.derive_contact_prior` (skinning weights +
rest normals).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np
import torch
from torch import Tensor

from hogsa_loader.assets.hands.anatomy import derive_contact_prior
from hogsa_loader.assets.hands.mano import MANOLayer
from hogsa_loader.models.pom.geometry import CappedMesh

__all__ = ["SIDES", "HandInfo", "hand_infos", "prior_contact_ids"]

SIDES: tuple[str, str] = ("right", "left")


def prior_contact_ids(layer: MANOLayer) -> np.ndarray:
    """Sorted ids of the model's prior contact vertices (finger pads + palm)."""
    sets: Mapping[str, np.ndarray] = layer.data.contact_vertex_ids or {}
    if not sets:
        sets = derive_contact_prior(layer.data)
    ids = np.unique(np.concatenate([np.asarray(v, dtype=np.int64).reshape(-1) for v in sets.values()]))
    if ids.size == 0:
        raise ValueError(f"{layer.data.source}: no prior contact vertices could be derived")
    return ids


@dataclass
class HandInfo:
    """One hand side.

    Attributes:
        side: ``"right"`` or ``"left"``.
        layer: the MANO layer (ARCTIC convention ``flat_hand_mean=False``).
        capped: :class:`CappedMesh` (wrist closed) for inside tests.
        prior_ids: (P,) long prior contact vertex ids.
        prior_mask: (V,) bool.

    :meth:`layer_on` gives the layer on another device (a copy, made once per device), so
    the optimisation can run on CUDA while ``layer`` stays where the caller keeps it.
    """

    side: str
    layer: MANOLayer
    capped: CappedMesh = field(init=False)
    prior_ids: Tensor = field(init=False)
    prior_mask: Tensor = field(init=False)
    _copies: dict[str, MANOLayer] = field(init=False, default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        V = self.layer.num_verts
        self.capped = CappedMesh.from_faces(self.layer.faces.cpu().numpy(), V)
        ids = prior_contact_ids(self.layer)
        self.prior_ids = torch.as_tensor(ids, device=self.layer.v_template.device)
        mask = torch.zeros(V, dtype=torch.bool, device=self.layer.v_template.device)
        mask[self.prior_ids] = True
        self.prior_mask = mask

    def layer_on(self, device: torch.device | str) -> MANOLayer:
        """The MANO layer on ``device``: :attr:`layer` itself when it is there, else a cached copy."""
        device = torch.device(device)
        if self.layer.v_template.device == device:
            return self.layer
        key = str(device)
        if key not in self._copies:
            self._copies[key] = copy.deepcopy(self.layer).to(device)
        return self._copies[key]

    @property
    def num_verts(self) -> int:
        return self.layer.num_verts

    @property
    def side_sign(self) -> float:
        return 1.0 if self.side == "right" else -1.0


def hand_infos(layers: Mapping[str, MANOLayer]) -> dict[str, HandInfo]:
    """``{side: HandInfo}`` for ``{"right": layer, "left": layer}``."""
    return {side: HandInfo(side, layers[side]) for side in SIDES}
