"""Eight views of two Gaussian hands holding a Gaussian textured object (visual check + timing).

Builds the synthetic hand pair (:func:`hogsa_world.hand.synthetic_hand_pair`) as Gaussian
parts in a grasp pose (:func:`hogsa_loader.assets.hands.anatomy.named_articulation`), a procedural
textured object (:func:`hogsa_world.objects.catalogue.make_object`), places the hands on opposite
sides of the object with their palms towards it, composes the scene and renders 8 views on a
ring around the vertical axis with the CPU Gaussian rasteriser. Writes a 2 x 4 PNG grid (a
third row of per-part masks with ``--masks``) and prints sizes and timings: the first
(cold) render and the median of ``--repeats`` further (warm) renders; ``--json OUT`` writes
them too.

Usage::

    python examples/eight_view_hands_object.py --out eight_views.png [--object box]
        [--variant games|avatars|free] [--k 2] [--hand-levels 1] [--object-levels 1]
        [--size 384] [--headlight 0.45] [--masks] [--repeats 3] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from hogsa_loader.assets.hands import ManoModelData, named_articulation
from hogsa_loader.assets.hands.anatomy import derive_joint_axes, rest_joints
from hogsa_loader.geometry.rotations import matrix_to_axis_angle
from hogsa_loader.models.gaussians import BindingConfig, HandGaussians, ObjectGaussians, compose, render_scene
from hogsa_loader.render.mesh_raster import camera_look_at, intrinsics_from_fov, save_png
from hogsa_world.hand import synthetic_hand_pair
from hogsa_world.objects.catalogue import make_object

BACKGROUND = (0.93, 0.93, 0.95)
PART_COLOURS = np.array([[0.85, 0.25, 0.2], [0.2, 0.45, 0.9], [0.95, 0.8, 0.2]])


def _frame(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Orthonormal frame with first axis a and second axis b made orthogonal to a."""
    a = a / np.linalg.norm(a)
    b = b - (b @ a) * a
    b = b / np.linalg.norm(b)
    return np.stack([a, b, np.cross(a, b)], 1)


def palm_placement(
    model: ManoModelData, palm_target: np.ndarray, palm_dir: np.ndarray, finger_dir: np.ndarray
) -> tuple[torch.Tensor, torch.Tensor]:
    """MANO global_orient and transl putting the palm surface at ``palm_target``.

    The palm's outward normal is turned to ``palm_dir`` and the wrist -> middle-MCP
    direction to ``finger_dir`` (made orthogonal). MANO rotates about the rest wrist joint.
    """
    J = rest_joints(model)
    n_palm = derive_joint_axes(model).palm_normal
    fingers = J[4] - J[0]
    centre = J[[0, 1, 4, 7, 10]].mean(0)
    v = model.v_template
    lateral = (v - centre) - ((v - centre) @ n_palm)[:, None] * n_palm
    near = np.linalg.norm(lateral, axis=1) < 0.02
    surface = centre + ((v[near] - centre) @ n_palm).max() * n_palm
    R = _frame(palm_dir, finger_dir) @ _frame(n_palm, fingers).T
    transl = palm_target - R @ (surface - J[0]) - J[0]
    rot = torch.tensor(R, dtype=torch.float64)
    return matrix_to_axis_angle(rot).float()[None], torch.tensor(transl, dtype=torch.float32)[None]


