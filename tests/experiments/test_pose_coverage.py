"""experiments/pose_coverage.py: nearest-hand distances and the held / rest split."""

from __future__ import annotations

import importlib

import numpy as np


def _bench():
    return importlib.import_module("experiments.pose_coverage")


def test_nearest_distance_is_the_mean_joint_distance_to_the_closest():
    pc = _bench()
    rng = np.random.default_rng(0)
    pool = rng.normal(size=(50, 21, 3))
    query = pool[[3, 17]].copy()
    np.testing.assert_allclose(pc.nearest_distance(query, pool, chunk=1), 0.0)
    query[0, 5] += [0.003, 0.0, 0.0]  # one of 21 joints 3 mm off
    assert np.isclose(pc.nearest_distance(query, pool)[0], 3.0 / 21)


def test_openness_and_mean_offset_measure_fingertips_and_the_mean_hand():
    """Openness is the fingertips' (joints 16..20) mean distance from the wrist; the offset is
    zero for the same distribution and the joint-mean distance for a shifted one."""
    pc = _bench()
    hands = np.zeros((2, 21, 3))
    hands[:, 16:21, 0] = [[0.10], [0.12]]  # fingertips 10 and 12 cm from the wrist
    hands[:, 1:16, 1] = 0.5  # other joints do not count
    assert np.isclose(pc.openness(hands), 110.0)
    rng = np.random.default_rng(1)
    pool = rng.normal(scale=0.01, size=(40, 21, 3))
    assert pc.mean_offset(pool, pool[::-1].copy()) < 1e-9
    shifted = pool.copy()
    shifted[:, 20] += [0.0, 0.0, 0.021]  # one of 21 joints 21 mm off
    assert np.isclose(pc.mean_offset(shifted, pool), 1.0)


def test_held_frames_are_where_the_object_has_moved():
    pc = _bench()
    obj = np.zeros((6, 7))
    obj[2:5, 4:7] = [[0.5, 0, 0], [3.0, 0, 0], [0, 0, 2.0]]  # mm
    obj[:, 0] = 0.3  # articulation alone does not count
    assert pc.held_frames(obj).tolist() == [False, False, False, True, True, False]


def test_coverage_of_the_tiny_world(tiny_world):
    pc = _bench()
    rec = pc.coverage(tiny_world / "arctic_data" / "data")
    assert rec["val_frames"] == 64 and 0.0 < rec["held_share"] < 1.0
    assert 0.0 < rec["pool_held_share"]["train"] < 1.0
    assert set(rec["mm"]) == {"train/right", "train/left"}
    for v in rec["mm"].values():
        assert 0.0 < v["rest"] < v["held"] < 50.0  # grasps differ more than hands at rest
    assert "| train | right |" in pc.markdown(rec)
    assert set(rec["shape"]) == {"val/right", "val/left", "train/right", "train/left"}
    assert rec["shape"]["val/right"]["offset"] == 0.0 and rec["shape"]["train/right"]["offset"] > 0.0
    assert all(50.0 < v["openness"] < 250.0 for v in rec["shape"].values())  # fingertips a hand's length away


def test_bank_moves_measure_each_grasp_from_its_source_frame(tiny_world):
    """A bank grasp equal to its source frame's hand moved 0 mm; one with a joint 3 mm off
    moved 3/21 mm; sources index the raw sequence's frames."""
    import torch

    from hogsa_loader.assets.arctic import ArcticRoot

    pc = _bench()
    root = ArcticRoot(tiny_world / "arctic_data" / "data")
    sid, seq = root.protocol("p1")["train"][0].split("/", 1)
    raw = root.raw_sequence(sid, seq)
    layers = root.mano_layers(torch.float64)
    sources = [(sid, seq, 5), (sid, seq, 20)]
    bank = {s: pc.articulated_joints(layers[s], raw.mano[s]["pose"][[5, 20]]) for s in pc.SIDES}
    moved = pc.bank_moves(root, layers, sources, bank)
    assert all(moved[s]["mean"] < 1e-9 for s in pc.SIDES)
    bank["right"][1, 4] += [0.0, 0.003, 0.0]
    moved = pc.bank_moves(root, layers, sources, bank)
    assert np.isclose(moved["right"]["mean"], 3.0 / 21 / 2) and moved["left"]["mean"] < 1e-9
    swapped = pc.bank_moves(root, layers, sources[::-1], {s: bank[s] for s in pc.SIDES})
    assert swapped["left"]["mean"] > 0.1  # another frame's hand is not the source's


def test_source_held_reads_each_source_frames_held_flag(tiny_world):
    """A bank's held share is that of the frames its grasps were made from."""
    from hogsa_loader.assets.arctic import ArcticRoot

    pc = _bench()
    root = ArcticRoot(tiny_world / "arctic_data" / "data")
    sid, seq = root.protocol("p1")["train"][0].split("/", 1)
    held = pc.held_frames(root.raw_sequence(sid, seq).object)
    frames = [int(np.flatnonzero(held)[0]), int(np.flatnonzero(~held)[0]), int(np.flatnonzero(held)[-1])]
    assert pc.source_held(root, [(sid, seq, f) for f in frames]).tolist() == [True, False, True]
