"""How near the held-out subject's hands come to the training hands, and to a pose bank's.

For every frame of the ``p1`` validation sequences and each hand: the mean distance of its 21
root-relative joints, posed with the mean hand shape (articulation only), to the nearest
training frame's hand, to the nearest pose-bank grasp's, and to the nearer of the two. Frames
are split into *held* (the object is being moved: its translation more than 1 mm from the
sequence's first frame) and *rest* (hands before and after the grasp, alike for every
subject). With a bank, also how far POM moved each grasp: the same distance from a bank grasp to
the annotated frame it was made from; and for every pool the share of held frames (a bank's:
of the frames its grasps were made from), since a bank of held frames alone teaches a model
nothing about hands at rest. Beside the nearest distances, what a pool teaches on average: its
*openness* (the mean distance of the five fingertips from the wrist) and the *offset* of its
mean hand from the held-out mean hand (the mean over the 21 joints of the distance between the
two joint-wise means); a pool of closed grasps shows as a smaller openness and a larger offset
than the training frames'. Reads annotations only.

Usage::

    python experiments/pose_coverage.py DATA [--bank BANK_DIR] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.models.pom.bank import load_pose_bank

SIDES = ("right", "left")
HELD_MM = 1.0
#: Joints 16..20 of the 21-joint MANO hand: the fingertips (thumb, index, middle, ring, pinky).
TIPS = slice(16, 21)


def articulated_joints(layer: torch.nn.Module, pose: np.ndarray) -> np.ndarray:
    """(F, 21, 3) root-relative joints (m) of (F, 45) MANO poses, mean shape, no global pose."""
    p = torch.as_tensor(pose, dtype=torch.float64)
    zeros = torch.zeros(len(p), 3, dtype=torch.float64)
    with torch.no_grad():
        j = layer(global_orient=zeros, hand_pose=p, betas=torch.zeros(len(p), 10, dtype=torch.float64), transl=zeros)
    joints = j.joints.numpy()
    return joints - joints[:, :1]


def held_frames(obj: np.ndarray) -> np.ndarray:
    """(F,) True where the object (F, 7) [θ, axis-angle, translation mm] has left its first frame's place."""
    return np.linalg.norm(obj[:, 4:7] - obj[:1, 4:7], axis=1) > HELD_MM