def ring_cameras(
    n: int, target: np.ndarray, dist: float, elevation_deg: float, size: int, fov_deg: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """(1, n, 4, 4) world->camera and (1, n, 3, 3) intrinsics on a ring around +y."""
    el = math.radians(elevation_deg)
    views = []
    for i in range(n):
        az = 2 * math.pi * i / n
        eye = target + dist * np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
        views.append(
            camera_look_at(
                torch.tensor(eye, dtype=torch.float32), torch.tensor(target, dtype=torch.float32), (0.0, 1.0, 0.0)
            )
        )
    K = intrinsics_from_fov(fov_deg, size, size)
    return torch.stack(views)[None], K.expand(1, n, 3, 3).contiguous()


def _label(img: np.ndarray, text: str) -> np.ndarray:
    out = np.ascontiguousarray((np.clip(img, 0, 1) * 255).astype(np.uint8))
    cv2.putText(out, text, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (40, 40, 40), 1, cv2.LINE_AA)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="output PNG")
    ap.add_argument("--object", default="box")
    ap.add_argument("--variant", default="games", choices=("games", "avatars", "free"))
    ap.add_argument("--k", type=int, default=2)
    ap.add_argument("--sh-degree", type=int, default=3)
    ap.add_argument("--hand-levels", type=int, default=1, help="MANO-HD subdivision levels")
    ap.add_argument("--object-levels", type=int, default=1, help="textured-mesh subdivision levels")
    ap.add_argument("--size", type=int, default=384)
    ap.add_argument("--angle", type=float, default=0.5, help="object articulation (rad)")
    ap.add_argument(
        "--headlight", type=float, default=0.45, help="ambient fraction of a camera light (negative: plain SH colours)"
    )
    ap.add_argument("--masks", action="store_true", help="add a row of per-part masks")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3, help="warm renders timed after the first (cold) one")
    ap.add_argument("--json", default=None, help="also write the figures to this JSON file")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    t0 = time.perf_counter()
    right, left = synthetic_hand_pair()
    template = make_object(args.object)
    t_assets = time.perf_counter() - t0

    t0 = time.perf_counter()
    common = dict(variant=args.variant, k=args.k, sh_degree=args.sh_degree)
    hand_binding = BindingConfig(subdivide_levels=args.hand_levels, **common)
    hands = [HandGaussians(m, hand_binding, flat_hand_mean=True) for m in (right, left)]
    obj = ObjectGaussians(template, BindingConfig(subdivide_levels=args.object_levels, **common))
    t_build = time.perf_counter() - t0

    # object: bottom part centred at the origin, lid opened by --angle
    bottom = template.verts[template.parts == 1]
    centre = 0.5 * (bottom.min(0) + bottom.max(0))
    obj_transl = torch.tensor(-centre, dtype=torch.float32)[None]
    half = 0.5 * (bottom.max(0) - bottom.min(0))
    gap = 0.002

    t0 = time.perf_counter()
    with torch.no_grad():
        parts = [obj(torch.tensor([args.angle]), torch.zeros(1, 3), obj_transl)]
        x_front = -half[0]
        for hand, model, side in zip(hands, (right, left), (1.0, -1.0)):
            # palm on the +z (right) / -z (left) face, fingers past the front edge (-x)
            target = np.array([x_front + 0.036, -0.012 * side, side * (half[2] + gap)])
            go, tr = palm_placement(model, target, np.array([0.0, 0.0, -side]), np.array([-1.0, 0.0, 0.0]))
            art = torch.tensor(named_articulation(model, "grasp"), dtype=torch.float32)[None]
            parts.append(hand(go, art, None, tr))
        scene = compose(parts)
    t_pose = time.perf_counter() - t0

    view_target = np.array([0.0, 0.0, 0.0])
    viewmats, Ks = ring_cameras(8, view_target, 0.5, 20.0, args.size, 36.0)
    bg = torch.tensor(BACKGROUND)[None, None].expand(1, 8, 3)
    times = []
    for _ in range(1 + max(0, args.repeats)):
        t0 = time.perf_counter()
        with torch.no_grad():
            out = render_scene(
                scene,
                viewmats,
                Ks,
                args.size,
                args.size,
                num_parts=3,
                backgrounds=bg,
                headlight=None if args.headlight < 0 else args.headlight,
            )
        times.append(time.perf_counter() - t0)
    t_render = times[0]
    t_warm = statistics.median(times[1:]) if len(times) > 1 else None

    rgb = out.rgb[0].numpy()
    cells = [_label(rgb[i], f"view {i} ({45 * i} deg)") for i in range(8)]
    rows = [np.concatenate(cells[:4], 1), np.concatenate(cells[4:], 1)]
    if args.masks:
        pa = out.part_alpha[0].numpy()  # (8, H, W, 3)
        masks = pa @ PART_COLOURS + (1 - pa.sum(-1, keepdims=True)) * np.array(BACKGROUND)
        rows.append(np.concatenate([_label(masks[i], f"parts {i}") for i in range(4)], 1))
    grid = np.concatenate(rows, 0)
    save_png(args.out, torch.from_numpy(grid))
    n = [p.num_gaussians for p in parts]
    print(f"gaussians: object {n[0]}, right {n[1]}, left {n[2]}, total {sum(n)}")
    print(f"object {args.object}: binding {obj.binding_mesh}; hands: {hands[0].binding_mesh}")
    warm = f", warm {t_warm:.2f}s (median of {len(times) - 1})" if t_warm is not None else ""
    print(
        f"assets {t_assets:.2f}s  build {t_build:.2f}s  pose+compose {t_pose:.3f}s  "
        f"render 8x{args.size}^2 cold {t_render:.2f}s{warm}"
    )
    if args.json:
        fig = {
            "benchmark": "eight_view_hands_object",
            "device": f"cpu ({platform.processor() or platform.machine()})",
            "torch": torch.__version__,
            "threads": args.threads,
            "size": args.size,
            "views": 8,
            "object": args.object,
            "variant": args.variant,
            "k": args.k,
            "num_gaussians": dict(zip(("object", "right", "left"), n)),
            "seconds": {
                "assets": t_assets,
                "build": t_build,
                "pose_compose": t_pose,
                "render_cold": t_render,
                "render_warm_median": t_warm,
                "render_all": times,
            },
        }
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(fig, indent=1, allow_nan=False) + "\n")
    print(f"wrote {args.out} ({grid.shape[1]}x{grid.shape[0]})")


if __name__ == "__main__":
    main()
