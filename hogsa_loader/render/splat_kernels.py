"""Compiled CPU kernels of the Gaussian compositor (numba): forward and backward per tile.

:func:`composite_forward` composites the busy tiles with gsplat's per-pixel rules and
:func:`composite_backward` replays them back to front for the gradients; the caller is
:func:`hogsa_loader.render.gaussians.render_gaussians` (``compositor="numba"``).
"""

from __future__ import annotations

import math

import numpy as np

from hogsa_loader.render.raster_kernels import AVAILABLE, compile_kernel

__all__ = ["AVAILABLE", "composite_forward", "composite_backward", "GRAD_COLUMNS"]

GRAD_COLUMNS = 6  # per-intersection gradient columns before the features: mx, my, A, B, C, log o


@compile_kernel
def _pixel_box(mx, my, rx, ry, x0, y0, tile_size):  # pragma: no cover
    """Tile-local column / row range ``[c0, c1) x [r0, r1)`` of the pixels whose centres lie
    within a Gaussian's radius plus half a pixel (the margin absorbs rounding: every pixel
    with ``alpha > 1/255`` lies within the radius when the opacity is at most 1)."""
    c0 = max(0, int(math.ceil(mx - rx - 1.0)) - x0)
    c1 = min(tile_size, int(math.floor(mx + rx)) - x0 + 1)
    r0 = max(0, int(math.ceil(my - ry - 1.0)) - y0)
    r1 = min(tile_size, int(math.floor(my + ry)) - y0 + 1)
    return c0, c1, r0, r1


