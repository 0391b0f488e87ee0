"""Grasp-quality metrics (those of GraspTTA's ``metric/*.py``), bimanual."""

from __future__ import annotations

from typing import Mapping, Optional

import numpy as np
import torch
from torch import Tensor

from hogsa_loader.assets.objects.articulated import articulation_matrix
from hogsa_loader.assets.objects.template import TOP
from hogsa_loader.models.pom.geometry import grid_inside, ray_parity_inside
from hogsa_loader.models.pom.hands import SIDES, HandInfo
from hogsa_loader.models.pom.objects import VOLUME_PITCH, ObjectSet
from hogsa_loader.models.pom.state import GraspState, canonical_hands

__all__ = ["CONTACT_DISTANCE", "ACCEPT_VOLUME", "grasp_metrics", "diversity", "summarize"]

#: Contact threshold (5 mm, GraspTTA).
CONTACT_DISTANCE = 0.005
#: Acceptance threshold of the intersection volume (4 cm³).
ACCEPT_VOLUME = 4e-6
#: Vertices whose SDF-grid distance is below this are tested exactly (parity + distance);
#: the grid is accurate to well under this, so the others are outside and not in contact.
CANDIDATE_DISTANCE = 0.008


def _inside_and_distance(g: object, Rt: Tensor, pts: Tensor, near: Tensor) -> tuple[np.ndarray, np.ndarray]:
    """For (P, 3) canonical points, with only the ``near`` ones tested exactly: inside the object
    (ray parity against either part's triangles) and distance to its surface (m; inf untested)."""
    cand = near.nonzero().squeeze(-1)
    inside = torch.zeros(pts.shape[0], dtype=torch.bool)
    dist = np.full(pts.shape[0], np.inf)
    for part in g.parts:
        q = pts[cand] @ Rt if part == TOP else pts[cand]
        inside[cand] |= ray_parity_inside(q, g.tris[part])
        if len(cand):
            d, _ = g.trees[part].query(q.numpy(), workers=1)
            dist[cand.numpy()] = np.minimum(dist[cand.numpy()], d)
    return inside.numpy(), dist


def _intersection_count(g: object, Rt: Tensor, V: Mapping[str, Tensor], infos: Mapping[str, HandInfo]) -> int:
    """Object voxel centres (per part's voxel grid) inside a (wrist-capped) hand mesh, summed over hands."""
    count = 0
    for part in g.parts:
        (xs, ys, zs), obj_in = g.vox_grid[part]
        if not bool(obj_in.any()):
            continue
        for s in SIDES:
            vh = V[s] @ Rt if part == TOP else V[s]  # hand in the part's frame
            tris = infos[s].capped.triangles(vh).numpy()
            lo, hi = tris.reshape(-1, 3).min(0), tris.reshape(-1, 3).max(0)
            kx = (xs >= lo[0]) & (xs <= hi[0])
            ky = (ys >= lo[1]) & (ys <= hi[1])
            kz = (zs >= lo[2]) & (zs <= hi[2])
            if not (kx.any() and ky.any() and kz.any()):
                continue
            hand_in = grid_inside(tris, xs[kx], ys[ky], zs[kz])
            sub = obj_in[np.ix_(kz, ky, kx)].numpy()
            count += int((hand_in & sub).sum())
    return count


def _canonical_vertices(state: GraspState, infos: Mapping[str, HandInfo]) -> dict[str, Tensor]:
    """side -> (B, 778, 3) float64 CPU hand vertices in the object canonical frame."""
    with torch.no_grad():
        dt = infos["right"].layer.v_template.dtype
        dev = infos["right"].layer.v_template.device
        hands = canonical_hands(state.map(lambda t: t.detach().to(dev, dt)), infos)
        return {s: hands[s].vertices.double().cpu() for s in SIDES}


