"""Compiled CPU kernels of the mesh rasteriser (numba): face setup, z-buffer, fragments, shading.

Each kernel loops over pixels instead of materialising triangle-pixel pairs, and repeats
the arithmetic of the vectorised PyTorch path operation for operation in the input dtype:
the face tables, the z-buffer and the fragments (face index, barycentrics, depth) are
bit-identical to it,
and shading agrees to a few float ulps (``pow`` and the texture filter round differently).
Floating constants are passed in as arrays of the input dtype so that float32 inputs are
never promoted to float64 inside a kernel.

Notation: V vertices, F faces, Fk kept faces, H x W image, N covered samples.
"""

from __future__ import annotations

import numpy as np
import torch

try:
    from numba import njit
except ImportError:  # numba is the [cpu] extra: without it the PyTorch paths run
    njit = None

__all__ = ["AVAILABLE", "compile_kernel", "use_kernels", "pixel_centres", "setup_faces", "zbuffer", "resolve", "shade"]

AVAILABLE = njit is not None
_INT64_MAX = np.iinfo(np.int64).max


def compile_kernel(fn):
    """Compile with numba when it is installed: GIL released, IEEE float semantics (division
    by zero gives inf / nan, as in PyTorch, instead of raising), cached on disk where numba
    finds a writable cache folder (else compiled once per process)."""
    if not AVAILABLE:
        return fn
    try:
        return njit(cache=True, nogil=True, error_model="numpy")(fn)
    except RuntimeError:  # no writable cache location (read-only install)
        return njit(nogil=True, error_model="numpy")(fn)


def pixel_centres(n: int, dtype: torch.dtype) -> torch.Tensor:
    """(n,) pixel centre coordinates ``i + 0.5`` in ``dtype`` (kernels take them as arrays of
    the input dtype, so that float32 scenes are evaluated in float32)."""
    return torch.arange(n).to(dtype) + 0.5


def use_kernels(option: str, choice: str, tensors, differentiable: bool) -> bool:
    """Whether compiled kernels run for ``option=choice`` (``"auto"``, ``"torch"`` or
    ``"numba"``) on ``tensors``: numba installed, CPU tensors, float32 / float64, and, for
    kernels that are not ``differentiable``, no input that requires grad.

    Raises:
        ValueError: an unknown choice, or ``"numba"`` where the kernels cannot run.
    """
    if choice not in ("auto", "torch", "numba"):
        raise ValueError(f"{option} must be 'auto', 'torch' or 'numba', got {choice!r}")
    if choice == "torch":
        return False
    why = None
    if not AVAILABLE:
        why = "numba is not installed (pip install numba)"
    elif any(t.device.type != "cpu" for t in tensors):
        why = "the tensors are not on the CPU"
    elif any(t.dtype not in (torch.float32, torch.float64) for t in tensors if t.is_floating_point()):
        why = "the kernels take float32 or float64"
    elif not differentiable and torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
        why = "an input requires grad (the kernels are not differentiable)"
    if why is not None and choice == "numba":
        raise ValueError(f"{option}='numba' cannot run: {why}")
    return why is None


