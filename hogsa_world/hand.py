"""A procedural hand in the exact MANO schema: the project's embedded default hand model.

Real MANO cannot be shipped or downloaded, so the project builds its own right hand and its
mirrored left hand with everything a MANO file holds (same keys, 16-joint kinematic tree
identical to MANO's, sparse ``J_regressor``, 10 shape directions, 135 pose correctives,
``hands_components``/``hands_mean``/``hands_coeffs``) plus project metadata (fingertips,
prior-contact vertices, per-vertex skin albedo).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.optimize
import scipy.sparse as sp
import trimesh

from hogsa_loader.assets.hands.anatomy import (
    FINGER_JOINTS,
    articulation_from_angles,
    derive_contact_prior,
    derive_joint_axes,
    unit_rows,
)
from hogsa_loader.assets.hands.mano_io import MANO_RELEASE_TIP_IDS, ManoModelData, reorder_vertices, validate_model
from hogsa_loader.extras import require
from hogsa_loader.geometry.meshes import vertex_normals_np

__all__ = ["HandSpec", "build_synthetic_hand", "mirror_to_left", "synthetic_hand_pair"]

GENERATOR_VERSION = "hogsa-synthetic-hand/2"
_FINGER_ORDER = ("index", "middle", "pinky", "ring")  # MANO joint order of the 4 fingers


@dataclass(frozen=True)
class HandSpec:
    """Proportions of the synthetic right hand (metres)."""

    voxel: float = 0.0046
    wrist: tuple[float, float, float] = (0.088, -0.003, 0.0)
    #: per finger: MCP position, direction, 3 segment lengths, 4 radii (MCP, PIP, DIP, tip)
    mcp: tuple[tuple[float, float, float], ...] = (
        (0.000, 0.000, 0.0250),
        (-0.004, 0.001, 0.0040),
        (0.013, -0.003, -0.0350),
        (0.003, 0.000, -0.0165),
    )
    direction: tuple[tuple[float, float, float], ...] = (
        (-1.0, 0.0, 0.15),
        (-1.0, 0.0, 0.02),
        (-1.0, 0.0, -0.25),
        (-1.0, 0.0, -0.11),
    )
    lengths: tuple[tuple[float, float, float], ...] = (
        (0.039, 0.023, 0.022),
        (0.044, 0.027, 0.023),
        (0.032, 0.019, 0.020),
        (0.041, 0.026, 0.022),
    )
    radii: tuple[tuple[float, float, float, float], ...] = (
        (0.0098, 0.0089, 0.0080, 0.0072),
        (0.0100, 0.0091, 0.0082, 0.0074),
        (0.0085, 0.0078, 0.0070, 0.0064),
        (0.0094, 0.0086, 0.0077, 0.0070),
    )
    thumb_cmc: tuple[float, float, float] = (0.066, -0.011, 0.019)
    thumb_dirs: tuple[tuple[float, float, float], ...] = (
        (-0.62, -0.30, 0.72),
        (-0.80, -0.28, 0.53),
        (-0.90, -0.25, 0.36),
    )
    thumb_lengths: tuple[float, float, float] = (0.038, 0.031, 0.026)
    thumb_radii: tuple[float, float, float, float] = (0.0125, 0.0112, 0.0101, 0.0088)
    skin_rgb: tuple[float, float, float] = (0.80, 0.60, 0.50)


# ----------------------------------------------------------------------------------------
# 1. skeleton
# ----------------------------------------------------------------------------------------
@dataclass
class _Skeleton:
    joints: np.ndarray  # (16, 3) MANO order
    tips: dict  # finger -> (3,) tip point
    chains: dict  # finger -> (4, 3) polyline base..tip
    radii: dict  # finger -> (4,) radius at each polyline node


def _build_skeleton(spec: HandSpec) -> _Skeleton:
    joints = np.zeros((16, 3))
    joints[0] = spec.wrist
    chains, radii, tips = {}, {}, {}
    for k, name in enumerate(_FINGER_ORDER):
        j1, j2, j3 = FINGER_JOINTS[name]
        d = unit_rows(np.asarray(spec.direction[k], float))
        p = [np.asarray(spec.mcp[k], float)]
        for L in spec.lengths[k]:
            p.append(p[-1] + L * d)
        joints[[j1, j2, j3]] = p[:3]
        chains[name] = np.stack(p)
        radii[name] = np.asarray(spec.radii[k])
        tips[name] = p[3]
    p = [np.asarray(spec.thumb_cmc, float)]
    for L, d in zip(spec.thumb_lengths, spec.thumb_dirs):
        p.append(p[-1] + L * unit_rows(np.asarray(d, float)))
    joints[[13, 14, 15]] = p[:3]
    chains["thumb"] = np.stack(p)
    radii["thumb"] = np.asarray(spec.thumb_radii)
    tips["thumb"] = p[3]
    return _Skeleton(joints, tips, chains, radii)


# ----------------------------------------------------------------------------------------
# 2. surface
# ----------------------------------------------------------------------------------------
def _smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum (blend radius k)."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b * (1 - h) + a * h - k * h * (1 - h)


def _tube_sdf(
    p: np.ndarray, chain: np.ndarray, radii: np.ndarray, flatten: float = 0.86
) -> tuple[np.ndarray, np.ndarray]:
    """Approximate SDF of a tapered tube along a polyline with an elliptic section.

    Returns (sdf (N,), arc parameter s (N,) of the closest axis point, metres from chain[0]).
    """
    best = np.full(p.shape[0], np.inf)
    best_s = np.zeros(p.shape[0])
    s0 = 0.0
    for a, b, ra, rb in zip(chain[:-1], chain[1:], radii[:-1], radii[1:]):
        ab = b - a
        L = np.linalg.norm(ab)
        t = np.clip((p - a) @ ab / (L * L), 0.0, 1.0)
        off = p - (a + t[:, None] * ab)
        off[:, 1] /= flatten  # flatter dorso-palmar section
        d = np.linalg.norm(off, axis=1) - (ra + (rb - ra) * t)
        take = d < best
        best = np.where(take, d, best)
        best_s = np.where(take, s0 + t * L, best_s)
        s0 += L
    return best, best_s


def _round_box_sdf(p: np.ndarray, center: np.ndarray, half: np.ndarray, r: float) -> np.ndarray:
    q = np.abs(p - center) - half
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(1), 0.0) - r


def _capsule_sdf(p: np.ndarray, a, b, ra: float, rb: float, scale=(1.0, 1.0, 1.0)) -> np.ndarray:
    a, b = np.asarray(a, float), np.asarray(b, float)
    ab = b - a
    t = np.clip((p - a) @ ab / (ab @ ab), 0.0, 1.0)
    off = (p - (a + t[:, None] * ab)) / np.asarray(scale)
    return np.linalg.norm(off, axis=1) - (ra + (rb - ra) * t)


def _palm_sdf(p: np.ndarray, sk: _Skeleton) -> np.ndarray:
    J = sk.joints
    x = p[:, 0]
    # palm slab, narrowing toward the wrist
    taper = np.clip((x - 0.012) / 0.07, 0.0, 1.0)
    half = np.stack([np.full_like(x, 0.034), np.full_like(x, 0.0062), 0.029 - 0.007 * taper], axis=1)
    q = np.abs(p - np.array([0.046, -0.003, -0.004])) - half
    slab = np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(1), 0.0) - 0.0065
    knuckles = J[[1, 4, 10, 7]]
    d = slab
    for a, b in zip(knuckles[:-1], knuckles[1:]):
        d = _smin(d, _capsule_sdf(p, a, b, 0.0095, 0.0090, (1.0, 0.9, 1.0)), 0.004)
    # hypothenar pad and forearm stub
    d = _smin(d, _capsule_sdf(p, (0.070, -0.007, -0.024), (0.020, -0.009, -0.031), 0.0105, 0.0095, (1, 0.9, 1)), 0.006)
    d = _smin(d, _capsule_sdf(p, (0.060, -0.003, 0.0), (0.16, -0.003, 0.0), 0.0195, 0.0215, (1.0, 0.66, 1.0)), 0.012)
    return d


def _thumb_sdf(p: np.ndarray, sk: _Skeleton) -> tuple[np.ndarray, np.ndarray]:
    d, s = _tube_sdf(p, sk.chains["thumb"], sk.radii["thumb"], flatten=0.9)
    # thenar eminence: a fleshy pad from the wrist to the thumb MCP
    pad = _capsule_sdf(
        p, (0.075, -0.010, 0.008), sk.joints[14] + np.array([0.004, -0.002, -0.004]), 0.0125, 0.0100, (1.0, 0.85, 1.0)
    )
    return _smin(d, pad, 0.006), s


def _field(p: np.ndarray, sk: _Skeleton) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hand SDF plus, per point, the owning primitive (0 palm, 1..5 fingers) and arc param."""
    names = ("palm",) + _FINGER_ORDER + ("thumb",)
    parts = [_palm_sdf(p, sk)]
    params = [np.zeros(p.shape[0])]
    for name in _FINGER_ORDER:
        d, s = _tube_sdf(p, sk.chains[name], sk.radii[name])
        parts.append(d)
        params.append(s)
    d, s = _thumb_sdf(p, sk)
    parts.append(d)
    params.append(s)
    stack = np.stack(parts)
    owner = stack.argmin(0)
    # fingers blend into the palm (webs, knuckles) but never into each other
    sdf = stack[0]
    for k in range(1, len(names)):
        sdf = _smin(sdf, stack[k], 0.0055) if k == len(names) - 1 else sdf
    fingers = stack[1 : len(names) - 1].min(0)
    sdf = _smin(sdf, fingers, 0.0055)
    arc = np.stack(params)[owner, np.arange(p.shape[0])]
    return sdf, owner, arc


