"""Interaction-field targets of InterField-SF: nearest hand↔object vertex distances.

:func:`interaction_field` computes them for one frame's meshes, :class:`InterFieldTargets`
from pose parameters, and :func:`interfield_targets` builds the latter for a data root.
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Optional, Union

import numpy as np
import torch
from torch import Tensor

__all__ = ["INTERFIELD_KEYS", "interaction_field", "InterFieldTargets", "interfield_targets"]

#: Target keys added by :class:`InterFieldTargets`, in insertion order.
INTERFIELD_KEYS: tuple[str, ...] = (
    "dist.ro",
    "dist.lo",
    "dist.or",
    "dist.ol",
    "idx.ro",
    "idx.lo",
    "idx.or",
    "idx.ol",
    "object.v_len",
)


def _nearest(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """For every point of ``a`` (N, 3): distance to and index of its nearest point in ``b`` (M, 3)."""
    d = torch.cdist(a[None], b[None])[0]  # (N, M)
    dist, idx = d.min(dim=1)
    return dist, idx


def interaction_field(v_r: Any, v_l: Any, v_o: Any, v_max: int, max_dist: float = math.inf) -> dict[str, Any]:
    """Interaction-field targets of one frame.

    For the right/left MANO meshes and the object mesh of one frame (all in one frame; the
    distances do not depend on which):

    =================  ==============  ==========================================================
    key                shape           value
    =================  ==============  ==========================================================
    ``dist.ro``        (Vh,) float32   each right-hand vertex → nearest object vertex (m)
    ``dist.lo``        (Vh,) float32   left hand → object
    ``dist.or``        (Vmax,) float32 each object vertex → nearest right-hand vertex (padded)
    ``dist.ol``        (Vmax,) float32 object → left hand (padded)
    ``idx.ro/lo``      (Vh,) int64     index of that nearest object vertex
    ``idx.or/ol``      (Vmax,) int64   index of that nearest hand vertex (padded)
    ``object.v_len``   int             real object vertex count (entries ≥ it are padding: 0)
    =================  ==============  ==========================================================

    Distances are clamped to ``[0, max_dist]`` (ARCTIC: 0.10 m for InterField-SF, no clamp =
    ``inf`` for ArcticNet-SF). ARCTIC computes these in its training step from the GT meshes
    with ``knn_points`` (K = 1) over the full object mesh zero-padded to the batch's largest
    object; here they are per sample, padded to the largest template of the data root
    (``Vmax``), so the default collate batches them. Vertex counts come from the models
    (never hard-coded).

    Args:
        v_r, v_l: (Vh, 3) right / left hand vertices; v_o: (Vo, 3) object vertices (m).
        v_max: padded object length (≥ Vo).
        max_dist: clamp of the distances (m).

    Returns:
        ``{key: np.ndarray | int}`` with the keys of :data:`INTERFIELD_KEYS`.
    """
    r, l, o = (torch.as_tensor(np.asarray(v, dtype=np.float64)) for v in (v_r, v_l, v_o))
    n_o = int(o.shape[0])
    if n_o > v_max:
        raise ValueError(f"object has {n_o} vertices, more than the padded length {v_max}")
    out: dict[str, Any] = {}
    pairs = {"ro": (r, o), "lo": (l, o), "or": (o, r), "ol": (o, l)}
    res = {k: _nearest(a, b) for k, (a, b) in pairs.items()}
    for k, (dist, idx) in res.items():
        dist = dist.clamp(0.0, max_dist).numpy().astype(np.float32)
        idx = idx.numpy().astype(np.int64)
        if k in ("or", "ol"):
            dist = np.pad(dist, (0, v_max - n_o))
            idx = np.pad(idx, (0, v_max - n_o))
        out[f"dist.{k}"] = dist
        out[f"idx.{k}"] = idx
    out["object.v_len"] = n_o
    return {k: out[k] for k in INTERFIELD_KEYS}


class InterFieldTargets:
    """Interaction-field targets from world-frame pose parameters.

    Args:
        mano_layers: ``{"right": layer, "left": layer}`` (MANO layers of the data root).
        object_layer: the data root's :class:`~hogsa_loader.assets.objects.articulated.ArticulatedObjectLayer`.
        v_max: padded object length (default: the layer's largest template).
        max_dist: distance clamp (m); ``inf`` = none (ArcticNet-SF), 0.1 for InterField-SF.
    """

    def __init__(
        self, mano_layers: Mapping[str, Any], object_layer: Any, v_max: int | None = None, max_dist: float = math.inf
    ) -> None:
        self.layers = mano_layers
        self.object_layer = object_layer
        self.max_dist = float(max_dist)
        self.v_max = int(object_layer.v_len.max()) if v_max is None else int(v_max)

    def from_vertices(self, v_r: Any, v_l: Any, v_o: Any) -> dict[str, Any]:
        """Targets of one frame from already posed meshes (``v_o`` without padding)."""
        return interaction_field(v_r, v_l, v_o, self.v_max, self.max_dist)

    def __call__(self, poses: Mapping[str, Tensor], names: list[str]) -> list[dict[str, Any]]:
        """Targets of B frames.

        Args:
            poses: ``{side}_rot`` (B, 3), ``{side}_pose`` (B, 45), ``{side}_betas`` (B, 10),
                ``{side}_trans`` (B, 3), ``obj_arti`` (B, 1), ``obj_rot`` (B, 3),
                ``obj_trans`` (B, 3) in metres — one frame for hands and object.
            names: B object names.

        Returns:
            B dicts of :func:`interaction_field` targets.
        """
        P = {k: torch.as_tensor(v, dtype=torch.float64) for k, v in poses.items()}
        B = len(names)
        with torch.no_grad():
            verts = {
                side: self.layers[side](
                    global_orient=P[f"{side}_rot"],
                    hand_pose=P[f"{side}_pose"],
                    betas=P[f"{side}_betas"],
                    transl=P[f"{side}_trans"],
                ).vertices
                for side in ("right", "left")
            }
            obj = self.object_layer(
                angles=P["obj_arti"].reshape(B, 1), global_orient=P["obj_rot"], transl=P["obj_trans"], names=list(names)
            )
        n_o = obj["v_len"].tolist()
        return [self.from_vertices(verts["right"][b], verts["left"][b], obj["v"][b, : n_o[b]]) for b in range(B)]


def interfield_targets(root: Any, option: Union[bool, float, None]) -> Optional[InterFieldTargets]:
    """The datasets' ``interfield`` option → an :class:`InterFieldTargets` of ``root`` (or None).

    ``False``/``None``: none; ``True``: no clamp (ArcticNet-SF); a number: the clamp in metres.
    """
    if option is None or option is False:
        return None
    max_dist = math.inf if option is True else float(option)
    if not max_dist > 0:
        raise ValueError(f"interfield clamp must be > 0 m, got {option}")
    return InterFieldTargets(root.mano_layers(torch.float64), root.object_layer(), max_dist=max_dist)
