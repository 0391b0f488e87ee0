"""360° orbits: look-at cameras on a full circle around the interaction centre, and
rendering one grasp from them with a HOGS model, with and without the SRM.

A scene may take its hand and object Gaussians from different runs (:func:`swap_hands`
of :mod:`hogsa_loader.models.gaussians.recombine`, used for pose transfer); each part is then
shaded by the learned light of its own run (:class:`PartLights`).

Conventions: ARCTIC world frame, metres, OpenCV cameras (``p_cam = R p + t``); poses as
:data:`~hogsa_loader.models.gaussians.hogs_model.POSE_KEYS` tensors, batch first.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from hogsa_loader.assets import conventions
from hogsa_loader.assets.conventions import render_intrinsics
from hogsa_loader.models.gaussians.recombine import PartLights, swap_hands
from hogsa_loader.sample.cameras import look_at

__all__ = [
    "OrbitRender",
    "PartLights",
    "orbit_azimuth",
    "orbit_cameras",
    "orbit_intrinsics",
    "posed_points",
    "project",
    "render_orbit",
    "render_views",
    "scene_bounds",
    "swap_hands",
]

SIDES = ("right", "left")


def _horizontal_basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit ``up`` and two unit vectors spanning the plane orthogonal to it (right-handed)."""
    up = np.asarray(up, dtype=np.float64).reshape(3)
    n = np.linalg.norm(up)
    if not np.isfinite(n) or n < 1e-9:
        raise ValueError(f"up must be a finite non-zero 3-vector, got {up.tolist()}")
    up = up / n
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(up, helper)
    e1 /= np.linalg.norm(e1)
    return up, e1, np.cross(up, e1)


def orbit_cameras(
    center: Sequence[float],
    n: int,
    elevation_deg: float,
    distance: float,
    up: Sequence[float] = (0.0, 0.0, 1.0),
    azimuth0_deg: float = 0.0,
) -> np.ndarray:
    """World→camera matrices of ``n`` cameras on a full circle around ``center``.

    Camera i sits at azimuth ``azimuth0_deg + 360 i / n`` (about ``up``), elevation
    ``elevation_deg`` above the plane through ``center`` orthogonal to ``up``, at
    ``distance`` from ``center``, and looks at ``center`` with no roll (image up = the
    projection of ``up``).

    Args:
        center: (3,) look-at point (world frame, m).
        n: number of views (≥ 1).
        elevation_deg: in (−90, 90).
        distance: camera-to-centre distance (m, > 0).
        up: (3,) world up vector (ARCTIC: +z).
        azimuth0_deg: azimuth of the first camera (0 = the first horizontal axis of ``up``'s
            basis; see :func:`orbit_azimuth`).

    Returns:
        (n, 4, 4) float64 OpenCV extrinsics.
    """
    if int(n) < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    if not -90.0 < float(elevation_deg) < 90.0:
        raise ValueError(f"elevation_deg must be in (-90, 90), got {elevation_deg}")
    if not float(distance) > 0:
        raise ValueError(f"distance must be > 0, got {distance}")
    up_u, e1, e2 = _horizontal_basis(np.asarray(up))
    c = np.asarray(center, dtype=np.float64).reshape(1, 3)
    az = np.radians(float(azimuth0_deg) + 360.0 * np.arange(int(n)) / int(n))
    el = np.radians(float(elevation_deg))
    dirs = np.cos(el) * (np.cos(az)[:, None] * e1 + np.sin(az)[:, None] * e2) + np.sin(el) * up_u
    eye = c + float(distance) * dirs
    return look_at(eye, np.repeat(c, int(n), 0), up_u)


def orbit_azimuth(center: Sequence[float], eye: Sequence[float], up: Sequence[float] = (0.0, 0.0, 1.0)) -> float:
    """Azimuth (degrees, :func:`orbit_cameras`' convention) of a camera centre ``eye`` seen from ``center``."""
    _, e1, e2 = _horizontal_basis(np.asarray(up))
    d = np.asarray(eye, dtype=np.float64).reshape(3) - np.asarray(center, dtype=np.float64).reshape(3)
    return float(np.degrees(np.arctan2(d @ e2, d @ e1)))