def _mesh_surface(sk: _Skeleton, voxel: float, wrist_cut: float) -> tuple[np.ndarray, np.ndarray]:
    pts = np.concatenate([c for c in sk.chains.values()] + [sk.joints])
    lo = pts.min(0) - 0.03
    hi = pts.max(0) + 0.03
    hi[0] = wrist_cut  # open wrist: the forearm stub leaves the grid here
    n = np.ceil((hi - lo) / voxel).astype(int) + 1
    axes = [lo[i] + voxel * np.arange(n[i]) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    sdf = np.concatenate([_field(c, sk)[0] for c in np.array_split(grid, 16)])
    vol = sdf.reshape(n)
    measure = require("skimage.measure", "demo", "the synthetic MANO-format hand")
    verts, faces, _, _ = measure.marching_cubes(vol, level=0.0, spacing=(voxel,) * 3, method="lewiner")
    verts = verts + lo
    mesh = trimesh.Trimesh(verts, faces, process=True)
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    # keep the largest connected piece
    comps = mesh.split(only_watertight=False)
    mesh = max(comps, key=lambda m: len(m.faces))
    trimesh.smoothing.filter_taubin(mesh, lamb=0.5, nu=-0.53, iterations=12)
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces, dtype=np.int64)
    # outward orientation: normals point away from the local skeleton
    c = v[f].mean(1)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    sdf_out = _field(c + 1e-3 * unit_rows(fn), sk)[0]
    sdf_in = _field(c - 1e-3 * unit_rows(fn), sk)[0]
    if np.mean(sdf_out > sdf_in) < 0.5:
        f = f[:, [0, 2, 1]]
    return v, f


