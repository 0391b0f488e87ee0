"""ARCTIC's hand-object pose metrics, by their definitions.

Per frame: MPJPE (root-aligned, mm), MRRPE (right-to-left hand and right-hand-to-object root,
mm), CDev (contact deviation, mm), AAE (articulation angle error, degrees) and the success
rate (percentage of object vertices within 5% of the object diameter after root alignment).
Per sequence (frames in temporal order): MDev (motion deviation of stable contacts, mm, one
value per contact window) and ACC (acceleration error, m/s^2, at 30 fps).

Undefined values (invalid frames, no contact) are nan. :func:`summarize` reduces them the way
ARCTIC reports its table: the arrays of every sequence (and camera view) of the split are
concatenated and each metric is one nan-mean over all of its entries. Frames therefore weigh
equally across the split (windows, for MDev); sequences are *not* averaged first.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Mapping

import numpy as np
import torch
from torch import Tensor

from hogsa_loader.baselines.loss import contact_deviation

__all__ = [
    "ACC_FPS",
    "MDEV_CONTACT_THRESHOLD_M",
    "MDEV_MIN_WINDOW",
    "SUCCESS_ALPHA",
    "acceleration_error",
    "articulation_error_deg",
    "contact_windows",
    "motion_deviation",
    "mpjpe_root_aligned",
    "object_roots",
    "per_frame_metrics",
    "relative_root_error",
    "sequence_metrics",
    "success_rate",
    "summarize",
]

SUCCESS_ALPHA = 0.05  #: success threshold as a fraction of the object diameter
ACC_FPS = 30.0  #: frame rate used for the acceleration stencil
MDEV_CONTACT_THRESHOLD_M = 3e-3  #: ground-truth contact distance for MDev windows (m)
MDEV_MIN_WINDOW = 15  #: shortest stable-contact window for MDev (frames, half a second)


def _t(x) -> Tensor:
    """Detached float64 CPU copy of a tensor or array."""
    return torch.as_tensor(x).detach().to("cpu", torch.float64)


def _mask(x) -> Tensor:
    """Boolean CPU mask from a 0/1 tensor or array; (B,) -> (B,)."""
    return torch.as_tensor(x).detach().cpu().reshape(-1).long() != 0


def _nan_where(values: Tensor, keep: Tensor) -> Tensor:
    """Set entries outside ``keep`` to nan; (B,), (B,) -> (B,)."""
    return torch.where(keep, values, torch.full_like(values, float("nan")))


def _nanmean_pair(a: Tensor, b: Tensor) -> Tensor:
    """Element-wise nan-mean of two (B,) tensors (nan where both are nan)."""
    both = torch.stack((a, b), 1)
    ok = ~torch.isnan(both)
    return torch.where(ok, both, torch.zeros_like(both)).sum(1) / ok.sum(1)


def _hand_valid(targets: Mapping, side: str) -> Tensor:
    """Frames where ``side`` ("r" or "l") is evaluated: hand valid and frame valid; (B,)."""
    flag = targets["right_valid" if side == "r" else "left_valid"]
    return _mask(targets["is_valid"]) & _mask(flag)


def _v_len(targets: Mapping, meta_info: Mapping, batch: int, vmax: int) -> Tensor:
    """True object vertex counts (B,), from targets or meta_info; all ``vmax`` if absent."""
    v_len = targets.get("object.v_len", meta_info.get("object.v_len"))
    if v_len is None:
        return torch.full((batch,), vmax, dtype=torch.long)
    return torch.as_tensor(v_len).detach().cpu().reshape(-1).long()


def mpjpe_root_aligned(j_pred: Tensor, j_gt: Tensor, valid: Tensor) -> Tensor:
    """Mean per-joint position error after subtracting joint 0 from each skeleton.

    Args:
        j_pred: (B, J, 3) predicted joints.
        j_gt: (B, J, 3) ground-truth joints.
        valid: (B,) bool frames to evaluate.

    Returns:
        (B,) mean joint distance (input units); nan where not valid.
    """
    err = ((j_pred - j_pred[:, :1]) - (j_gt - j_gt[:, :1])).norm(dim=-1).mean(-1)
    return _nan_where(err, valid)


def relative_root_error(a_pred: Tensor, b_pred: Tensor, a_gt: Tensor, b_gt: Tensor, valid: Tensor) -> Tensor:
    """MRRPE: error of the vector from root ``a`` to root ``b``.

    Args:
        a_pred, b_pred: (B, 3) predicted roots.
        a_gt, b_gt: (B, 3) ground-truth roots.
        valid: (B,) bool frames to evaluate.

    Returns:
        (B,) ``|(b_pred - a_pred) - (b_gt - a_gt)|``; nan where not valid.
    """
    return _nan_where(((b_pred - a_pred) - (b_gt - a_gt)).norm(dim=-1), valid)


def object_roots(v: Tensor, v_len: Tensor, part_ids: Tensor) -> Tensor:
    """Object root: mean of the bottom-part vertices (``part_ids == 2``).

    Args:
        v: (B, Vmax, 3) zero-padded object vertices.
        v_len: (B,) true vertex counts.
        part_ids: (B, Vmax) part label of every vertex.

    Returns:
        (B, 3) roots.
    """
    ar = torch.arange(v.shape[1])
    bottom = (torch.as_tensor(part_ids).cpu() == 2) & (ar[None] < v_len[:, None])
    w = bottom.to(v.dtype)[..., None]
    return (v * w).sum(1) / w.sum(1)


def success_rate(
    v_pred: Tensor,
    v_gt: Tensor,
    v_len: Tensor,
    part_ids: Tensor,
    diameter: Tensor,
    valid: Tensor,
    alpha: float = SUCCESS_ALPHA,
) -> Tensor:
    """Percentage of object vertices within ``alpha * diameter`` after root alignment.

    Args:
        v_pred, v_gt: (B, Vmax, 3) zero-padded object vertices (m).
        v_len: (B,) true vertex counts.
        part_ids: (B, Vmax) vertex part labels (root = mean of part 2).
        diameter: (B,) object diameters (m).
        valid: (B,) bool frames to evaluate.
        alpha: fraction of the diameter counted as success.

    Returns:
        (B,) percentage in [0, 100]; nan where not valid.
    """
    ra_pred = v_pred - object_roots(v_pred, v_len, part_ids)[:, None]
    ra_gt = v_gt - object_roots(v_gt, v_len, part_ids)[:, None]
    real = torch.arange(v_pred.shape[1])[None] < v_len[:, None]
    hit = ((ra_pred - ra_gt).norm(dim=-1) < alpha * diameter.reshape(-1, 1)) & real
    return _nan_where(100.0 * hit.sum(1) / v_len.to(v_pred.dtype), valid)


def articulation_error_deg(rad_pred: Tensor, rad_gt: Tensor, valid: Tensor) -> Tensor:
    """AAE: absolute articulation angle difference in degrees.

    Args:
        rad_pred, rad_gt: (B,) articulation angles (radians).
        valid: (B,) bool frames to evaluate.

    Returns:
        (B,) degrees; nan where not valid.
    """
    return _nan_where(torch.rad2deg((rad_pred - rad_gt).abs()), valid)


def per_frame_metrics(pred: Mapping, targets: Mapping, meta_info: Mapping) -> dict[str, np.ndarray]:
    """ARCTIC's per-frame metrics of one batch.

    Args:
        pred: ``mano.j3d.cam.{r,l}`` (B, 21, 3), ``mano.v3d.cam.{r,l}`` (B, Vh, 3),
            ``object.v.cam`` (B, Vmax, 3) zero-padded, ``object.radian`` (B, 1), in metres
            and radians.
        targets: the same keys as ground truth, plus ``is_valid``, ``right_valid``,
            ``left_valid`` (B,), ``dist.{ro,lo}`` (B, Vh), ``idx.{ro,lo}`` (B, Vh) and
            ``object.v_len`` (B,) (or in ``meta_info``).
        meta_info: ``part_ids`` (B, Vmax) and ``diameter`` (B,) (m).

    Returns:
        ``{key: (B,) float64 array}`` with nan where undefined: ``mpjpe/ra/h`` (the nan-mean
        of each hand's ``mpjpe/ra/r`` and ``mpjpe/ra/l``), ``mrrpe/r/l``, ``mrrpe/r/o``,
        ``cdev/ho`` (mm), ``aae`` (degrees) and ``success_rate/0.05`` (percent).
    """
    jp = {s: _t(pred[f"mano.j3d.cam.{s}"]) for s in "rl"}
    jg = {s: _t(targets[f"mano.j3d.cam.{s}"]) for s in "rl"}
    vo_p, vo_g = _t(pred["object.v.cam"]), _t(targets["object.v.cam"])
    v_len = _v_len(targets, meta_info, *vo_g.shape[:2])
    part_ids = torch.as_tensor(meta_info["part_ids"]).cpu()
    frame, rv, lv = _mask(targets["is_valid"]), _hand_valid(targets, "r"), _hand_valid(targets, "l")

    per_hand = {s: mpjpe_root_aligned(jp[s], jg[s], v) for s, v in (("r", rv), ("l", lv))}
    mrrpe_rl = relative_root_error(jp["r"][:, 0], jp["l"][:, 0], jg["r"][:, 0], jg["l"][:, 0], rv & lv)
    root_o_p, root_o_g = object_roots(vo_p, v_len, part_ids), object_roots(vo_g, v_len, part_ids)
    mrrpe_ro = relative_root_error(jp["r"][:, 0], root_o_p, jg["r"][:, 0], root_o_g, rv)
    cdev = [
        contact_deviation(
            vo_p,
            _t(pred[f"mano.v3d.cam.{s}"]),
            _t(targets[f"dist.{s}o"]),
            torch.as_tensor(targets[f"idx.{s}o"]).cpu().long(),
            valid,
        )
        for s, valid in (("r", rv), ("l", lv))
    ]
    rad_p, rad_g = _t(pred["object.radian"]).reshape(-1), _t(targets["object.radian"]).reshape(-1)
    diameter = _t(meta_info["diameter"]).reshape(-1)
    success = success_rate(vo_p, vo_g, v_len, part_ids, diameter, frame)
    out = {
        "mpjpe/ra/h": 1000.0 * _nanmean_pair(per_hand["r"], per_hand["l"]),
        "mpjpe/ra/r": 1000.0 * per_hand["r"],
        "mpjpe/ra/l": 1000.0 * per_hand["l"],
        "mrrpe/r/l": 1000.0 * mrrpe_rl,
        "mrrpe/r/o": 1000.0 * mrrpe_ro,
        "cdev/ho": 1000.0 * _nanmean_pair(*cdev),
        "aae": articulation_error_deg(rad_p, rad_g, frame),
        f"success_rate/{SUCCESS_ALPHA:.2f}": success,
    }
    return {k: v.numpy() for k, v in out.items()}


def acceleration_error(x_gt: Tensor, x_pred: Tensor, fps: float = ACC_FPS) -> Tensor:
    """Acceleration error by the central second difference ``(x[t-1] - 2x[t] + x[t+1]) / h^2``.

    Args:
        x_gt, x_pred: (N, P, 3) point trajectories (m) over N consecutive frames.
        fps: frame rate; ``h = 1 / fps`` seconds.

    Returns:
        (N - 2,) mean over points of the norm of the acceleration difference (m/s^2), for
        frames 1 .. N-2.
    """

    def accel(x: Tensor) -> Tensor:
        return (x[:-2] - 2.0 * x[1:-1] + x[2:]) * fps**2

    return (accel(x_pred) - accel(x_gt)).norm(dim=-1).mean(-1)


def _triple_valid(valid: Tensor) -> Tensor:
    """Frame t (1 .. N-2) is usable when t-1, t and t+1 are all valid; (N,) -> (N-2,)."""
    return valid[:-2] & valid[1:-1] & valid[2:]


def _pad_nan(x: Tensor) -> Tensor:
    """Pad one nan at both ends; (N-2,) -> (N,)."""
    pad = torch.full((1,), float("nan"), dtype=x.dtype)
    return torch.cat((pad, x, pad))


def _acc_metrics(pred: Mapping, targets: Mapping, v_len: int, part_ids: Tensor, fps: float) -> dict[str, Tensor]:
    """ACC of the root-relative hand and object vertices of one sequence, padded to (N,)."""
    acc = {}
    for s in "rl":
        vp, vg = _t(pred[f"mano.v3d.cam.{s}"]), _t(targets[f"mano.v3d.cam.{s}"])
        jp, jg = _t(pred[f"mano.j3d.cam.{s}"]), _t(targets[f"mano.j3d.cam.{s}"])
        err = acceleration_error(vg - jg[:, :1], vp - jp[:, :1], fps)
        acc[s] = _nan_where(err, _triple_valid(_hand_valid(targets, s)))
    vo_p, vo_g = _t(pred["object.v.cam"])[:, :v_len], _t(targets["object.v.cam"])[:, :v_len]
    bottom = part_ids[:v_len] == 2
    root_p, root_g = vo_p[:, bottom].mean(1, keepdim=True), vo_g[:, bottom].mean(1, keepdim=True)
    acc_o = acceleration_error(vo_g - root_g, vo_p - root_p, fps)
    acc_o = _nan_where(acc_o, _triple_valid(_mask(targets["is_valid"])))
    return {"acc/h": _pad_nan(_nanmean_pair(acc["r"], acc["l"])), "acc/o": _pad_nan(acc_o)}


def _is_sliding(j_list: np.ndarray, v_ref: Tensor, thres: float, min_len: int) -> bool:
    """Whether the object vertices matched to one hand vertex over a window spread apart.

    The mean pairwise distance of the matched vertices (in the reference object pose) is
    taken over the pairs ARCTIC keeps: the full window's distance matrix minus the upper
    triangle, diagonal included, of its leading ``min_len`` x ``min_len`` block.
    """
    vj = v_ref[torch.as_tensor(j_list)]
    d = torch.cdist(vj, vj).numpy()
    iu = np.triu_indices(min_len)
    d[iu] = np.nan
    return bool(np.nanmean(d) > thres)


def contact_windows(
    dist: Tensor, idx: Tensor, v_ref: Tensor, thres: float = MDEV_CONTACT_THRESHOLD_M, min_len: int = MDEV_MIN_WINDOW
) -> list[tuple[int, int, int, int]]:
    """Stable-contact windows of one hand, as ARCTIC finds them for MDev.

    A window is a maximal run of at least ``min_len`` frames in which hand vertex ``i`` is
    closer than ``thres`` to the object (strictly) and that has ended before the last frame
    (a run still open at the end of the sequence is not counted). Runs whose matched object
    vertices slide over the surface (mean pairwise distance above ``thres``) are dropped;
    the window's object vertex ``j`` is the most frequent match (smallest index on ties).

    Args:
        dist: (N, Vh) ground-truth hand-vertex-to-object distances (m).
        idx: (N, Vh) nearest object vertex of each hand vertex.
        v_ref: (Vo, 3) object vertices in a reference pose (the first ground-truth frame).
        thres: contact threshold (m).
        min_len: shortest window (frames).

    Returns:
        ``[(m, n, i, j)]``: first and last frame (inclusive), hand vertex, object vertex.
    """
    contact = (_t(dist) < thres).numpy()
    idx = torch.as_tensor(idx).cpu().long().numpy()
    num_frames = contact.shape[0]
    windows = []
    for vi in np.flatnonzero(contact.sum(0) >= min_len):
        edges = np.diff(np.concatenate(([0], contact[:, vi].astype(np.int8), [0])))
        for s, e in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1):
            if e == num_frames - 1 or e - s + 1 < min_len:
                continue
            j_list = idx[s : e + 1, vi]
            if _is_sliding(j_list, v_ref, thres, min_len):
                continue
            windows.append((int(s), int(e), int(vi), int(np.bincount(j_list).argmax())))
    return windows


def motion_deviation(
    windows: Iterable[tuple[int, int, int, int]], v_hand: Tensor, v_obj: Tensor, frame_valid: Tensor
) -> Tensor:
    """MDev: per window, mean norm of the difference between the frame-to-frame motion of
    the predicted hand vertex ``i`` and of the predicted object vertex ``j``.

    Args:
        windows: ``(m, n, i, j)`` tuples from :func:`contact_windows`.
        v_hand: (N, Vh, 3) predicted hand vertices (m).
        v_obj: (N, Vo, 3) predicted object vertices (m).
        frame_valid: (N,) bool; a motion step counts when both of its frames are valid.

    Returns:
        (W,) deviation per window (m per frame step); nan if no step of it is valid.
    """
    out = []
    for m, n, i, j in windows:
        step = (v_hand[m + 1 : n + 1, i] - v_hand[m:n, i]) - (v_obj[m + 1 : n + 1, j] - v_obj[m:n, j])
        ok = frame_valid[m + 1 : n + 1] & frame_valid[m:n]
        norms = step.norm(dim=-1)[ok]
        out.append(norms.mean() if norms.numel() else torch.tensor(float("nan"), dtype=v_hand.dtype))
    return torch.stack(out) if out else torch.zeros(0, dtype=v_hand.dtype)


def sequence_metrics(
    pred: Mapping, targets: Mapping, meta_info: Mapping, fps: float = ACC_FPS
) -> dict[str, np.ndarray]:
    """ARCTIC's temporal metrics of one sequence (one object, frames consecutive, in order).

    Args:
        pred: ``mano.v3d.cam.{r,l}`` (N, Vh, 3), ``mano.j3d.cam.{r,l}`` (N, 21, 3),
            ``object.v.cam`` (N, Vmax, 3) (m).
        targets: the same keys as ground truth, plus ``is_valid``, ``right_valid``,
            ``left_valid`` (N,), ``dist.{ro,lo}``, ``idx.{ro,lo}`` (N, Vh) and
            ``object.v_len`` (N,) (or in ``meta_info``).
        meta_info: ``part_ids`` (N, Vmax) (the first frame's is used).
        fps: frame rate of the sequence.

    Returns:
        ``mdev/h``: (W,) mm, one value per contact window of either hand (right first);
        ``acc/h``, ``acc/o``: (N,) m/s^2, nan at both ends and where a frame of the
        three-frame stencil is invalid.
    """
    vo_g = _t(targets["object.v.cam"])
    num_frames = vo_g.shape[0]
    v_len = int(_v_len(targets, meta_info, num_frames, vo_g.shape[1])[0])
    part_ids = torch.as_tensor(meta_info.get("part_ids", targets.get("object.parts_ids"))).cpu()[0]
    mdev = []
    for s in "rl":
        wins = contact_windows(targets[f"dist.{s}o"], targets[f"idx.{s}o"], vo_g[0, :v_len])
        v_hand, v_obj = _t(pred[f"mano.v3d.cam.{s}"]), _t(pred["object.v.cam"])
        mdev.append(motion_deviation(wins, v_hand, v_obj, _hand_valid(targets, s)))
    out = {"mdev/h": 1000.0 * torch.cat(mdev)}
    if num_frames >= 3:
        out.update(_acc_metrics(pred, targets, v_len, part_ids, fps))
    else:
        nan = torch.full((num_frames,), float("nan"), dtype=torch.float64)
        out.update({"acc/h": nan, "acc/o": nan.clone()})
    return {k: v.numpy() for k, v in out.items()}


def summarize(results: Mapping | Iterable[Mapping], keys: Iterable[str] | None = None) -> dict[str, float]:
    """Split-level numbers as ARCTIC reports them.

    ARCTIC concatenates the metric arrays of every sequence (and camera view) and takes one
    nan-mean per metric, i.e. a frame-weighted mean over the split (window-weighted for
    ``mdev/h``) with undefined entries skipped; it does not average per sequence first.

    Args:
        results: one ``{key: array}`` dict or a list of them (per batch or per sequence),
            e.g. from :func:`per_frame_metrics` and :func:`sequence_metrics`.
        keys: metrics to report; default every key seen.

    Returns:
        ``{key: float}``; nan when a metric has no defined entry.
    """
    parts = [results] if isinstance(results, Mapping) else list(results)
    names = list(keys) if keys is not None else list(dict.fromkeys(k for p in parts for k in p))
    out = {}
    for name in names:
        vals = [np.asarray(p[name], dtype=np.float64).reshape(-1) for p in parts if name in p]
        flat = np.concatenate(vals) if vals else np.zeros(0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            out[name] = float(np.nanmean(flat)) if flat.size else float("nan")
    return out
