"""Metrics per validation clip and the uncertainty of paired differences over clips."""

from __future__ import annotations

import numpy as np
import pytest

from hogsa_loader.baselines.clips import clip_mean, clip_sums, clip_uncertainty, interval_text, left_out_text


def test_clip_sums_form_the_split_value_of_any_set_of_clips():
    names = [
        f"./data/arctic_data/data/cropped_images/s05/box_use_01/{v}/{f:05d}.jpg" for v in (1, 2) for f in (10, 11, 12)
    ]
    ev = {
        "imgnames": names,
        "per_frame": {
            "mpjpe/ra/h": np.array([10.0, np.nan, 20.0, 40.0, 50.0, 60.0]),
            "cdev/ho": np.array([np.nan, np.nan, np.nan, 1.0, 2.0, 3.0]),
        },
    }
    sums = clip_sums(ev, ["mpjpe/ra/h", "cdev/ho"])
    assert list(sums) == ["s05/box_use_01/1", "s05/box_use_01/2"]
    assert sums["s05/box_use_01/1"] == {"mpjpe/ra/h": [30.0, 2.0], "cdev/ho": [0.0, 0.0]}  # nan entries skipped
    assert sums["s05/box_use_01/2"] == {"mpjpe/ra/h": [150.0, 3.0], "cdev/ho": [6.0, 3.0]}
    total = sum(c["mpjpe/ra/h"][0] for c in sums.values()) / sum(c["mpjpe/ra/h"][1] for c in sums.values())
    assert total == pytest.approx(np.nanmean(ev["per_frame"]["mpjpe/ra/h"]))


def _clips(per_clip: dict[str, tuple[float, int]]) -> dict:
    """Clip sums of a run whose every frame of a clip has the same value."""
    return {c: {"mpjpe/ra/h": [v * n, float(n)]} for c, (v, n) in per_clip.items()}


def test_clip_uncertainty_names_the_clip_that_carries_a_difference():
    """A paired difference made by one clip: leaving that clip out removes it, and the interval
    over resampled clips reaches from no difference (draws without it) to most of its own."""
    names = [f"s05/laptop_grab_01/{v}" for v in range(4)]
    ref = _clips({c: (40.0, 10) for c in names})
    arm = _clips({c: (60.0 if c.endswith("/1") else 40.0, 10) for c in names})  # +20 mm on one clip
    rec = clip_uncertainty([(arm, ref), (arm, ref)], "mpjpe/ra/h")
    assert rec["clips"] == 4 and rec["estimate"] == pytest.approx(5.0)  # 20 mm × 10 of 40 frames
    assert rec["leave_one_out"]["min"] == [pytest.approx(0.0), "s05/laptop_grab_01/1"]
    assert rec["leave_one_out"]["max"][0] == pytest.approx(20.0 / 3)  # 20 mm × 10 of 30 frames
    lo, hi = rec["ci95"]
    assert lo == pytest.approx(0.0) and 10.0 <= hi <= 20.0
    assert clip_uncertainty([(arm, ref)], "mpjpe/ra/h") == clip_uncertainty([(arm, ref)], "mpjpe/ra/h")  # fixed draws
    many = {f"a/s/{k}": (float(k * k), 10) for k in range(20)}
    flat = {c: (0.0, 10) for c in many}
    a, b = (clip_uncertainty([(_clips(many), _clips(flat))], "mpjpe/ra/h", seed=k)["ci95"] for k in (0, 1))
    assert a != b  # the seed draws other resamples


def test_clip_uncertainty_averages_seeds_and_weighs_frames():
    """Seeds are averaged after each is formed frame-weighted: a clip with more frames weighs more."""
    ref = _clips({"a/s/1": (10.0, 30), "a/s/2": (10.0, 10)})
    one = _clips({"a/s/1": (12.0, 30), "a/s/2": (30.0, 10)})  # (12·30 + 30·10) / 40 = 16.5 → +6.5
    two = _clips({"a/s/1": (10.0, 30), "a/s/2": (10.0, 10)})  # +0
    rec = clip_uncertainty([(one, ref), (two, ref)], "mpjpe/ra/h")
    assert rec["estimate"] == pytest.approx(6.5 / 2)
    assert rec["leave_one_out"]["min"] == [pytest.approx(1.0), "a/s/2"]  # only clip 1 left: +2 and +0
    assert rec["leave_one_out"]["max"] == [pytest.approx(10.0), "a/s/1"]  # only clip 2 left: +20 and +0


