"""Metrics per validation clip and how much a paired difference depends on the clips drawn.

A clip is the frames of one (subject, sequence, camera view). Frames of a clip are strongly
correlated, so a small held-out split holds few independent units: a difference between two
models can come from one clip where one of them fails. :func:`clip_sums` keeps, per clip, what
forms a split-level value again (sum and count of each metric's defined per-frame entries);
:func:`clip_uncertainty` resamples the clips to give an interval for a seed-averaged paired
difference and leaves each clip out in turn.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any, Optional

import numpy as np

from hogsa_loader.sample.arctic_dataset import parse_imgname

__all__ = ["CLIP_METRICS", "ClipSums", "clip_mean", "clip_sums", "clip_uncertainty", "interval_text", "left_out_text"]

#: The metrics kept per clip by the benchmarks: ARCTIC's MPJPE_h and CDev_ho.
CLIP_METRICS = ("mpjpe/ra/h", "cdev/ho")

#: ``{"subject/sequence/view": {metric: [sum, count]}}``
ClipSums = dict[str, dict[str, list[float]]]


def clip_sums(ev: Mapping[str, Any], keys: Iterable[str]) -> ClipSums:
    """Per clip of an evaluation: the sum and count of each per-frame metric's defined entries.

    Args:
        ev: ``per_frame`` (``{metric: (N,) array}``) and ``imgnames`` (N ARCTIC image names),
            as :func:`~hogsa_loader.baselines.engine.evaluate` returns them.
        keys: per-frame metrics to keep (e.g. ``"mpjpe/ra/h"``, ``"cdev/ho"``).

    Returns:
        ``{"subject/sequence/view": {metric: [sum, count]}}`` in order of first frame
        (non-finite entries left out); the sum of ``sum`` over clips divided by the sum of
        ``count`` is the split-level value (ARCTIC's frame-weighted nan-mean) wherever that is
        finite.
    """
    clips = np.array(["/".join(str(x) for x in parse_imgname(n)[:3]) for n in ev["imgnames"]])
    out: ClipSums = {}
    for clip in dict.fromkeys(clips.tolist()):
        rows = clips == clip
        out[clip] = {}
        for k in keys:
            v = np.asarray(ev["per_frame"][k], dtype=np.float64)[rows]
            v = v[np.isfinite(v)]
            out[clip][k] = [float(v.sum()), float(v.size)]
    return out


def clip_mean(clips: ClipSums, metric: str) -> Optional[float]:
    """The frame-weighted value of ``metric`` over every clip of ``clips`` (None without a
    defined entry)."""
    count = sum(c[metric][1] for c in clips.values())
    return sum(c[metric][0] for c in clips.values()) / count if count else None


def _arrays(pairs: Sequence[tuple[ClipSums, ClipSums]], metric: str, clips: list[str]) -> np.ndarray:
    """(2, 2, S, C): [model, reference] × [sum, count] per seed and clip."""
    return np.array(
        [[[[run[c][metric][i] for c in clips] for run in side] for i in (0, 1)] for side in zip(*pairs)],
        dtype=np.float64,
    )


def _paired_means(arrays: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Seed-mean paired difference for each row of clip ``weights`` (R, C) → (R,); nan for a
    row whose drawn clips hold no defined entry in some run."""
    means = []
    for k in (0, 1):
        total, count = weights @ arrays[k, 0].T, weights @ arrays[k, 1].T  # (R, S)
        means.append(np.divide(total, count, out=np.full_like(total, np.nan), where=count > 0))
    return (means[0] - means[1]).mean(axis=1)


def clip_uncertainty(
    pairs: Sequence[tuple[Optional[ClipSums], Optional[ClipSums]]], metric: str, resamples: int = 2000, seed: int = 0
) -> Optional[dict[str, Any]]:
    """How much a seed-averaged paired difference depends on which clips were drawn.

    The clips are resampled with replacement ``resamples`` times (a generator seeded with
    ``seed``), each run's metric formed again frame-weighted over the drawn clips and the
    paired difference (model − reference) averaged over seeds: its 2.5th and 97.5th
    percentiles are a 95 % interval. Leaving out each clip in turn shows whether one clip
    carries the difference. Draws (and clips left out) after which a run has no defined
    entry are skipped, not counted as no difference.

    Args:
        pairs: per seed, the :func:`clip_sums` of (model, reference).
        metric: a metric both hold.
        resamples: number of resamples.
        seed: seed of the resampling.

    Returns:
        ``{"clips": C, "estimate": d, "draws": k, "ci95": [lo, hi], "leave_one_out": {"min":
        [value, clip], "max": [value, clip]}}`` (``estimate``: the difference over every clip;
        ``draws``: the resamples with a defined difference, ``ci95`` None without one;
        ``leave_one_out`` only when some clip can be left out); None when a run lacks its
        clips, the runs differ in clips or a run has no defined entry at all.
    """
    runs = [(a, r) for a, r in pairs if a is not None and r is not None]
    if not runs or len(runs) != len(pairs):
        return None
    clips = sorted(runs[0][0])
    if any(sorted(a) != clips or sorted(r) != clips for a, r in runs):
        return None
    arrays = _arrays(runs, metric, clips)
    n = len(clips)
    estimate = float(_paired_means(arrays, np.ones((1, n)))[0])
    if not np.isfinite(estimate):
        return None
    draws = np.random.default_rng(seed).multinomial(n, np.full(n, 1.0 / n), size=resamples).astype(np.float64)
    boot = _paired_means(arrays, draws)
    boot = boot[np.isfinite(boot)]
    rec: dict[str, Any] = {
        "clips": n,
        "estimate": estimate,
        "draws": int(boot.size),
        "ci95": [float(np.percentile(boot, 2.5)), float(np.percentile(boot, 97.5))] if boot.size else None,
    }
    loo = _paired_means(arrays, 1.0 - np.eye(n)) if n > 1 else np.full(0, np.nan)
    if np.isfinite(loo).any():
        lo, hi = int(np.nanargmin(loo)), int(np.nanargmax(loo))
        rec["leave_one_out"] = {"min": [float(loo[lo]), clips[lo]], "max": [float(loo[hi]), clips[hi]]}
    return rec


def interval_text(rec: Optional[dict[str, Any]]) -> str:
    """``[lo, hi]`` of a :func:`clip_uncertainty` record, signed, in its unit ("n/a" without one)."""
    if rec is None or rec.get("ci95") is None:
        return "n/a"
    return f"[{rec['ci95'][0]:+.2f}, {rec['ci95'][1]:+.2f}]"


def left_out_text(rec: Optional[dict[str, Any]]) -> str:
    """The leave-one-out range of a :func:`clip_uncertainty` record with the clips that give its
    ends ("n/a" without one)."""
    loo = (rec or {}).get("leave_one_out")
    if not loo:
        return "n/a"
    return f"{loo['min'][0]:+.2f} (without {loo['min'][1]}) … {loo['max'][0]:+.2f} (without {loo['max'][1]})"