def orbit_intrinsics(size: int, distance: float, radius: float, fill: float = 0.9) -> np.ndarray:
    """(3, 3) label-convention intrinsics of a square ``size`` image in which a sphere of
    ``radius`` at ``distance`` spans ``fill`` of the width (principal point at the centre)."""
    if not distance > radius * 1.05:
        raise ValueError(f"camera distance {distance:.3f} m is not outside the scene (radius {radius:.3f} m)")
    f = fill * 0.5 * size * np.sqrt(distance**2 - radius**2) / radius
    c = (size - 1) / 2.0
    return np.array([[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]])


def scene_bounds(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Interaction centre (centre of the axis-aligned box of ``points`` (P, 3)) and the
    radius of the sphere about it that holds them all."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    centre = 0.5 * (p.min(0) + p.max(0))
    return centre, float(np.linalg.norm(p - centre, axis=1).max())


def project(points: np.ndarray, world2cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(C, P, 2) pixel coordinates (label convention) of (P, 3) world points in C cameras."""
    w2c = np.asarray(world2cam, dtype=np.float64).reshape(-1, 4, 4)
    return conventions.project(conventions.transform(w2c, np.asarray(points, dtype=np.float64)), np.asarray(K, float))


def posed_points(
    layers: Mapping[str, Any], object_layer: Any, poses: Mapping[str, Tensor], obj: str
) -> dict[str, np.ndarray]:
    """World points of B posed frames (float64 numpy).

    Args:
        layers: ``{"right", "left"}`` MANO layers; object_layer: the data root's
            :class:`~hogsa_loader.assets.objects.articulated.ArticulatedObjectLayer`.
        poses: :data:`~hogsa_loader.models.gaussians.hogs_model.POSE_KEYS` tensors, batch B.
        obj: object name.

    Returns:
        ``verts.right`` / ``verts.left`` (B, Vh, 3), ``joints.right`` / ``joints.left``
        (B, 21, 3), ``verts.object`` (B, Vo, 3), ``kp3d`` (B, 32, 3).
    """
    out: dict[str, np.ndarray] = {}
    with torch.no_grad():
        for side in SIDES:
            lay = layers[side]
            dt = lay.v_template.dtype
            res = lay(
                global_orient=poses[f"{side}_rot"].to(dt),
                hand_pose=poses[f"{side}_pose"].to(dt),
                betas=poses[f"{side}_betas"].to(dt),
                transl=poses[f"{side}_trans"].to(dt),
            )
            out[f"verts.{side}"] = res.vertices.double().cpu().numpy()
            out[f"joints.{side}"] = res.joints.double().cpu().numpy()
        B = poses["obj_rot"].shape[0]
        res = object_layer(
            angles=poses["obj_arti"].reshape(B, 1).float(),
            global_orient=poses["obj_rot"].float(),
            transl=poses["obj_trans"].float(),
            names=[obj] * B,
        )
        n_o = int(object_layer.v_len[object_layer.indices([obj])][0])
    out["verts.object"] = res["v"][:, :n_o].double().cpu().numpy()
    out["kp3d"] = res["kp3d"].double().cpu().numpy()
    return out


def render_views(
    model: Any,
    poses: Mapping[str, Tensor],
    world2cam: np.ndarray,
    K: np.ndarray,
    size: int,
    *,
    refiner: Callable[[Tensor, Tensor], Tensor] | None = None,
    chunk: int = 8,
    backend: str = "auto",
) -> tuple[Tensor, Tensor, Tensor | None]:
    """Render one posed frame from C cameras (``chunk`` cameras per render call).

    Args:
        model: a :class:`~hogsa_loader.models.gaussians.hogs_model.HogsModel`.
        poses: POSE_KEYS tensors of one frame (batch 1; further rows are ignored).
        world2cam: (C, 4, 4); K: (3, 3) label-convention intrinsics of a ``size`` square.
        refiner: optional ``(rgb, alpha) -> rgb`` (e.g. ``SRM.refine``), applied per chunk.

    Returns:
        rgb (C, S, S, 3) premultiplied on black, alpha (C, S, S, 1), refined rgb (C, S, S, 3)
        or None; float32, CPU.
    """
    p = next(model.parameters())
    dev, dt = p.device, p.dtype
    P = {k: v[:1].to(dev, dt) for k, v in poses.items()}
    Kr = torch.as_tensor(render_intrinsics(np.asarray(K)), dtype=dt, device=dev)
    w2c = torch.as_tensor(np.asarray(world2cam), dtype=dt, device=dev).reshape(-1, 4, 4)
    rgbs, alphas, refined = [], [], []
    with torch.no_grad():
        for i in range(0, w2c.shape[0], max(1, int(chunk))):
            v = w2c[i : i + chunk][None]
            out = model.render(P, v, Kr.expand(1, v.shape[1], 3, 3), size, size, render_mode="RGB", backend=backend)
            rgb, alpha = out.rgb[0].float(), out.alpha[0].float()
            rgbs.append(rgb.cpu())
            alphas.append(alpha.cpu())
            if refiner is not None:
                refined.append(refiner(rgb, alpha).float().cpu())
    return torch.cat(rgbs), torch.cat(alphas), (torch.cat(refined) if refiner is not None else None)


@dataclass
class OrbitRender:
    """One orbit.

    Attributes:
        world2cam: (N, 4, 4); K: (3, 3) label-convention intrinsics of the ``size`` square.
        azimuth_deg: (N,) azimuths; elevation_deg, distance: the orbit's.
        centre: (3,) interaction centre; radius: bounding radius of the posed meshes.
        rgb, alpha: (N, S, S, 3) / (N, S, S, 1) HOGS renders (premultiplied, float32).
        refined: (N, S, S, 3) SRM output, or None.
        seconds: ``{"render", "srm"}`` wall time.
    """

    world2cam: np.ndarray
    K: np.ndarray
    azimuth_deg: np.ndarray
    elevation_deg: float
    distance: float
    centre: np.ndarray
    radius: float
    rgb: Tensor
    alpha: Tensor
    refined: Tensor | None
    seconds: dict[str, float]


def render_orbit(
    model: Any,
    poses: Mapping[str, Tensor],
    points: np.ndarray,
    n: int = 16,
    elevation_deg: float = 20.0,
    distance: float | None = None,
    size: int = 256,
    *,
    up: Sequence[float] = (0.0, 0.0, 1.0),
    azimuth0_deg: float = 0.0,
    refiner: Callable[[Tensor, Tensor], Tensor] | None = None,
    fill: float = 0.9,
    backend: str = "auto",
) -> OrbitRender:
    """Render one grasp on a full 360° orbit around its interaction centre.

    Args:
        model: HogsModel; poses: POSE_KEYS of one frame.
        points: (P, 3) posed mesh points (hands and object) giving the centre and radius
            (:func:`scene_bounds`).
        n, elevation_deg, up, azimuth0_deg: see :func:`orbit_cameras`.
        distance: camera distance (m); None = 4 × the bounding radius.
        size: square image side (px).
        refiner: optional SRM ``(rgb, alpha) -> rgb``: also render the refined views.
        fill: fraction of the image width the bounding sphere spans.
    """
    centre, radius = scene_bounds(points)
    d = float(distance) if distance is not None else 4.0 * radius
    w2c = orbit_cameras(centre, n, elevation_deg, d, up=up, azimuth0_deg=azimuth0_deg)
    K = orbit_intrinsics(size, d, radius, fill)
    t0 = time.perf_counter()
    rgb, alpha, _ = render_views(model, poses, w2c, K, size, backend=backend)
    t1 = time.perf_counter()
    refined = None
    if refiner is not None:
        with torch.no_grad():
            refined = torch.cat([refiner(rgb[i : i + 8], alpha[i : i + 8]).float().cpu() for i in range(0, n, 8)])
    t2 = time.perf_counter()
    az = float(azimuth0_deg) + 360.0 * np.arange(n) / n
    return OrbitRender(
        world2cam=w2c,
        K=K,
        azimuth_deg=az,
        elevation_deg=float(elevation_deg),
        distance=d,
        centre=centre,
        radius=radius,
        rgb=rgb,
        alpha=alpha,
        refined=refined,
        seconds={"render": t1 - t0, "srm": t2 - t1},
    )
