"""Interaction-field targets (InterField-SF): definition, padding, clamp, real-dataset wiring."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.assets.conventions import transform
from hogsa_loader.sample.arctic_dataset import ArcticDataset
from hogsa_loader.sample.interfield import INTERFIELD_KEYS, interaction_field


def _brute(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = np.sqrt(((a[:, None, :] - b[None, :, :]) ** 2).sum(-1))
    return d.min(1), d.argmin(1)


def test_interaction_field_matches_brute_force_with_padding_and_clamp():
    rng = np.random.default_rng(0)
    r, l, o = rng.normal(size=(50, 3)) * 0.05, rng.normal(size=(40, 3)) * 0.05 + 0.1, rng.normal(size=(30, 3)) * 0.05
    f = interaction_field(r, l, o, v_max=36)
    assert list(f) == list(INTERFIELD_KEYS) and f["object.v_len"] == 30
    for key, (a, b) in {"ro": (r, o), "lo": (l, o), "or": (o, r), "ol": (o, l)}.items():
        d, i = _brute(a, b)
        n = len(a)
        np.testing.assert_allclose(f[f"dist.{key}"][:n], d, rtol=1e-6, atol=1e-7)
        np.testing.assert_array_equal(f[f"idx.{key}"][:n], i)
        assert f[f"dist.{key}"].dtype == np.float32 and f[f"idx.{key}"].dtype == np.int64
    assert f["dist.ro"].shape == (50,) and f["dist.or"].shape == (36,)
    assert (f["dist.or"][30:] == 0).all() and (f["idx.ol"][30:] == 0).all()
    clamped = interaction_field(r, l, o, v_max=30, max_dist=0.05)
    assert clamped["dist.lo"].max() <= 0.05 + 1e-7
    np.testing.assert_allclose(clamped["dist.ro"], np.minimum(f["dist.ro"], 0.05), rtol=1e-6)
    with pytest.raises(ValueError, match="more than the padded length"):
        interaction_field(r, l, o, v_max=10)


def test_real_dataset_interfield_uses_the_frames_meshes(tiny_world):
    """The field is computed from the item's own GT frame: the hand joints of the same
    parameters, moved into the view's camera, are the sample's ``mano.j3d.full.r``; a
    grasping frame has a hand within a few millimetres of the object."""
    ds = ArcticDataset(tiny_world, split="p1_train", augment=False, interfield=True)
    plain = ArcticDataset(tiny_world, split="p1_train", augment=False)
    root = ArcticRoot(tiny_world)
    layers = root.mano_layers(torch.float64)
    n_hand = int(layers["right"].num_verts)  # from the model, never hard-coded
    v_max = int(root.object_layer().v_len.max())
    closest = math.inf
    for index in np.linspace(0, len(ds) - 1, 12).round().astype(int):
        inputs, targets, meta = ds[int(index)]
        base = plain[int(index)][1]
        assert list(targets)[: len(base)] == list(base) and list(targets)[len(base) :] == list(INTERFIELD_KEYS)
        assert targets["dist.ro"].shape == (n_hand,) and targets["idx.lo"].shape == (n_hand,)
        assert targets["dist.or"].shape == (v_max,)
        sid, seq, view, vidx, seq_data = ds._locate(ds.imgnames[int(index)])
        p = ds._world_poses(seq_data["params"], vidx)
        j = layers["right"](
            global_orient=torch.as_tensor(p["right_rot"]),
            hand_pose=torch.as_tensor(p["right_pose"]),
            betas=torch.as_tensor(p["right_betas"]),
            transl=torch.as_tensor(p["right_trans"]),
        ).joints
        w2c = np.asarray(root.subject_misc(sid).world2cam[view - 1]) if view > 0 else None
        if w2c is not None:
            np.testing.assert_allclose(transform(w2c, j[0].numpy()), np.asarray(targets["mano.j3d.full.r"]), atol=1e-4)
        if targets["is_valid"] > 0:
            closest = min(closest, float(targets["dist.ro"].min()), float(targets["dist.lo"].min()))
    assert closest < 0.01  # the world's grasps touch the object