# ----------------------------------------------------------------------------------------
# 3. skinning
# ----------------------------------------------------------------------------------------
def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def _adjacency(faces: np.ndarray, V: int) -> sp.csr_matrix:
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    A = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(V, V)).tocsr()
    A = ((A + A.T) > 0).astype(np.float64)
    deg = np.asarray(A.sum(1)).ravel()
    return sp.diags(1.0 / np.maximum(deg, 1)) @ A


def _skin_weights(v: np.ndarray, f: np.ndarray, sk: _Skeleton) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(V, 16) smooth skinning weights, plus owner (V,) and arc parameter (V,)."""
    _, owner, arc = _field(v, sk)
    V = v.shape[0]
    W = np.zeros((V, 16))
    W[owner == 0, 0] = 1.0
    names = _FINGER_ORDER + ("thumb",)
    for k, name in enumerate(names, start=1):
        sel = owner == k
        j1, j2, j3 = FINGER_JOINTS[name]
        L = np.linalg.norm(np.diff(sk.chains[name], axis=0), axis=1)
        bounds = np.array([0.0, L[0], L[0] + L[1]])
        width = 0.35 * sk.radii[name][:3] + 0.002
        s = arc[sel]
        # cumulative "past joint i" indicators, blended around each joint
        past = [_smoothstep((s - bounds[i] + width[i]) / (2 * width[i])) for i in range(3)]
        w = np.stack([1 - past[0], past[0] - past[1], past[1] - past[2], past[2]], 1)
        W[np.ix_(sel, [0, j1, j2, j3])] = np.clip(w, 0.0, 1.0)
    P = _adjacency(f, V)
    for _ in range(6):
        W = 0.5 * W + 0.5 * (P @ W)
    W /= W.sum(1, keepdims=True)
    return W, owner, arc


# ----------------------------------------------------------------------------------------
# 4. joint regressor
# ----------------------------------------------------------------------------------------
def _joint_regressor(v: np.ndarray, joints: np.ndarray, k: int = 80, lam: float = 0.01) -> sp.csc_matrix:
    """Sparse (16, V) convex weights: ``J_regressor @ v ~= joints`` (regularised NNLS)."""
    rows, cols, vals = [], [], []
    for j, target in enumerate(joints):
        idx = np.argsort(np.linalg.norm(v - target, axis=1))[:k]
        P = v[idx].T  # (3, k)
        u = np.full(k, 1.0 / k)
        big = 10.0
        A = np.vstack([P * 100.0, big * np.ones((1, k)), np.sqrt(lam) * np.eye(k)])
        b = np.concatenate([target * 100.0, [big], np.sqrt(lam) * u])
        w, _ = scipy.optimize.nnls(A, b, maxiter=2000)
        w /= w.sum()
        keep = w > 1e-4
        w = w[keep] / w[keep].sum()
        rows += [j] * int(keep.sum())
        cols += idx[keep].tolist()
        vals += w.tolist()
    return sp.csc_matrix((vals, (rows, cols)), shape=(16, v.shape[0]))


# ----------------------------------------------------------------------------------------
# 5. blend shapes
# ----------------------------------------------------------------------------------------
def _shape_dirs(v: np.ndarray, W: np.ndarray, owner: np.ndarray, arc: np.ndarray, sk: _Skeleton) -> np.ndarray:
    """(V, 3, 10) smooth shape directions, one standard deviation each."""
    V = v.shape[0]
    J = sk.joints
    wrist = J[0]
    w_palm = W[:, 0:1]
    names = ("palm",) + _FINGER_ORDER + ("thumb",)
    # per-vertex finger frame (palm vertices borrow the nearest finger by z)
    base = np.zeros((V, 3))
    direc = np.zeros((V, 3))
    axis_pt = np.zeros((V, 3))
    fing_sign = np.zeros(V)
    sign_map = {"index": 1.0, "middle": 0.5, "ring": -0.5, "pinky": -1.0, "thumb": 0.0}
    mcp_z = np.array([sk.chains[n][0, 2] for n in _FINGER_ORDER])
    for i in range(V):
        o = owner[i]
        name = names[o] if o > 0 else _FINGER_ORDER[int(np.argmin(np.abs(mcp_z - v[i, 2])))]
        ch = sk.chains[name]
        seg = np.diff(ch, axis=0)
        cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(seg, axis=1))])
        s = arc[i] if o > 0 else 0.0
        k = int(np.clip(np.searchsorted(cum, s) - 1, 0, 2))
        t = (s - cum[k]) / max(cum[k + 1] - cum[k], 1e-9)
        axis_pt[i] = ch[k] + t * seg[k]
        base[i] = ch[0]
        direc[i] = unit_rows(seg[k])
        fing_sign[i] = sign_map[name]
    s = np.where(owner > 0, arc, 0.0)[:, None]
    center = np.array([0.046, -0.003, -0.004])
    ex, ey, ez = np.eye(3)

    def blend(palm_field: np.ndarray, finger_field: np.ndarray) -> np.ndarray:
        return w_palm * palm_field + (1 - w_palm) * finger_field

    dirs = []
    dirs.append(0.06 * (v - wrist))  # 0 overall size
    dirs.append(blend(np.zeros((V, 3)), 0.09 * s * direc))  # 1 finger length
    palm_w = 0.07 * ((v - center) * ez)
    dirs.append(blend(palm_w, 0.07 * ((base - center) * ez)))  # 2 palm width
    radial = v - axis_pt
    dirs.append(blend(np.zeros((V, 3)), 0.12 * radial))  # 3 finger thickness
    palm_len = 0.07 * np.minimum(v[:, :1] - wrist[0], 0.0) * ex
    dirs.append(blend(palm_len, 0.07 * np.minimum(base[:, :1] - wrist[0], 0.0) * ex))  # 4 palm length
    dirs.append(blend(0.10 * (v - center) * ey, np.zeros((V, 3))))  # 5 palm thickness
    thumb = (owner == len(names) - 1)[:, None]
    dirs.append(blend(np.zeros((V, 3)), thumb * 0.10 * s * direc))  # 6 thumb length
    dirs.append(blend(np.zeros((V, 3)), 0.06 * fing_sign[:, None] * s * direc))  # 7 index vs pinky length
    dirs.append(blend(-0.05 * (v - center) * ez, 0.10 * radial))  # 8 slender vs stocky
    fore = np.clip((v[:, 0] - wrist[0]) / 0.02, 0.0, 1.0)[:, None]
    dirs.append(0.10 * fore * ((v - wrist) * (ey + ez)))  # 9 wrist thickness
    return np.stack(dirs, axis=2)


def _pose_dirs(v: np.ndarray, f: np.ndarray, joints: np.ndarray, W: np.ndarray, axes) -> np.ndarray:
    """(V, 3, 135) knuckle correctives driven by the flexion part of each joint rotation.

    For joint j with flexion axis a, ``1 - cos(phi) = -0.5 * sum_{ab} (R - I)_{ab} (I - a a^T)_{ab}``;
    the dorsal skin near the joint bulges and the palmar skin creases by that amount.
    """
    n = vertex_normals_np(v, f)
    P = np.zeros((v.shape[0], 3, 135))
    for j in range(1, 16):
        a = axes.flex[j - 1]
        coef = -0.5 * (np.eye(3) - np.outer(a, a)).reshape(9)  # feature weights -> 1 - cos
        d2 = ((v - joints[j]) ** 2).sum(1)
        fall = np.exp(-d2 / (2 * 0.007**2))
        side = n @ np.cross(a, axes.twist[j - 1])  # >0 on the side the bone bends away from
        bulge = 0.0035 * fall * np.where(side < 0, 1.0, -0.4) * np.abs(side)
        P[:, :, 9 * (j - 1) : 9 * j] = (bulge[:, None] * n)[:, :, None] * coef[None, None, :]
    return P


# ----------------------------------------------------------------------------------------
# 6. pose space
# ----------------------------------------------------------------------------------------
def _pose_space(model: ManoModelData, n: int = 1554, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sample articulations, return (hands_mean (45,), components (45, 45), coeffs (n, 45))."""
    rng = np.random.default_rng(seed)
    axes = derive_joint_axes(model)
    base = rng.beta(2.0, 2.2, size=(n, 1))  # overall grasp closure
    per = np.clip(base + 0.18 * rng.standard_normal((n, 5)), -0.1, 1.05)  # thumb, index, middle, ring, pinky
    flex = np.zeros((n, 15))
    abd = np.zeros((n, 15))
    order = ("thumb", "index", "middle", "ring", "pinky")
    for k, name in enumerate(order):
        j1, j2, j3 = FINGER_JOINTS[name]
        c = per[:, k]
        if name == "thumb":
            flex[:, [j1 - 1, j2 - 1, j3 - 1]] = np.stack([0.55 * c, 0.6 * c, 0.8 * c], 1)
            abd[:, j1 - 1] = 0.2 + 0.35 * rng.standard_normal(n) * 0.6 + 0.3 * c
        else:
            flex[:, [j1 - 1, j2 - 1, j3 - 1]] = np.stack([1.35 * c, 1.55 * c, 0.95 * c], 1)
            spread_dir = {"index": 1.0, "middle": 0.15, "ring": -0.5, "pinky": -1.0}[name]
            abd[:, j1 - 1] = (1 - c) * spread_dir * 0.18 * rng.uniform(0, 1.2, n)
    flex += 0.06 * rng.standard_normal(flex.shape)
    abd += 0.03 * rng.standard_normal(abd.shape)
    poses = articulation_from_angles(axes, flex, abd)
    poses += 0.02 * rng.standard_normal(poses.shape)  # small twists: full-rank pose space
    mean = poses.mean(0)
    _, _, vt = np.linalg.svd(poses - mean, full_matrices=False)
    comps = vt  # rows = components, decreasing variance
    coeffs = (poses - mean) @ comps.T
    return mean, comps, coeffs


