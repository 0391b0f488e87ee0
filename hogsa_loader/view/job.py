"""``hogsa view``: orbit sheets and animations, and the pose-transfer grid of a bundle."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.assets.objects.articulated import ArticulatedObjectLayer
from hogsa_loader.assets.objects.template import load_object_templates
from hogsa_loader.compose import make_backgrounds
from hogsa_loader.errors import HogsaError
from hogsa_loader.models.bundle import load_bundle
from hogsa_loader.models.gaussians.recombine import hands_run
from hogsa_loader.models.pom.hands import hand_infos
from hogsa_loader.models.pom.objects import ObjectSet
from hogsa_loader.models.srm import load_srm
from hogsa_loader.view.config import ViewConfig, ViewError, check_view_config, parse_item
from hogsa_loader.view.orbit import (
    orbit_azimuth,
    orbit_cameras,
    orbit_intrinsics,
    posed_points,
    project,
    render_orbit,
    render_views,
    scene_bounds,
    swap_hands,
)
from hogsa_loader.view.pictures import (
    caption,
    demo_photographs,
    draw_keypoints,
    neutral_background,
    sheet,
    to_uint8,
    write_png,
    write_video,
)
from hogsa_loader.view.transfer import (
    ViewPose,
    bank_pose,
    default_pose,
    frame_pose,
    state_poses,
    subject_betas,
    transfer_pose,
    transfer_report,
)

__all__ = ["run_view"]


@dataclass
class _Setup:
    bundle: Any
    root: Any
    poses: list[ViewPose]
    subjects: list[str]
    hands_key: dict[str, tuple[str, str]]


def _prepare(cfg: ViewConfig) -> _Setup:
    """Load the bundle and the pose sources; every request error is a :class:`ViewError`."""
    check_view_config(cfg)
    try:
        bundle = load_bundle(cfg.bundle, data_root=cfg.data)  # type: ignore[arg-type]
    except HogsaError as exc:
        raise ViewError(" ".join(str(exc).split())) from None
    key = (str(cfg.subject), str(cfg.object))
    if key not in bundle.hogs:
        raise ViewError(
            f"the bundle has no HOGS model for {key[0]}/{key[1]} (has {', '.join(f'{s}/{o}' for s, o in bundle.keys)})"
        )
    hands_key = {key[0]: key}
    for sid in cfg.transfer_to:
        run = hands_run(bundle.keys, sid, key[1])
        if run is None:
            raise ViewError(
                f"--transfer-to {sid}: the bundle has no HOGS model of that subject (subjects: "
                f"{', '.join(sorted({s for s, _ in bundle.keys}))})"
            )
        hands_key[sid] = run
    root = ArcticRoot(cfg.data)  # type: ignore[arg-type]
    for sid in hands_key:
        if sid not in root.subjects():
            raise ViewError(f"subject {sid} is not in {cfg.data} (misc.json has {', '.join(root.subjects())})")
    poses = [frame_pose(root, key[0], *parse_item(v, "--frame", "SEQ:IDX")) for v in cfg.frame]
    poses += [bank_pose(bundle, *parse_item(v, "--pose-bank", "NAME:I")) for v in cfg.pose_bank]
    if not poses:
        poses = [default_pose(root, key[0], key[1])]
    for p in poses:
        if p.object != key[1]:
            raise ViewError(f"pose source {p.label} holds a {p.object}, the model shows a {key[1]}")
    if cfg.srm and bundle.srm is None:
        raise ViewError("the bundle has no SRM checkpoint; pass --no-srm")
    return _Setup(bundle, root, poses, [key[0], *cfg.transfer_to], hands_key)


def _dataset_view(root: Any, sid: str, centre: np.ndarray, up: np.ndarray) -> tuple[float, float]:
    """(median distance of the subject's dataset cameras to ``centre``, azimuth of view 1)."""
    misc = root.subject_misc(sid)
    R = misc.world2cam[:, :3, :3]
    eyes = -np.einsum("vji,vj->vi", R, misc.world2cam[:, :3, 3])
    return float(np.median(np.linalg.norm(eyes - centre, axis=1))), orbit_azimuth(centre, eyes[0], up)


def _transfer_line(label: str, sid: str, rec: dict[str, Any]) -> str:
    def err(stage: str) -> str:
        items = rec[stage]["contact_error_mm"].items()
        return ", ".join(f"{s} {v:.1f} mm" for s, v in items if v is not None) or "no contact"

    pen = {k: rec[k]["penetration_depth_mm"] for k in ("source", "transferred")}
    return (
        f"[transfer] {label} -> {sid}: penetration {pen['transferred']:.1f} mm (source {pen['source']:.1f} mm), "
        f"contact error {err('transferred')} (wrists only aligned: {err('aligned')})"
    )


class _Scenes:
    """The bundle's models, SRM and geometry, loaded once."""

    def __init__(self, cfg: ViewConfig, su: _Setup) -> None:
        self.cfg, self.su = cfg, su
        self.obj = str(cfg.object)
        self.dev = torch.device(cfg.device)
        self.layers = su.root.mano_layers()
        names = sorted({self.obj, *(k[1] for k in su.hands_key.values())})  # the objects of the runs loaded
        self.templates = load_object_templates(su.root.meta_dir, names=names)
        self.object_layer = ArticulatedObjectLayer({self.obj: self.templates[self.obj]})
        self._models: dict[tuple[str, str], Any] = {}
        src = self.model((str(cfg.subject), self.obj))
        self.scene = {sid: swap_hands(self.model(su.hands_key[sid]), src) for sid in su.subjects}
        self.refiner = None
        if cfg.srm:
            srm = load_srm(su.bundle.srm.path, device=self.dev)
            self.refiner = lambda rgb, alpha: srm.refine(rgb.to(self.dev), alpha.to(self.dev)).float().cpu()
        self.up = np.array([0.0, 0.0, 1.0])  # ARCTIC world frame

    def model(self, key: tuple[str, str]) -> Any:
        if key not in self._models:
            self._models[key] = self.su.bundle.load_hogs(key, self.layers, self.templates, self.dev)
        return self._models[key]

    def posed(self, state: Any) -> tuple[dict[str, Tensor], dict[str, np.ndarray], np.ndarray]:
        """POSE_KEYS, posed points, and the (P, 3) mesh points of one grasp."""
        poses = state_poses(state)
        pts = posed_points(self.layers, self.object_layer, poses, self.obj)
        return poses, pts, np.concatenate([pts[k][0] for k in ("verts.right", "verts.left", "verts.object")])

    def camera(self, centre: np.ndarray) -> tuple[float, float]:
        """Orbit distance and the azimuth of the first view (the shown subject's dataset view 1)."""
        d, az0 = _dataset_view(self.su.root, str(self.cfg.subject), centre, self.up)
        return (self.cfg.distance if self.cfg.distance is not None else d), az0


def _orbit(sc: _Scenes, sid: str, vp: ViewPose, state: Any, bg: Tensor, out: Path) -> dict[str, Any]:
    """``orbit_<sid>.png`` (+ animation) of one grasp on ``sid``'s hands; returns its record."""
    cfg = sc.cfg
    poses, _, points = sc.posed(state)
    d, az0 = sc.camera(scene_bounds(points)[0])
    orb = render_orbit(
        sc.scene[sid],
        poses,
        points,
        cfg.orbit,
        cfg.elevation,
        d,
        cfg.size,
        up=sc.up,
        azimuth0_deg=az0,
        refiner=sc.refiner,
        backend=cfg.backend,
    )
    raw = to_uint8(orb.rgb, orb.alpha, bg)
    ref = to_uint8(orb.refined, orb.alpha, bg) if orb.refined is not None else None
    caps = [f"{a - az0:+.4g} deg" for a in orb.azimuth_deg]
    what = f"{vp.label} on {sid}'s hands" + (" (transferred)" if sid != vp.subject else "")
    rows = [
        (
            f"HOGS: {what}; azimuth from dataset view 1, elevation {cfg.elevation:g} deg, distance {d:.2f} m",
            list(raw),
            caps,
        )
    ]
    if ref is not None:
        rows.append(("HOGS + SRM", list(ref), caps))
    png = out / f"orbit_{sid}.png"
    write_png(png, sheet(rows, cols=min(8, cfg.orbit)))
    rec = {
        "png": str(png),
        "pose": vp.label,
        "views": cfg.orbit,
        "azimuth_deg": [round(float(a), 3) for a in orb.azimuth_deg],
        "elevation_deg": cfg.elevation,
        "distance_m": round(orb.distance, 4),
        "centre": [round(float(c), 5) for c in orb.centre],
        "radius_m": round(orb.radius, 4),
        "seconds": {k: round(v, 2) for k, v in orb.seconds.items()},
    }
    if cfg.video != "none":
        frames = [
            np.concatenate([caption(raw[j], "HOGS")] + ([caption(ref[j], "HOGS + SRM")] if ref is not None else []), 1)
            for j in range(cfg.orbit)
        ]
        rec["video"] = str(out / f"orbit_{sid}.{cfg.video}")
        write_video(Path(rec["video"]), frames, cfg.fps)
    return rec


def _cells(sc: _Scenes, sid: str, state: Any, bg: Tensor) -> list[np.ndarray]:
    """Transfer-grid cells of the grasp on ``sid``'s hands seen from dataset view 1's azimuth:
    HOGS, then HOGS + SRM when the SRM is on."""
    cfg = sc.cfg
    poses, pts, points = sc.posed(state)
    centre, radius = scene_bounds(points)
    d, az0 = sc.camera(centre)
    w2c = orbit_cameras(centre, 1, cfg.elevation, d, up=sc.up, azimuth0_deg=az0)
    K = orbit_intrinsics(cfg.size, d, radius)
    rgb, alpha, ref = render_views(sc.scene[sid], poses, w2c, K, cfg.size, refiner=sc.refiner, backend=cfg.backend)
    imgs = [to_uint8(x, alpha, bg)[0] for x in (rgb, ref) if x is not None]
    if cfg.keypoints:
        kp = {k: project(pts[k][0], w2c, K)[0] for k in ("joints.right", "joints.left", "kp3d")}
        imgs = [draw_keypoints(im, kp) for im in imgs]
    return imgs


def _grasps(
    cfg: ViewConfig, su: _Setup, sc: _Scenes, say: Callable[[str], None]
) -> tuple[dict[tuple[int, str], Any], list[dict[str, Any]]]:
    """The grasp of every (pose source i, subject) and the transfer records.

    A pose source made with a subject's own hands is used as it is; on any other subject it is
    transferred (:func:`~hogsa_loader.view.transfer.transfer_pose`).
    """
    grasps: dict[tuple[int, str], Any] = {}
    transfers: list[dict[str, Any]] = []
    if any(vp.subject != sid for vp in su.poses for sid in su.subjects):
        infos = hand_infos(sc.layers)
        objects = ObjectSet({sc.obj: sc.templates[sc.obj]}, sdf_voxel=cfg.contact_voxel)
        betas = {sid: subject_betas(su.root, sid) for sid in su.subjects}
    for i, vp in enumerate(su.poses):
        for sid in su.subjects:
            if sid == vp.subject:
                grasps[i, sid] = vp.state
                continue
            tr = transfer_pose(vp.state, betas[sid], infos, objects, steps=cfg.regrasp_steps)
            grasps[i, sid] = tr.state
            rec = transfer_report(tr, infos, objects)[0]
            transfers.append({"pose": vp.label, "from": vp.subject, "to": sid, **rec})
            say(_transfer_line(vp.label, sid, rec))
    return grasps, transfers


def _backgrounds(cfg: ViewConfig, out: Path) -> Callable[[int], Tensor]:
    """``k`` → the (S, S, 3) background of picture ``k``: neutral, or a photograph drawn with seed
    ``cfg.seed * 1000 + k``."""
    photo = None
    if cfg.background == "photo":
        photo = make_backgrounds(folder=cfg.backgrounds or demo_photographs(out / "backgrounds"))

    def background(k: int) -> Tensor:
        if photo is None:
            return neutral_background(cfg.size)
        return photo.sample(1, cfg.size, cfg.size, torch.Generator().manual_seed(cfg.seed * 1000 + k))[0]

    return background


def _orbits(
    sc: _Scenes,
    grasps: dict[tuple[int, str], Any],
    background: Callable[[int], Tensor],
    out: Path,
    say: Callable[[str], None],
) -> dict[str, Any]:
    """The orbit of the first pose source on every subject (none when ``cfg.orbit`` is 0); their records."""
    cfg, su = sc.cfg, sc.su
    orbits: dict[str, Any] = {}
    for sid in su.subjects if cfg.orbit > 0 else ():
        orbits[sid] = rec = _orbit(sc, sid, su.poses[0], grasps[0, sid], background(0), out)
        srm_s = f" + SRM {rec['seconds']['srm']:.1f} s" if sc.refiner is not None else ""
        say(f"[orbit] {sid}: {cfg.orbit} views in {rec['seconds']['render']:.1f} s{srm_s} -> {rec['png']}")
    return orbits


def _transfer_grid(
    sc: _Scenes, grasps: dict[tuple[int, str], Any], background: Callable[[int], Tensor], out: Path
) -> Path:
    """``transfer.png``: a row per pose source (HOGS, then HOGS + SRM when on), a column per subject."""
    su = sc.su
    rows = []
    for i, vp in enumerate(su.poses):
        cells = [
            _cells(sc, sid, grasps[i, sid], background(1 + i * len(su.subjects) + j))
            for j, sid in enumerate(su.subjects)
        ]
        caps = [sid + ("" if sid == vp.subject else " (transferred)") for sid in su.subjects]
        rows.append((f"pose: {vp.label} (HOGS)", [c[0] for c in cells], caps))
        if sc.refiner is not None:
            rows.append((f"pose: {vp.label} (HOGS + SRM)", [c[1] for c in cells], caps))
    grid = out / "transfer.png"
    write_png(grid, sheet(rows, cols=len(su.subjects)))
    return grid


def run_view(cfg: ViewConfig, log: Callable[[str], None] | None = print) -> dict[str, Any]:
    """Orbits and pose-transfer pictures of a bundle.

    Writes into ``cfg.out``: ``orbit_<sid>.png`` and ``orbit_<sid>.gif`` (or ``.mp4``) of
    the first pose source on the shown subject and on every ``transfer_to`` subject,
    ``transfer.png`` (rows: pose sources, each rendered by HOGS and, with ``cfg.srm``, by
    HOGS + SRM; columns: the shown subject, then the targets), ``view.json`` (settings,
    timings, pose sources, the transfer figures of
    :func:`~hogsa_loader.view.transfer.transfer_report`, outputs).

    Raises:
        ViewError: a request that cannot be served (before anything is rendered).

    Returns:
        the ``view.json`` record.
    """
    say = log or (lambda s: None)
    t_start = time.perf_counter()
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    su = _prepare(cfg)
    out = Path(os.path.abspath(cfg.out))  # type: ignore[arg-type]
    out.mkdir(parents=True, exist_ok=True)
    sc = _Scenes(cfg, su)
    seconds = {"setup": time.perf_counter() - t_start}
    t0 = time.perf_counter()
    grasps, transfers = _grasps(cfg, su, sc, say)
    seconds["transfer"] = time.perf_counter() - t0
    background = _backgrounds(cfg, out)
    t0 = time.perf_counter()
    orbits = _orbits(sc, grasps, background, out, say)
    seconds["orbit"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    grid = _transfer_grid(sc, grasps, background, out)
    seconds["grid"] = time.perf_counter() - t0
    seconds["total"] = time.perf_counter() - t_start

    record = {
        "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(cfg).items()},
        "subjects": su.subjects,
        "hand_models": {sid: "/".join(k) for sid, k in su.hands_key.items()},
        "object_model": f"{cfg.subject}/{sc.obj}",
        "poses": [{"label": p.label, **p.origin} for p in su.poses],
        "orbits": orbits,
        "transfers": transfers,
        "outputs": {"transfer": str(grid), **{f"orbit_{k}": v["png"] for k, v in orbits.items()}},
        "seconds": {k: round(v, 2) for k, v in seconds.items()},
    }
    (out / "view.json").write_text(json.dumps(record, indent=1))
    say(f"[view] transfer grid: {grid}\n[view] record: {out / 'view.json'} ({seconds['total']:.1f} s)")
    return record
