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

from hogsa_loader.datasets.arctic_dataset import parse_imgname

__all__ = ["ClipSums", "clip_sums", "clip_uncertainty"]

#: ``{"subject/sequence/view": {metric: [sum, count]}}``
ClipSums = dict[str, dict[str, list[float]]]


def clip_sums(ev: Mapping[str, Any], keys: Iterable[str]) -> ClipSums:
    """Per clip of an evaluation: the sum and count of each per-frame metric's defined entries.

    Args:
        ev: ``per_frame`` (``{metric: (N,) array}``) and ``imgnames`` (N ARCTIC image names),
            as :func:`~hogsa_loader.baselines.engine.evaluate` returns them.
        keys: per-frame metrics to keep (e.g. ``"mpjpe/ra/h"``, ``"cdev/ho"``).

    Returns:
        ``{"subject/sequence/view": {metric: [sum, count]}}`` in order of first frame; the
        sum of ``sum`` over clips divided by the sum of ``count`` is the split-level value
        (ARCTIC's frame-weighted nan-mean).
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


def _arrays(pairs: Sequence[tuple[ClipSums, ClipSums]], metric: str, clips: list[str]) -> np.ndarray:
    """(2, 2, S, C): [model, reference] × [sum, count] per seed and clip."""
    return np.array(
        [[[[run[c][metric][i] for c in clips] for run in side] for i in (0, 1)] for side in zip(*pairs)],
        dtype=np.float64,
    )


def _paired_means(arrays: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Seed-mean paired difference for each row of clip ``weights`` (R, C) → (R,)."""
    means = [(weights @ arrays[k, 0].T) / np.maximum(weights @ arrays[k, 1].T, 1e-12) for k in (0, 1)]
    return (means[0] - means[1]).mean(axis=1)


def clip_uncertainty(
    pairs: Sequence[tuple[Optional[ClipSums], Optional[ClipSums]]], metric: str, resamples: int = 2000, seed: int = 0
) -> Optional[dict[str, Any]]:
    """How much a seed-averaged paired difference depends on which clips were drawn.

    The clips are resampled with replacement ``resamples`` times (a generator seeded with
    ``seed``), each run's metric formed again frame-weighted over the drawn clips and the
    paired difference (model − reference) averaged over seeds: its 2.5th and 97.5th
    percentiles are a 95 % interval. Leaving out each clip in turn shows whether one clip
    carries the difference.

    Args:
        pairs: per seed, the :func:`clip_sums` of (model, reference).
        metric: a metric both hold.
        resamples: number of resamples.
        seed: seed of the resampling.

    Returns:
        ``{"clips": C, "estimate": d, "ci95": [lo, hi], "leave_one_out": {"min": [value,
        clip], "max": [value, clip]}}`` (``estimate``: the difference over every clip;
        ``leave_one_out`` only with C > 1); None when a run lacks its clips or the runs
        differ in clips.
    """
    if not pairs or any(a is None or r is None for a, r in pairs):
        return None
    clips = sorted(pairs[0][0])  # type: ignore[arg-type]
    if any(sorted(a) != clips or sorted(r) != clips for a, r in pairs):  # type: ignore[arg-type]
        return None
    arrays = _arrays(pairs, metric, clips)  # type: ignore[arg-type]
    n = len(clips)
    draws = np.random.default_rng(seed).multinomial(n, np.full(n, 1.0 / n), size=resamples).astype(np.float64)
    boot = _paired_means(arrays, draws)
    rec: dict[str, Any] = {
        "clips": n,
        "estimate": float(_paired_means(arrays, np.ones((1, n)))[0]),
        "ci95": [float(np.percentile(boot, 2.5)), float(np.percentile(boot, 97.5))],
    }
    if n > 1:
        loo = _paired_means(arrays, 1.0 - np.eye(n))
        lo, hi = int(np.argmin(loo)), int(np.argmax(loo))
        rec["leave_one_out"] = {"min": [float(loo[lo]), clips[lo]], "max": [float(loo[hi]), clips[hi]]}
    return rec