# ----------------------------------------------------------------------------------------
# colours and assembly
# ----------------------------------------------------------------------------------------
def _albedo(v: np.ndarray, f: np.ndarray, W: np.ndarray, sk: _Skeleton, skin: np.ndarray, axes) -> np.ndarray:
    n = vertex_normals_np(v, f)
    palmar = np.clip(n @ axes.palm_normal, 0.0, 1.0)
    col = np.tile(skin, (v.shape[0], 1))
    col = col * (1.0 + 0.10 * palmar[:, None])  # lighter palm
    col[:, 0] *= 1.0 + 0.05 * palmar  # and a little redder
    # knuckle creases: slightly darker around finger joints
    for j in range(1, 16):
        d = np.linalg.norm(v - sk.joints[j], axis=1)
        col *= 1.0 - 0.06 * np.exp(-((d / 0.006) ** 2))[:, None]
    # nails: dorsal side near each fingertip
    for tip in sk.tips.values():
        d = np.linalg.norm(v - tip, axis=1)
        dorsal = n @ (-axes.palm_normal)
        nail = (d < 0.012) & (dorsal > 0.55)
        col[nail] = 0.55 * col[nail] + 0.45 * np.array([0.93, 0.80, 0.78])
    return np.clip(col, 0.0, 1.0)