@compile_kernel
def _tile_origin(tile, n_tiles, tile_w, tile_size):  # pragma: no cover
    """Pixel column / row of a global tile index's top-left corner."""
    local = tile % n_tiles
    return (local % tile_w) * tile_size, (local // tile_w) * tile_size


@compile_kernel
def _gaussian(g, means2d, conics, log_o, radii, x0, y0, tile_size):  # pragma: no cover
    """Table row ``g``: mean, conic, log opacity and its pixel box in the tile at (x0, y0)."""
    mx, my = means2d[g, 0], means2d[g, 1]
    box = _pixel_box(mx, my, radii[g, 0], radii[g, 1], x0, y0, tile_size)
    return mx, my, conics[g, 0], conics[g, 1], conics[g, 2], log_o[g], box


@compile_kernel
def _visibility(mx, dy, a, b, c, lo, px, half):  # pragma: no cover
    """``dx = mx - px`` and ``exp(log o - sigma)`` at a pixel centre ``px`` (``dy = my - py``)."""
    dx = mx - px
    return dx, np.exp(lo - (half * (a * dx * dx + c * dy * dy) + b * dx * dy))


@compile_kernel
def composite_forward(
    sel,
    busy,
    start,
    count,
    gids,
    means2d,
    conics,
    log_o,
    radii,
    feats,
    tile_size,
    tile_w,
    n_tiles,
    width,
    height,
    pxs,
    pys,
    consts,
    acc,
    trans,
    last,
    done,
):  # pragma: no cover
    """Composite the busy tiles ``sel`` front to back.

    The forward pass walks each tile's depth-sorted Gaussians front to back and updates only
    the pixels of each Gaussian's box (its 2D radius plus half a pixel), with gsplat's per-pixel
    rules: ``alpha = min(0.999, exp(log o - sigma))``, samples with ``alpha <= 1/255``
    skipped, a pixel stopping before the Gaussian whose ``next_T`` would be ``<= 1e-4``. It
    records, per pixel, how many list entries it used, which the backward pass replays back to
    front (transmittance recovered by division, as gsplat's backward kernel does).

    Notation: M table rows (image, Gaussian), F feature channels, K intersections, nb busy
    tiles, P = tile_size**2 pixels per tile.

    Args:
        sel: (ns,) int64 rows of the busy-tile arrays this call handles.
        busy: (nb,) int64 global tile index ``image * n_tiles + ty * tile_w + tx``.
        start, count: (nb,) int64 offset / length of each tile's list in ``gids``.
        gids: (K,) int64 table row of each sorted intersection.
        means2d: (M, 2); conics: (M, 3) ``(A, B, C)`` of the inverse 2D covariance;
        log_o: (M,) log opacity; radii: (M, 2) int32 pixel radii; feats: (M, F).
        tile_size, tile_w, n_tiles, width, height: tile edge, tile grid width, tiles per
            image, image size.
        pxs, pys: pixel-centre coordinates ``j + 0.5`` of every column / row of the tile
            grid, in the feature dtype (float32 features are evaluated in float32).
        consts: (4,) in the feature dtype: 1/255, 0.999, 1e-4, 1.
        acc: (nb, P, F) zeros, trans: (nb, P) ones, last: (nb, P) int32 zeros; written for
            the rows in ``sel``: ``sum w feat``, final transmittance, list entries used.
        done: (P,) bool scratch (passed in: the kernel allocates nothing, so threads that
            run it create no allocator state).
    """
    thr, amax, tmin, one = consts[0], consts[1], consts[2], consts[3]
    half = one / (one + one)
    nfeat = feats.shape[1]
    P = tile_size * tile_size
    for i in sel:
        x0, y0 = _tile_origin(busy[i], n_tiles, tile_w, tile_size)
        n_done = 0
        for p in range(P):
            out = x0 + p % tile_size >= width or y0 + p // tile_size >= height
            done[p] = out
            n_done += out
        s = start[i]
        for k in range(count[i]):
            if n_done == P:
                break
            g = gids[s + k]
            mx, my, a, b, c, lo, (c0, c1, r0, r1) = _gaussian(g, means2d, conics, log_o, radii, x0, y0, tile_size)
            for r in range(r0, r1):
                dy = my - pys[y0 + r]
                for cc in range(c0, c1):
                    p = r * tile_size + cc
                    if done[p]:
                        continue
                    dx, vis = _visibility(mx, dy, a, b, c, lo, pxs[x0 + cc], half)
                    if not vis > thr:
                        continue
                    alpha = min(vis, amax)
                    t = trans[i, p]
                    next_t = t * (one - alpha)
                    if not next_t > tmin:
                        done[p] = True
                        n_done += 1
                        continue
                    w = alpha * t
                    for f in range(nfeat):
                        acc[i, p, f] += w * feats[g, f]
                    trans[i, p] = next_t
                    last[i, p] = k + 1


@compile_kernel
def composite_backward(
    sel,
    busy,
    start,
    count,
    gids,
    means2d,
    conics,
    log_o,
    radii,
    feats,
    tile_size,
    tile_w,
    n_tiles,
    width,
    height,
    pxs,
    pys,
    consts,
    trans,
    last,
    v_acc,
    v_trans,
    grads,
    scratch,
):  # pragma: no cover
    """Gradients of :func:`composite_forward`'s outputs, per intersection.

    Gradients are those of the vectorised PyTorch compositor: nothing flows through the 0.999
    clamp, the 1/255 cut-off or the stop. They are written per intersection (each belongs to
    one tile, so tiles run on several threads without write races) and summed per Gaussian by
    the caller.

    Args:
        sel ... consts: as in :func:`composite_forward`.
        trans, last: (nb, P) the forward's final transmittance and entries used.
        v_acc: (nb, P, F), v_trans: (nb, P) gradients of the outputs.
        grads: (K, 6 + F) zeros; row ``j`` gets the gradient of intersection ``j`` with
            respect to its Gaussian's ``mx, my, A, B, C, log o, feats``.
        scratch: (2 P + F,) in the feature dtype (passed in, as in :func:`composite_forward`).
    """
    thr, amax, one = consts[0], consts[1], consts[3]
    half = one / (one + one)
    nfeat = feats.shape[1]
    P = tile_size * tile_size
    t_cur = scratch[:P]  # transmittance after the entry being visited
    after = scratch[P : 2 * P]  # sum over later entries of w (feat . v) + T_final v_T
    gfeat = scratch[2 * P :]
    for i in sel:
        x0, y0 = _tile_origin(busy[i], n_tiles, tile_w, tile_size)
        n_used = 0
        for p in range(P):
            t_cur[p] = trans[i, p]
            after[p] = trans[i, p] * v_trans[i, p]
            n_used = max(n_used, last[i, p])
        s = start[i]
        for k in range(n_used - 1, -1, -1):
            g = gids[s + k]
            mx, my, a, b, c, lo, (c0, c1, r0, r1) = _gaussian(g, means2d, conics, log_o, radii, x0, y0, tile_size)
            gmx = gmy = ga = gb = gc = glo = one - one
            for f in range(nfeat):
                gfeat[f] = one - one
            for r in range(r0, r1):
                dy = my - pys[y0 + r]
                for cc in range(c0, c1):
                    p = r * tile_size + cc
                    if k >= last[i, p]:
                        continue
                    dx, vis = _visibility(mx, dy, a, b, c, lo, pxs[x0 + cc], half)
                    if not vis > thr:
                        continue
                    alpha = min(vis, amax)
                    om = one - alpha
                    t = t_cur[p] / om  # transmittance before this entry
                    w = alpha * t
                    fv = one - one
                    for f in range(nfeat):
                        fv += feats[g, f] * v_acc[i, p, f]
                        gfeat[f] += w * v_acc[i, p, f]
                    d_alpha = t * fv - after[p] / om
                    after[p] += w * fv
                    t_cur[p] = t
                    if vis < amax:
                        G = d_alpha * vis  # d loss / d (log o - sigma)
                        gmx -= G * (a * dx + b * dy)
                        gmy -= G * (b * dx + c * dy)
                        ga -= G * half * dx * dx
                        gb -= G * dx * dy
                        gc -= G * half * dy * dy
                        glo += G
            j = s + k
            grads[j, 0], grads[j, 1], grads[j, 2] = gmx, gmy, ga
            grads[j, 3], grads[j, 4], grads[j, 5] = gb, gc, glo
            for f in range(nfeat):
                grads[j, GRAD_COLUMNS + f] = gfeat[f]
