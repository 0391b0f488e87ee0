"""Pictures of what a bundle has learnt: 360° orbits and pose transfer between subjects.

* :mod:`~hogsa_loader.view.orbit` — :func:`orbit_cameras` (N look-at cameras evenly spaced
  in azimuth on a full circle around the interaction centre), :func:`render_orbit` (one
  grasp from them, with and without the SRM); :func:`swap_hands` (hands of one run, object
  of another) is :mod:`hogsa_loader.models.gaussians.recombine`'s;
* :mod:`~hogsa_loader.view.transfer` — :func:`transfer_pose` (a grasp on another
  subject's hands: their betas, wrists re-solved to keep the contacts, articulation and
  object kept exactly) and :func:`transfer_report` (contact / penetration figures);
* :mod:`~hogsa_loader.view.job` — :func:`run_view`, what ``hogsa view`` runs
  (:class:`ViewConfig`).

Names are imported lazily, so ``from hogsa_loader.view import ViewConfig`` stays cheap.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "config": ("ViewConfig", "ViewError", "check_view_config", "parse_item"),
    "orbit": (
        "OrbitRender",
        "PartLights",
        "orbit_cameras",
        "orbit_azimuth",
        "orbit_intrinsics",
        "scene_bounds",
        "project",
        "posed_points",
        "swap_hands",
        "render_views",
        "render_orbit",
    ),
    "transfer": (
        "Transfer",
        "ViewPose",
        "align_wrists",
        "transfer_pose",
        "transfer_report",
        "state_poses",
        "subject_betas",
        "frame_pose",
        "default_pose",
        "bank_pose",
    ),
    "pictures": ("neutral_background", "to_uint8", "draw_keypoints", "sheet"),
    "job": ("run_view",),
}
_WHERE = {name: mod for mod, names in _EXPORTS.items() for name in names}

__all__ = [
    "OrbitRender",
    "PartLights",
    "Transfer",
    "ViewConfig",
    "ViewError",
    "ViewPose",
    "align_wrists",
    "bank_pose",
    "check_view_config",
    "default_pose",
    "draw_keypoints",
    "frame_pose",
    "neutral_background",
    "orbit_azimuth",
    "orbit_cameras",
    "orbit_intrinsics",
    "parse_item",
    "posed_points",
    "project",
    "render_orbit",
    "render_views",
    "run_view",
    "scene_bounds",
    "sheet",
    "state_poses",
    "subject_betas",
    "swap_hands",
    "to_uint8",
    "transfer_pose",
    "transfer_report",
]


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        return getattr(importlib.import_module(f"hogsa_loader.view.{_WHERE[name]}"), name)
    raise AttributeError(f"module 'hogsa_loader.view' has no attribute {name!r}")