def _tips(v: np.ndarray, owner: np.ndarray, sk: _Skeleton) -> np.ndarray:
    names = ("palm",) + _FINGER_ORDER + ("thumb",)
    out = []
    for name in ("thumb", "index", "middle", "ring", "pinky"):
        k = names.index(name)
        ch = sk.chains[name]
        d = unit_rows(ch[3] - ch[2])
        cand = np.flatnonzero(owner == k)
        out.append(int(cand[np.argmax(v[cand] @ d)]))
    return np.asarray(out, dtype=np.int64)


def build_synthetic_hand(spec: HandSpec = HandSpec(), seed: int = 0) -> ManoModelData:
    """Build the synthetic right hand in the MANO schema (deterministic for a spec and seed).

    How it is made (right hand, metres; fingers along -x, back of the hand +y, thumb on +z as in
    the MANO right template):
    1. Skeleton: wrist, four fingers with MCP/PIP/DIP + tip, thumb CMC/MCP/IP + tip.
    2. Surface: the zero level set of a signed-distance field (palm slab, knuckle bar, thenar and
       hypothenar pads, forearm stub, tapered finger tubes with flattened cross-sections) joined
       with smooth minimum, meshed by marching cubes (open at the wrist cut like MANO), Taubin
       smoothed.
    3. Skinning: each vertex is owned by the finger or palm primitive nearest to it; along its
       finger it blends between consecutive joints with a smoothstep around each joint, then the
       weight field is diffused over the mesh.
    4. Joint regressor: per joint, non-negative convex weights on nearby vertices that reproduce
       the skeleton joint (regularised NNLS), stored sparse.
    5. Blend shapes: 10 smooth displacement fields (size, finger length, palm width, thickness,
       ...); pose correctives: knuckle bulges driven by (1 - cos) of flexion.
    6. Pose space: 1554 sampled articulations (curl/spread/opposition families) -> PCA.
    7. Vertex order: the five fingertip vertices are renumbered to MANO's fingertip ids
       (744, 320, 443, 554, 671), which smplx and ARCTIC append as joints 16..20 by id.
    """
    sk = _build_skeleton(spec)
    v, f = _mesh_surface(sk, spec.voxel, wrist_cut=sk.joints[0, 0] + 0.017)
    W, owner, arc = _skin_weights(v, f, sk)
    Jreg = _joint_regressor(v, sk.joints)
    joints = Jreg @ v
    shapedirs = _shape_dirs(v, W, owner, arc, sk)
    parents = np.array([-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 0, 10, 11, 0, 13, 14], dtype=np.int64)
    zeros45 = np.zeros(45)
    draft = ManoModelData(
        v_template=v,
        shapedirs=shapedirs,
        posedirs=np.zeros((v.shape[0], 3, 135)),
        J_regressor=Jreg.toarray(),
        weights=W,
        parents=parents,
        faces=f,
        hands_components=np.eye(45),
        hands_mean=zeros45,
        hands_coeffs=None,
        side="right",
        tip_vertex_ids=_tips(v, owner, sk),
        meta={},
    )
    axes = derive_joint_axes(draft)
    posedirs = _pose_dirs(v, f, joints, W, axes)
    draft = draft.replace(posedirs=posedirs)
    mean, comps, coeffs = _pose_space(draft, seed=seed)
    model = draft.replace(
        hands_mean=mean,
        hands_components=comps,
        hands_coeffs=coeffs,
        vertex_colors=_albedo(v, f, W, sk, np.asarray(spec.skin_rgb), axes),
        meta={
            "generator": GENERATOR_VERSION,
            "units": "m",
            "seed": seed,
            "left_shapedirs_x_unmirrored": False,
            "note": "procedural hand in the MANO schema; not the MANO model",
        },
    )
    model = model.replace(contact_vertex_ids=derive_contact_prior(model))
    model = _tips_at_mano_ids(model)
    validate_model(model)
    return model