def test_clip_uncertainty_needs_the_same_clips_in_every_run():
    a = _clips({"a/s/1": (1.0, 1)})
    assert clip_uncertainty([(a, None)], "mpjpe/ra/h") is None
    assert clip_uncertainty([(a, _clips({"b/s/1": (1.0, 1)}))], "mpjpe/ra/h") is None
    assert clip_uncertainty([], "mpjpe/ra/h") is None
    one = clip_uncertainty([(a, _clips({"a/s/1": (3.0, 1)}))], "mpjpe/ra/h")
    assert one["estimate"] == pytest.approx(-2.0) and "leave_one_out" not in one and one["ci95"] == [-2.0, -2.0]


def test_clips_without_defined_entries_are_skipped_not_counted_as_no_difference():
    """CDev is undefined in frames without contact: a draw of such clips only, or leaving out the
    only clip with contact, says nothing about the difference, and is left out."""
    ref = {c: {"cdev/ho": [10.0 * n, float(n)]} for c, n in (("a/s/1", 10), ("a/s/2", 0), ("a/s/3", 0))}
    arm = {c: {"cdev/ho": [12.0 * n, float(n)]} for c, n in (("a/s/1", 10), ("a/s/2", 0), ("a/s/3", 0))}
    rec = clip_uncertainty([(arm, ref)], "cdev/ho")
    assert rec["estimate"] == pytest.approx(2.0) and rec["ci95"] == [pytest.approx(2.0), pytest.approx(2.0)]
    assert rec["leave_one_out"]["min"][0] == pytest.approx(2.0)  # leaving out a/s/1 is undefined, not 0
    assert clip_uncertainty([(_clips({"a/s/2": (0.0, 0)}), _clips({"a/s/2": (0.0, 0)}))], "mpjpe/ra/h") is None


def test_clip_mean_and_the_table_cells():
    clips = {"a/s/1": {"m": [30.0, 3.0]}, "a/s/2": {"m": [10.0, 1.0]}, "a/s/3": {"m": [0.0, 0.0]}}
    assert clip_mean(clips, "m") == pytest.approx(10.0) and clip_mean({"a/s/3": {"m": [0.0, 0.0]}}, "m") is None
    rec = {"ci95": [-1.234, 0.5], "leave_one_out": {"min": [-2.0, "a/s/1"], "max": [0.25, "a/s/2"]}}
    assert interval_text(rec) == "[-1.23, +0.50]" and interval_text(None) == "n/a"
    assert left_out_text(rec) == "-2.00 (without a/s/1) … +0.25 (without a/s/2)"
    assert left_out_text({"ci95": [0.0, 0.0]}) == "n/a"


def test_an_interval_needs_a_defined_draw():
    """Only one clip of twenty has an entry: most resamples miss it and are dropped; with three
    resamples none may be left, and the interval is then None, not an error."""
    names = [f"a/s/{k}" for k in range(20)]
    ref = {c: {"m": [10.0, 1.0] if c == "a/s/0" else [0.0, 0.0]} for c in names}
    arm = {c: {"m": [12.0, 1.0] if c == "a/s/0" else [0.0, 0.0]} for c in names}
    recs = [clip_uncertainty([(arm, ref)], "m", resamples=3, seed=k) for k in range(20)]
    assert all(r["estimate"] == pytest.approx(2.0) and r["draws"] <= 3 for r in recs)
    empty = [r for r in recs if r["draws"] == 0]
    assert empty and all(r["ci95"] is None and interval_text(r) == "n/a" for r in empty)
