"""Figures for POM: a small exact t-SNE (numpy, no scikit-learn) and grasp renders.

:func:`tsne` is the standard exact t-SNE (van der Maaten & Hinton 2008): PCA to at most 30
dimensions, Gaussian affinities with a per-point bandwidth found by bisection to the
target perplexity, symmetrised; Student-t low-dimensional affinities; gradient descent with
momentum, early exaggeration (×12 for the first 100 steps) and per-parameter gains. O(N²)
memory and time — meant for a few hundred points.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import cv2
import numpy as np
import torch

from hogsa_loader.assets.objects.articulated import articulate
from hogsa_loader.models.pom.hands import SIDES, HandInfo
from hogsa_loader.models.pom.objects import ObjectSet
from hogsa_loader.models.pom.state import GraspState, hand_forward
from hogsa_loader.render.mesh_raster import Light, MeshPart, camera_look_at, intrinsics_from_fov, render_meshes

__all__ = ["tsne", "render_grasps"]


def _affinities(X: np.ndarray, perplexity: float) -> np.ndarray:
    n = X.shape[0]
    D = np.square(X[:, None] - X[None]).sum(-1)
    P = np.zeros((n, n))
    target = np.log(perplexity)
    for i in range(n):
        d = np.delete(D[i], i)
        lo, hi, beta = 0.0, np.inf, 1.0
        for _ in range(60):
            p = np.exp(-(d - d.min()) * beta)
            s = p.sum()
            H = np.log(s) + beta * (d - d.min()) @ p / s
            if abs(H - target) < 1e-5:
                break
            if H > target:
                lo = beta
                beta = beta * 2 if hi == np.inf else (beta + hi) / 2
            else:
                hi = beta
                beta = (beta + lo) / 2
        P[i, np.arange(n) != i] = p / s
    P = (P + P.T) / (2 * n)
    return np.maximum(P, 1e-12)


def tsne(X: np.ndarray, perplexity: float = 30.0, iters: int = 750, seed: int = 0) -> np.ndarray:
    """2-D t-SNE embedding.

    Args:
        X: (N, D) data; perplexity: clipped to (N - 1) / 3; iters: gradient steps.

    Returns:
        (N, 2) embedding.
    """
    X = np.asarray(X, dtype=np.float64)
    n = X.shape[0]
    X = X - X.mean(0)
    X = X / max(X.std(), 1e-12)
    if X.shape[1] > 30:  # PCA
        U, S, _ = np.linalg.svd(X, full_matrices=False)
        X = U[:, :30] * S[:30]
    P = _affinities(X, min(perplexity, max(2.0, (n - 1) / 3.0)))
    rng = np.random.default_rng(seed)
    Y = rng.normal(scale=1e-4, size=(n, 2))
    vel = np.zeros_like(Y)
    gains = np.ones_like(Y)
    for it in range(iters):
        exag = 12.0 if it < 100 else 1.0
        mom = 0.5 if it < 250 else 0.8
        d2 = np.square(Y[:, None] - Y[None]).sum(-1)
        num = 1.0 / (1.0 + d2)
        np.fill_diagonal(num, 0.0)
        Q = np.maximum(num / num.sum(), 1e-12)
        W = (exag * P - Q) * num
        grad = 4.0 * (np.diag(W.sum(1)) - W) @ Y
        gains = np.where(np.sign(grad) != np.sign(vel), gains + 0.2, gains * 0.8).clip(0.01)
        vel = mom * vel - 200.0 * gains * grad
        Y = Y + vel
        Y = Y - Y.mean(0)
    return Y


def render_grasps(
    states: Sequence[GraspState],
    labels: Sequence[str],
    infos: Mapping[str, HandInfo],
    objects: ObjectSet,
    size: int = 240,
    max_cols: int = 6,
) -> np.ndarray:
    """Sheet of grasps: one row per state (e.g. original / perturbed / optimised), one column
    per sample; each cell is the object and both hands seen from a fixed offset of the object.

    Returns:
        (rows · size, cols · size, 3) float image in [0, 1].
    """

    cols = min(max_cols, states[0].batch)
    colors = {"right": (0.86, 0.62, 0.50), "left": (0.55, 0.66, 0.86)}
    rows = []
    for st, lab in zip(states, labels):
        cells = []
        with torch.no_grad():
            verts = {s: hand_forward(infos[s], st.hands[s].map(lambda t: t[:cols].float())).vertices for s in SIDES}
        for b in range(cols):
            tpl = objects.templates[st.obj_names[b]]
            ov = articulate(
                torch.as_tensor(tpl.verts)[None],
                torch.as_tensor(tpl.parts == 0),
                st.obj_arti[b : b + 1].float(),
                st.obj_rot[b : b + 1].float(),
                st.obj_trans[b : b + 1].float(),
            )[0]
            parts = [MeshPart(ov, torch.as_tensor(tpl.faces), 1, vertex_colors=torch.full_like(ov, 0.72))]
            for k, s in enumerate(SIDES):
                v = verts[s][b]
                parts.append(
                    MeshPart(
                        v,
                        infos[s].layer.faces.cpu(),
                        2 + k,
                        vertex_colors=torch.tensor(colors[s]).expand_as(v).contiguous(),
                    )
                )
            allv = torch.cat([p.verts for p in parts])
            center = allv.mean(0)
            ext = float((allv.max(0).values - allv.min(0).values).norm())
            eye = center + ext * 1.25 * torch.tensor([0.45, -0.75, -0.5]) / torch.tensor([0.45, -0.75, -0.5]).norm()
            w2c = camera_look_at(eye, center, torch.tensor([0.0, -1.0, 0.0]))
            img = render_meshes(
                parts,
                w2c,
                intrinsics_from_fov(40.0, size, size),
                size,
                size,
                light=Light(direction=(0.3, 0.5, 1.0)),
                background=(0.95, 0.95, 0.97),
            ).rgb.numpy()
            img = np.ascontiguousarray((img * 255).astype(np.uint8))
            cv2.putText(
                img, f"{lab} {st.obj_names[b]}", (5, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (20, 20, 20), 1, cv2.LINE_AA
            )
            cells.append(img.astype(np.float32) / 255.0)
        rows.append(np.concatenate(cells, 1))
    return np.concatenate(rows, 0)