def _tip_order(tips: np.ndarray, targets: np.ndarray, num_verts: int) -> np.ndarray:
    """A vertex order (see :func:`reorder_vertices`) moving vertex ``tips[k]`` to id ``targets[k]``.

    The other vertices keep their relative order in the remaining ids.

    Args:
        tips: (K,) current ids; targets: (K,) wanted ids, both distinct and < ``num_verts``.

    Returns:
        (num_verts,) permutation: ``order[targets[k]] == tips[k]``.
    """
    tips, targets = np.asarray(tips, dtype=np.int64), np.asarray(targets, dtype=np.int64)
    if targets.max() >= num_verts:
        raise ValueError(f"a mesh of {num_verts} vertices has no vertex id {int(targets.max())}")
    order = np.full(num_verts, -1, dtype=np.int64)
    order[targets] = tips
    order[order < 0] = np.setdiff1d(np.arange(num_verts), tips)
    return order


def _tips_at_mano_ids(model: ManoModelData) -> ManoModelData:
    """Renumber the vertices so the fingertips have MANO's fingertip ids."""
    targets = np.asarray(MANO_RELEASE_TIP_IDS[model.side])
    return reorder_vertices(model, _tip_order(model.tip_vertex_ids, targets, model.num_verts))


_MIRROR = np.array([-1.0, 1.0, 1.0])