@compile_kernel
def zbuffer(a, b, x, y, tl, inv_z, row0, col0, nrows, ncols, pxs, pys, width, zkey):  # pragma: no cover
    """Nearest (depth, face) key per pixel over every kept face's pixel box.

    Args:
        a, b, x, y: (3, Fk) oriented edge coefficients and canonical first endpoints.
        tl: (3, Fk) bool, top-left edges (ties are inside).
        inv_z: (3, Fk) ``1 / z`` of the vertex opposite each edge.
        row0, col0, nrows, ncols: (Fk,) int64 pixel box of each face.
        pxs, pys: (W,), (H,) pixel centre coordinates ``j + 0.5`` / ``i + 0.5``.
        width: W.
        zkey: (H W,) int64, updated in place with ``min`` of ``float32 bits(depth) << 32 | k``.
    """
    bits = np.empty(1, np.float32)
    ibits = bits.view(np.int32)
    for f in range(row0.shape[0]):
        a0, a1, a2 = a[0, f], a[1, f], a[2, f]
        b0, b1, b2 = b[0, f], b[1, f], b[2, f]
        x0, x1, x2 = x[0, f], x[1, f], x[2, f]
        y0, y1, y2 = y[0, f], y[1, f], y[2, f]
        t0, t1, t2 = tl[0, f], tl[1, f], tl[2, f]
        z0, z1, z2 = inv_z[0, f], inv_z[1, f], inv_z[2, f]
        for r in range(row0[f], row0[f] + nrows[f]):
            py = pys[r]
            dy0 = b0 * (py - y0)
            dy1 = b1 * (py - y1)
            dy2 = b2 * (py - y2)
            base = r * width
            for c in range(col0[f], col0[f] + ncols[f]):
                px = pxs[c]
                e0 = a0 * (px - x0) + dy0
                if not ((e0 >= 0) if t0 else (e0 > 0)):
                    continue
                e1 = a1 * (px - x1) + dy1
                if not ((e1 >= 0) if t1 else (e1 > 0)):
                    continue
                e2 = a2 * (px - x2) + dy2
                if not ((e2 >= 0) if t2 else (e2 > 0)):
                    continue
                den = e0 + e1 + e2
                if not den > 0:
                    continue
                d = den / (e0 * z0 + e1 * z1 + e2 * z2)
                if not (np.isfinite(d) and d > 0):
                    continue
                bits[0] = d
                key = (np.int64(ibits[0]) << 32) | f
                if key < zkey[base + c]:
                    zkey[base + c] = key