def grasp_metrics(
    state: GraspState, infos: Mapping[str, HandInfo], objects: ObjectSet, active: Optional[Mapping[str, Tensor]] = None
) -> dict[str, np.ndarray]:
    """Per-sample grasp-quality metrics.

    Per sample (both hands together):

    * ``penetration_depth``: max over the hand vertices that are inside the object — by ray
      parity against the object's part meshes (GraspTTA's fixed ray) — of their distance to
      the object surface (m); 0 when none is inside;
    * ``intersection``: the object voxelised at 5 mm (voxel centres inside a part, by parity),
      number of voxel centres inside each (wrist-capped) hand mesh × pitch³, summed over the
      hands (m³);
    * ``contact_ratio``: fraction of hand vertices inside or within 5 mm of the surface;
    * ``contact``: per hand, at least one such vertex;
    * ``accept``: GraspTTA's acceptance without its physics test: intersection < 4 cm³ and
      contact (every hand listed as ``active`` — the hands touching the object in the source
      frame — must touch; at least one hand must touch, unless ``active`` lists none for that
      frame: a frame without contact is accepted on intersection alone). GraspTTA also
      requires a simulated object displacement < 3 cm; no simulator runs here, so that
      criterion is not applied.

    Args:
        state: B grasps; infos: hands; objects: geometry.
        active: side -> (B,) bool hands that must touch for acceptance (default: none
            required beyond "at least one hand touches").

    Returns:
        dict of (B,) arrays: ``penetration_depth`` (m), ``intersection`` (m³),
        ``contact_ratio``, ``contact_right``, ``contact_left`` (bool), ``accept`` (bool).
    """
    B = state.batch
    verts = _canonical_vertices(state, infos)
    arti = state.obj_arti.detach().double().cpu()
    with torch.no_grad():  # SDF-grid pre-filter: only vertices near or below the surface are tested
        sdf = {s: objects.sdf(verts[s].float(), state.obj_names, arti.float()) for s in SIDES}
    depth = np.zeros(B)
    volume = np.zeros(B)
    ratio = np.zeros(B)
    contact = {s: np.zeros(B, dtype=bool) for s in SIDES}
    for b in range(B):
        g = objects.geometry(state.obj_names[b])
        Rt = articulation_matrix(arti[b : b + 1])[0]  # top-part frame -> canonical
        V = {s: verts[s][b] for s in SIDES}
        near = torch.cat([sdf[s][b] for s in SIDES]) < CANDIDATE_DISTANCE
        ins, dist = _inside_and_distance(g, Rt, torch.cat([V[s] for s in SIDES]), near)
        depth[b] = float(dist[ins].max()) if ins.any() else 0.0
        touch = ins | (dist <= CONTACT_DISTANCE)
        ratio[b] = float(touch.mean())
        n0 = 0
        for s in SIDES:
            n = V[s].shape[0]
            contact[s][b] = bool(touch[n0 : n0 + n].any())
            n0 += n
        volume[b] = _intersection_count(g, Rt, V, infos) * VOLUME_PITCH**3
    need = np.ones(B, dtype=bool)
    touches = contact["right"] | contact["left"]
    if active is not None:
        source_touches = np.zeros(B, dtype=bool)
        for s in SIDES:
            a = np.asarray(active[s].cpu())
            need &= ~a | contact[s]
            source_touches |= a
        touches |= ~source_touches  # a frame whose source has no touching hand needs none
    accept = (volume < ACCEPT_VOLUME) & touches & need
    return {
        "penetration_depth": depth,
        "intersection": volume,
        "contact_ratio": ratio,
        "contact_right": contact["right"],
        "contact_left": contact["left"],
        "accept": accept,
    }


def both_hand_joints(state: GraspState, infos: Mapping[str, HandInfo]) -> Tensor:
    """(B, 42, 3) right then left joints in the object canonical frame."""
    with torch.no_grad():
        dt = infos["right"].layer.v_template.dtype
        dev = infos["right"].layer.v_template.device
        hands = canonical_hands(state.map(lambda t: t.detach().to(dev, dt)), infos)
    return torch.cat([hands["right"].joints, hands["left"].joints], 1).float().cpu()


def diversity(joints: Tensor, max_samples: int = 2000) -> float:
    """Mean pairwise distance (m) between samples: mean per-joint Euclidean distance.

    Args:
        joints: (N, J, 3); at most ``max_samples`` (the first ones) are used.
    """
    j = joints[:max_samples].double()
    N = j.shape[0]
    if N < 2:
        return 0.0
    d = (j[:, None] - j[None]).norm(dim=-1).mean(-1)  # (N, N)
    return float(d.sum() / (N * (N - 1)))


def summarize(m: Mapping[str, np.ndarray], joints: Optional[Tensor] = None) -> dict[str, float]:
    """Means in report units: depth mm, volume cm³, ratios, accept rate, diversity mm."""
    out = {
        "penetration_depth_mm": float(np.mean(m["penetration_depth"]) * 1000.0),
        "penetration_depth_max_mm": float(np.max(m["penetration_depth"]) * 1000.0)
        if len(m["penetration_depth"])
        else 0.0,
        "intersection_cm3": float(np.mean(m["intersection"]) * 1e6),
        "contact_ratio": float(np.mean(m["contact_ratio"])),
        "contact_rate": float(np.mean(m["contact_right"] | m["contact_left"])),
        "accept_rate": float(np.mean(m["accept"])),
        "samples": int(len(m["accept"])),
    }
    if joints is not None:
        out["diversity_mm"] = diversity(joints) * 1000.0
    return out