def nearest_distance(query: np.ndarray, pool: np.ndarray, chunk: int = 0) -> np.ndarray:
    """(Q,) mean joint distance (mm) from each hand of ``query`` (Q, J, 3) to its nearest in ``pool`` (N, J, 3).

    ``chunk`` query hands at a time; 0 picks as many as keep one step's differences near 64 MB.
    """
    chunk = chunk or max(1, (1 << 26) // max(1, pool[0].size * len(pool) * 8))
    out = []
    for i in range(0, len(query), chunk):
        d = np.linalg.norm(query[i : i + chunk, None] - pool[None], axis=-1).mean(-1)
        out.append(d.min(1))
    return np.concatenate(out) * 1000.0


def openness(joints: np.ndarray) -> float:
    """Mean distance (mm) of the fingertips from the wrist over (N, 21, 3) root-relative hands (m)."""
    return float(np.linalg.norm(joints[:, TIPS], axis=-1).mean() * 1000.0)


def mean_offset(pool: np.ndarray, query: np.ndarray) -> float:
    """Mean over joints of the distance (mm) between the joint-wise means of two sets of (N, 21, 3) hands (m)."""
    return float(np.linalg.norm(pool.mean(0) - query.mean(0), axis=-1).mean() * 1000.0)


def split_hands(root: ArcticRoot, split: str) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Articulated joints per side of every frame of a ``p1`` split, and which frames are held."""
    layers = root.mano_layers(torch.float64)
    joints: dict[str, list[np.ndarray]] = {s: [] for s in SIDES}
    held = []
    for key in root.protocol("p1")[split]:
        raw = root.raw_sequence(*key.split("/", 1))
        held.append(held_frames(raw.object))
        for s in SIDES:
            joints[s].append(articulated_joints(layers[s], raw.mano[s]["pose"]))
    return {s: np.concatenate(v) for s, v in joints.items()}, np.concatenate(held)


def source_held(root: ArcticRoot, sources: list[tuple[str, str, int]]) -> np.ndarray:
    """(N,) True where the frame ``sources[i]`` = (subject, sequence, frame) is held."""
    held = {key: held_frames(root.raw_sequence(*key).object) for key in dict.fromkeys(s[:2] for s in sources)}
    return np.array([bool(held[(sid, seq)][frame]) for sid, seq, frame in sources], dtype=bool)


def bank_moves(
    root: ArcticRoot, layers: dict, sources: list[tuple[str, str, int]], bank: dict[str, np.ndarray]
) -> dict:
    """Per side, the mean and median distance (mm) of each bank grasp (N, 21, 3) from the
    annotated hand of the frame ``sources[i]`` = (subject, sequence, frame) it was made from
    (``layers``: the root's float64 MANO layers per side)."""
    raws = {key: root.raw_sequence(*key) for key in dict.fromkeys((sid, seq) for sid, seq, _ in sources)}
    out = {}
    for s in SIDES:
        source = [raws[(sid, seq)].mano[s]["pose"][frame] for sid, seq, frame in sources]
        d = np.linalg.norm(bank[s] - articulated_joints(layers[s], np.stack(source)), axis=-1).mean(-1) * 1000.0
        out[s] = {"mean": float(d.mean()), "median": float(np.median(d))}
    return out


def coverage(data: Path, bank: Optional[Path] = None) -> dict:
    """Mean nearest distances (mm) per side, pool (train, bank, train+bank) and frame kind."""
    root = ArcticRoot(data)
    train, train_held = split_hands(root, "train")
    val, held = split_hands(root, "val")
    pools = {"train": train}
    rec: dict = {"val_frames": int(len(held)), "held_share": float(held.mean()), "pool_sizes": {}, "mm": {}}
    rec["pool_held_share"] = {"train": float(train_held.mean())}
    if bank is not None:
        poses = load_pose_bank(bank)
        layers = root.mano_layers(torch.float64)
        pools["bank"] = {s: articulated_joints(layers[s], poses.state.hands[s].pose.double().numpy()) for s in SIDES}
        pools["train+bank"] = {s: np.concatenate([train[s], pools["bank"][s]]) for s in SIDES}
        rec["bank_moved_mm"] = bank_moves(root, layers, poses.sources, pools["bank"])
        rec["pool_held_share"]["bank"] = float(source_held(root, poses.sources).mean())
    rec["shape"] = {
        f"{name}/{s}": {"openness": openness(pool[s]), "offset": mean_offset(pool[s], val[s])}
        for name, pool in {"val": val, **pools}.items()
        for s in SIDES
    }
    for name, pool in pools.items():
        rec["pool_sizes"][name] = int(len(pool["right"]))
        for s in SIDES:
            d = nearest_distance(val[s], pool[s])
            rec["mm"][f"{name}/{s}"] = {
                "held": float(d[held].mean()) if held.any() else None,
                "rest": float(d[~held].mean()) if (~held).any() else None,
                "all": float(d.mean()),
            }
    return rec


def markdown(rec: dict) -> str:
    """The table: one row per (pool, side), columns held / rest / all (mm)."""
    share = rec.get("pool_held_share", {})
    lines = [
        f"{rec['val_frames']} held-out frames, {rec['held_share']:.0%} held; pools: "
        + ", ".join(
            f"{k} {v}" + (f" ({share[k]:.0%} held)" if k in share else "") for k, v in rec["pool_sizes"].items()
        ),
        "",
        "| nearest of | hand | held (mm) | rest (mm) | all (mm) |",
        "|---|---|---|---|---|",
    ]
    for key, v in rec["mm"].items():
        pool, side = key.rsplit("/", 1)
        cells = " | ".join("—" if v[k] is None else f"{v[k]:.1f}" for k in ("held", "rest", "all"))
        lines.append(f"| {pool} | {side} | {cells} |")
    lines += ["", "| pool | hand | openness (mm) | mean hand's offset from val's (mm) |", "|---|---|---|---|"]
    for key, v in rec["shape"].items():
        pool, side = key.rsplit("/", 1)
        lines.append(f"| {pool} | {side} | {v['openness']:.1f} | {v['offset']:.1f} |")
    if "bank_moved_mm" in rec:
        moved = rec["bank_moved_mm"]
        lines += [
            "",
            "POM moved each grasp from its annotated frame by (mean / median, mm): "
            + ", ".join(f"{s} {moved[s]['mean']:.1f} / {moved[s]['median']:.1f}" for s in SIDES),
        ]
    return "\n".join(lines) + "\n"


def main(argv: Optional[list[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", help="an ARCTIC(-format) data root")
    ap.add_argument("--bank", help="a pose bank folder (hogsa train bank)")
    ap.add_argument("--json", help="write the figures here")
    args = ap.parse_args(argv)
    rec = coverage(Path(args.data), Path(args.bank) if args.bank else None)
    print(markdown(rec), end="")
    if args.json:
        Path(args.json).write_text(json.dumps(rec, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
