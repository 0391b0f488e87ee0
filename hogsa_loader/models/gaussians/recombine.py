"""Scenes whose hands and object come from different HOGS runs.

:func:`swap_hands` puts one run's hand Gaussians with another run's object (parameters
shared, not copied), each part shaded by the learned light of its own run
(:class:`PartLights`); :func:`hands_run` picks the run whose hands stand for a subject.
Hand Gaussians are bound to the MANO mesh, so they follow any pose and shape: a scene keeps
its own poses and labels and the hands take the other run's colours, with the other run's
learnt vertex offsets (a few millimetres, like the scene's own run's), so their outline can
move that much against the labels.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any, Optional

import torch
from torch import Tensor, nn

from hogsa_loader.models.gaussians.hogs_model import HogsModel
from hogsa_loader.render.gaussians import sh_colors

__all__ = ["PartLights", "hands_run", "swap_hands"]


class PartLights(nn.Module):
    """Learned lights of a scene whose parts come from different HOGS runs.

    Each Gaussian is shaded by the light of its part's run
    (:class:`~hogsa_loader.models.gaussians.shading.DirectionalLight`); a part without a light
    keeps its unshaded SH colour. Used as :attr:`HogsModel.light`.

    Args:
        lights: ``{part_id: DirectionalLight or None}``.
    """

    def __init__(self, lights: Mapping[int, nn.Module | None]) -> None:
        super().__init__()
        self.lights = nn.ModuleDict({str(k): v for k, v in lights.items() if v is not None})

    def forward(self, scene: Any, viewmats: Tensor) -> Tensor:
        """(B, C, N, 3) colours of the (B, N) scene seen from (B, C) cameras."""
        campos = torch.linalg.inv(viewmats)[..., :3, 3]
        dirs = scene.means[:, None] - campos[:, :, None, :]
        sh = scene.sh[:, None].expand(-1, viewmats.shape[1], -1, -1, -1)
        base = torch.clamp_min(sh_colors(scene.sh_degree, dirs, sh) + 0.5, 0.0)
        if scene.normals is None:
            return base
        out = base
        for key, light in self.lights.items():
            sel = (scene.part_ids == int(key)).to(base.device)[None, None, :, None]
            out = torch.where(sel, base * light.shade(scene.normals)[:, None], out)
        return out


def swap_hands(hands: HogsModel, obj: HogsModel) -> HogsModel:
    """A :class:`~hogsa_loader.models.gaussians.hogs_model.HogsModel` with the hand Gaussians of
    ``hands`` and the object Gaussians of ``obj`` (two HogsModels; parameters shared, not
    copied), each part lit by its own run's light (:class:`PartLights`)."""
    if hands is obj:
        return hands
    parts = {
        "hand_right": hands.parts["hand_right"],
        "hand_left": hands.parts["hand_left"],
        "object": obj.parts["object"],
    }
    light: nn.Module | None = None
    if hands.light is not None or obj.light is not None:
        light = PartLights(
            {
                parts["hand_right"].part_id: hands.light,
                parts["hand_left"].part_id: hands.light,
                parts["object"].part_id: obj.light,
            }
        )
    source = {
        **obj.source,
        "hands_from": hands.source.get("subject", "?"),
        "object_from": obj.source.get("subject", "?"),
    }
    return HogsModel(parts["hand_right"], parts["hand_left"], parts["object"], source=source, light=light).eval()


def hands_run(keys: Iterable[tuple[str, str]], subject: str, obj: str) -> Optional[tuple[str, str]]:
    """The ``(subject, object)`` run whose hands stand for ``subject`` next to ``obj``: the
    subject's run with that object when there is one, else its first run in sorted order;
    None when ``keys`` has no run of ``subject``."""
    runs = sorted(k for k in keys if k[0] == subject)
    if not runs:
        return None
    return (subject, obj) if (subject, obj) in runs else runs[0]