@compile_kernel
def resolve(zkey, face_ids, verts_cam, faces, K, pxs, pys, width, consts, face_idx, bary, depth):  # pragma: no cover
    """Visible face, perspective-correct barycentrics and depth of every covered pixel.

    Args:
        zkey: (H W,) int64 z-buffer keys (``INT64_MAX`` on background).
        face_ids: (Fk,) original index of each kept face.
        verts_cam: (V, 3) camera-space vertices; faces: (F, 3) int64; K: (3, 3).
        pxs, pys: pixel centre coordinates; width: W.
        consts: (2,) the dtype's smallest normal number, and 1.
        face_idx: (H W,) int64, bary: (H W, 3), depth: (H W,): written everywhere (-1, 0
            and +inf on background).
    """
    tiny, one = consts[0], consts[1]
    zero = tiny - tiny
    inf = one / zero
    du = np.empty(3, verts_cam.dtype)
    dv = np.empty(3, verts_cam.dtype)
    zs = np.empty(3, verts_cam.dtype)
    for p in range(zkey.shape[0]):
        key = zkey[p]
        if key == _INT64_MAX:
            face_idx[p] = -1
            bary[p, 0] = bary[p, 1] = bary[p, 2] = zero
            depth[p] = inf
            continue
        f = face_ids[key & 0xFFFFFFFF]
        pu = pxs[p % width]
        pv = pys[p // width]
        for k in range(3):
            v = faces[f, k]
            xn = verts_cam[v, 0] / verts_cam[v, 2]
            yn = verts_cam[v, 1] / verts_cam[v, 2]
            du[k] = (K[0, 0] * xn + K[0, 1] * yn + K[0, 2]) - pu
            dv[k] = (K[1, 0] * xn + K[1, 1] * yn + K[1, 2]) - pv
            zs[k] = verts_cam[v, 2]
        lam0 = du[1] * dv[2] - dv[1] * du[2]
        lam1 = du[2] * dv[0] - dv[2] * du[0]
        lam2 = du[0] * dv[1] - dv[0] * du[1]
        s = lam0 + lam1 + lam2
        lam0, lam1, lam2 = lam0 / s, lam1 / s, lam2 / s
        lam0 = zero if lam0 < zero else lam0
        lam1 = zero if lam1 < zero else lam1
        lam2 = zero if lam2 < zero else lam2
        s = lam0 + lam1 + lam2
        s = tiny if s < tiny else s
        w0, w1, w2 = lam0 / s / zs[0], lam1 / s / zs[1], lam2 / s / zs[2]
        inv = w0 + w1 + w2
        face_idx[p] = f
        bary[p, 0] = w0 / inv
        bary[p, 1] = w1 / inv
        bary[p, 2] = w2 / inv
        depth[p] = one / inv


@compile_kernel
def shade(
    face_idx,
    bary,
    verts_cam,
    faces,
    unit_fn,
    vert_n,
    smooth,
    face_part,
    part_ids,
    part_tex,
    colors,
    uv,
    tex,
    tex_off,
    tex_h,
    tex_w,
    tex_hw,
    light,
    consts,
    color,
    normal,
    pid,
):  # pragma: no cover
    """Blinn-Phong colour, shading normal and part id of every covered sample.

    Args:
        face_idx: (S,) visible face per sample (-1 on background); bary: (S, 3).
        verts_cam: (V, 3); faces: (F, 3) int64; unit_fn: (F, 3) unit face normals.
        vert_n: (V, 3) unit vertex normals (used when ``smooth``).
        face_part: (F,) part of each face; part_ids: (P,) their ids.
        part_tex: (P,) int64 texture slot of each part, -1 for vertex colours.
        colors: (V, 3) vertex colours (0 on textured parts); uv: (V, 2) (0 elsewhere).
        tex: flat float textures; tex_off, tex_h, tex_w: (T,) int64 offset and size of each;
            tex_hw: (T, 2) the sizes in the dtype.
        light: (9,) to-light direction (3), ambient, diffuse, specular, shininess, and the
            normal thresholds 1e-6 and 1e-12 of the PyTorch path.
        consts: (1,) holding 1 in the dtype.
        color, normal: (S, 3), pid: (S,) int64: written everywhere (0 on background).
    """
    one = consts[0]
    zero = one - one
    two = one + one
    lx, ly, lz = light[0], light[1], light[2]
    amb, dif, spw, shin = light[3], light[4], light[5], light[6]
    n_eps, u_eps = light[7], light[8]
    for p in range(face_idx.shape[0]):
        f = face_idx[p]
        if f < 0:
            color[p, 0] = color[p, 1] = color[p, 2] = zero
            normal[p, 0] = normal[p, 1] = normal[p, 2] = zero
            pid[p] = 0
            continue
        b0, b1, b2 = bary[p, 0], bary[p, 1], bary[p, 2]
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        px = verts_cam[i0, 0] * b0 + verts_cam[i1, 0] * b1 + verts_cam[i2, 0] * b2
        py = verts_cam[i0, 1] * b0 + verts_cam[i1, 1] * b1 + verts_cam[i2, 1] * b2
        pz = verts_cam[i0, 2] * b0 + verts_cam[i1, 2] * b1 + verts_cam[i2, 2] * b2
        fx, fy, fz = unit_fn[f, 0], unit_fn[f, 1], unit_fn[f, 2]
        facing = -one if (fx * px + fy * py + fz * pz) > zero else one
        if smooth:
            nx = vert_n[i0, 0] * b0 + vert_n[i1, 0] * b1 + vert_n[i2, 0] * b2
            ny = vert_n[i0, 1] * b0 + vert_n[i1, 1] * b1 + vert_n[i2, 1] * b2
            nz = vert_n[i0, 2] * b0 + vert_n[i1, 2] * b1 + vert_n[i2, 2] * b2
            norm = np.sqrt(nx * nx + ny * ny + nz * nz)
            if norm > n_eps:
                nx, ny, nz = nx / norm, ny / norm, nz / norm
            else:
                nx, ny, nz = fx, fy, fz
        else:
            nx, ny, nz = fx, fy, fz
        nx, ny, nz = nx * facing, ny * facing, nz * facing
        part = face_part[f]
        slot = part_tex[part]
        if slot < 0:
            ar = colors[i0, 0] * b0 + colors[i1, 0] * b1 + colors[i2, 0] * b2
            ag = colors[i0, 1] * b0 + colors[i1, 1] * b1 + colors[i2, 1] * b2
            ab = colors[i0, 2] * b0 + colors[i1, 2] * b1 + colors[i2, 2] * b2
        else:
            tu = uv[i0, 0] * b0 + uv[i1, 0] * b1 + uv[i2, 0] * b2
            tv = uv[i0, 1] * b0 + uv[i1, 1] * b1 + uv[i2, 1] * b2
            th, tw, off = tex_h[slot], tex_w[slot], tex_off[slot]
            thf, twf = tex_hw[slot, 0], tex_hw[slot, 1]
            # grid_sample, bilinear, border padding, align_corners=False
            ix = ((tu * two - one + one) * twf - one) / two
            iy = (((one - tv) * two - one + one) * thf - one) / two
            if not ix >= zero:  # also NaN (from NaN uv): stay inside the texture
                ix = zero
            if not iy >= zero:
                iy = zero
            ix = min(max(ix, zero), twf - one)
            iy = min(max(iy, zero), thf - one)
            x0 = np.floor(ix)
            y0 = np.floor(iy)
            wx0, wx1 = (x0 + one) - ix, ix - x0
            wy0, wy1 = (y0 + one) - iy, iy - y0
            c0, r0 = int(x0), int(y0)
            c1 = c0 + 1 if c0 + 1 < tw else c0  # outside corners carry weight 0
            r1 = r0 + 1 if r0 + 1 < th else r0
            ar = ag = ab = zero
            for rr, cc, w in ((r0, c0, wx0 * wy0), (r0, c1, wx1 * wy0), (r1, c0, wx0 * wy1), (r1, c1, wx1 * wy1)):
                q = off + (rr * tw + cc) * 3
                ar += w * tex[q]
                ag += w * tex[q + 1]
                ab += w * tex[q + 2]
        # view = normalize(-points), half = normalize(to_light + view)
        vn = np.sqrt(px * px + py * py + pz * pz)
        vn = u_eps if vn < u_eps else vn
        vx, vy, vz = -px / vn, -py / vn, -pz / vn
        n_dot_l = nx * lx + ny * ly + nz * lz
        n_dot_l = zero if n_dot_l < zero else n_dot_l
        hx, hy, hz = lx + vx, ly + vy, lz + vz
        hn = np.sqrt(hx * hx + hy * hy + hz * hz)
        hn = u_eps if hn < u_eps else hn
        hx, hy, hz = hx / hn, hy / hn, hz / hn
        n_dot_h = nx * hx + ny * hy + nz * hz
        n_dot_h = zero if n_dot_h < zero else n_dot_h
        spec = n_dot_h**shin if n_dot_l > zero else zero
        k = amb + dif * n_dot_l
        r = ar * k + spw * spec
        g = ag * k + spw * spec
        bb = ab * k + spw * spec
        color[p, 0] = min(max(r, zero), one)
        color[p, 1] = min(max(g, zero), one)
        color[p, 2] = min(max(bb, zero), one)
        normal[p, 0], normal[p, 1], normal[p, 2] = nx, ny, nz
        pid[p] = part_ids[part]


@compile_kernel
def setup_faces(
    verts_cam, faces, K, height, width, near, front, consts, face_ids, a, b, x, y, tl, inv_z, row0, col0, nrows, ncols
):  # pragma: no cover
    """Project, drop (near plane, non-finite, culled, degenerate, off-screen) and tabulate
    faces; the kept ones are written in increasing face order.

    Args:
        verts_cam: (V, 3) camera-space vertices; faces: (F, 3) int64; K: (3, 3).
        height, width: image size; near: (1,) near plane in the dtype.
        front: (F,) bool, False for the faces that back-face culling drops (it is computed
            outside: PyTorch's cross product may fuse multiply-adds, and edge-on faces
            depend on it).
        consts: (4,) 0.5, the box margin (px), -1 and ``max(H, W) + 1`` in the dtype.
        face_ids, row0, col0, nrows, ncols: (F,) int64 outputs; a, b, x, y, inv_z: (3, F)
            outputs; tl: (3, F) bool output.

    Returns:
        Fk, the number of kept faces (the first Fk entries of the outputs are valid).
    """
    half, eps, lo_clamp, hi_clamp = consts[0], consts[1], consts[2], consts[3]
    one = half + half
    zero = half - half
    uv = np.empty((3, 2), verts_cam.dtype)
    zs = np.empty(3, verts_cam.dtype)
    ea = np.empty(3, verts_cam.dtype)
    eb = np.empty(3, verts_cam.dtype)
    ex = np.empty(3, verts_cam.dtype)
    ey = np.empty(3, verts_cam.dtype)
    kept = 0
    for f in range(faces.shape[0]):
        ok = True
        for k in range(3):
            v = faces[f, k]
            zs[k] = verts_cam[v, 2]
            if not (
                verts_cam[v, 2] > near[0]
                and np.isfinite(verts_cam[v, 0])
                and np.isfinite(verts_cam[v, 1])
                and np.isfinite(verts_cam[v, 2])
            ):
                ok = False
        if not ok:
            continue
        for k in range(3):
            v = faces[f, k]
            xn = verts_cam[v, 0] / verts_cam[v, 2]
            yn = verts_cam[v, 1] / verts_cam[v, 2]
            uv[k, 0] = K[0, 0] * xn + K[0, 1] * yn + K[0, 2]
            uv[k, 1] = K[1, 0] * xn + K[1, 1] * yn + K[1, 2]
            if not (np.isfinite(uv[k, 0]) and np.isfinite(uv[k, 1])):
                ok = False
        if not ok:
            continue
        if not front[f]:
            continue
        for k in range(3):
            p, q = (k + 1) % 3, (k + 2) % 3
            if uv[q, 0] < uv[p, 0] or (uv[q, 0] == uv[p, 0] and uv[q, 1] < uv[p, 1]):
                p, q = q, p
            ea[k] = -(uv[q, 1] - uv[p, 1])
            eb[k] = uv[q, 0] - uv[p, 0]
            side = np.float64(ea[k]) * (np.float64(uv[k, 0]) - np.float64(uv[p, 0])) + np.float64(eb[k]) * (
                np.float64(uv[k, 1]) - np.float64(uv[p, 1])
            )
            if side > 0:
                sign = one
            elif side < 0:
                sign = -one
            else:
                ok = False
                sign = zero
            ea[k] = ea[k] * sign
            eb[k] = eb[k] * sign
            ex[k] = uv[p, 0]
            ey[k] = uv[p, 1]
        if not ok:
            continue
        umin = min(uv[0, 0], min(uv[1, 0], uv[2, 0]))
        vmin = min(uv[0, 1], min(uv[1, 1], uv[2, 1]))
        umax = max(uv[0, 0], max(uv[1, 0], uv[2, 0]))
        vmax = max(uv[0, 1], max(uv[1, 1], uv[2, 1]))
        lu = min(max(umin - half - eps, lo_clamp), hi_clamp)
        lv = min(max(vmin - half - eps, lo_clamp), hi_clamp)
        hu = min(max(umax - half + eps, lo_clamp), hi_clamp)
        hv = min(max(vmax - half + eps, lo_clamp), hi_clamp)
        c0 = max(np.int64(np.ceil(lu)), 0)
        r0 = max(np.int64(np.ceil(lv)), 0)
        c1 = min(np.int64(np.floor(hu)), width - 1)
        r1 = min(np.int64(np.floor(hv)), height - 1)
        if r1 < r0 or c1 < c0:
            continue
        face_ids[kept] = f
        for k in range(3):
            a[k, kept] = ea[k]
            b[k, kept] = eb[k]
            x[k, kept] = ex[k]
            y[k, kept] = ey[k]
            tl[k, kept] = ea[k] > 0 or (ea[k] == 0 and eb[k] > 0)
            inv_z[k, kept] = one / zs[k]
        row0[kept], col0[kept] = r0, c0
        nrows[kept], ncols[kept] = r1 - r0 + 1, c1 - c0 + 1
        kept += 1
    return kept