def mirror_to_left(right: ManoModelData, replicate_release_shapedirs: bool = True) -> ManoModelData:
    """The left hand as the mirror image (x -> -x) of a right-hand model.

    Vertices are mirrored, faces re-wound, pose correctives conjugated by the reflection
    (``P_L[v, c, 3a+b] = m_c m_a m_b P_R[v, c, 3a+b]``), articulation components and the mean
    mirrored per joint (``(a_x, a_y, a_z) -> (a_x, -a_y, -a_z)``).

    Args:
        replicate_release_shapedirs: keep ``shapedirs[:, 0, :]`` equal to the right hand's,
            reproducing the sign issue of the official left MANO file (smplx issue #48), so
            that ``MANOLayer(fix_left_shapedirs=True)`` behaves on this model as on the real
            one. With False the shape blend shapes are mirrored correctly.
    """
    m = _MIRROR
    s9 = np.outer(m, m).reshape(9)
    posedirs = right.posedirs.reshape(right.num_verts, 3, 15, 9) * m[None, :, None, None] * s9
    shapedirs = right.shapedirs.copy()
    if not replicate_release_shapedirs:
        shapedirs = shapedirs * m[None, :, None]
    aa_mirror = np.tile(-m, 15)  # (1,-1,-1) per joint
    meta = dict(right.meta)
    meta["left_shapedirs_x_unmirrored"] = bool(replicate_release_shapedirs)
    return right.replace(
        v_template=right.v_template * m,
        faces=right.faces[:, [0, 2, 1]],
        posedirs=posedirs.reshape(right.num_verts, 3, 135),
        shapedirs=shapedirs,
        hands_mean=right.hands_mean * aa_mirror,
        hands_components=right.hands_components * aa_mirror[None, :],
        side="left",
        meta=meta,
    )


def synthetic_hand_pair(spec: HandSpec = HandSpec(), seed: int = 0) -> tuple[ManoModelData, ManoModelData]:
    """(right, left) synthetic MANO-schema models."""
    right = build_synthetic_hand(spec, seed)
    return right, mirror_to_left(right)
