"""ArcticNet-SF loss and ARCTIC metrics on constructed cases with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from hogsa_loader.baselines.loss import ARCTIC_SF_LOSS_WEIGHTS, arcticnet_sf_loss
from hogsa_loader.baselines.metrics import (
    contact_windows,
    motion_deviation,
    per_frame_metrics,
    sequence_metrics,
    summarize,
)

F64 = torch.float64
VH, VMAX, NC = 40, 36, 5  # hand vertices, padded object vertices, contact vertices per hand
EXPECTED_WEIGHTS = {
    "loss/mano/cam_t/r": 1.0,
    "loss/mano/cam_t/l": 1.0,
    "loss/object/cam_t": 1.0,
    "loss/mano/kp2d/r": 5.0,
    "loss/mano/kp3d/r": 5.0,
    "loss/mano/pose/r": 10.0,
    "loss/mano/beta/r": 0.001,
    "loss/mano/kp2d/l": 5.0,
    "loss/mano/kp3d/l": 5.0,
    "loss/mano/pose/l": 10.0,
    "loss/cd": 1.0,
    "loss/mano/transl/l": 1.0,
    "loss/mano/beta/l": 0.001,
    "loss/object/kp2d": 1.0,
    "loss/object/kp3d": 5.0,
    "loss/object/radian": 1.0,
    "loss/object/rot": 1.0,
    "loss/object/transl": 1.0,
}


def _nn(v_hand, v_obj, v_len):
    """Nearest true object vertex of every hand vertex: (B, VH) distances and indices."""
    dist, idx = [], []
    for vh, vo, n in zip(v_hand, v_obj, v_len):
        d = torch.cdist(vh, vo[:n])
        dist.append(d.min(1).values)
        idx.append(d.argmin(1))
    return torch.stack(dist), torch.stack(idx)


def make_sample(B: int = 4, seed: int = 0, contact_offset: float = 1e-3):
    """Ground truth (targets, meta_info) and a prediction equal to it."""
    g = torch.Generator().manual_seed(seed)
    rnd = lambda *s: torch.randn(*s, generator=g, dtype=F64)  # noqa: E731
    v_len = torch.tensor([VMAX, VMAX - 8, VMAX - 4, VMAX - 12][:B] * (B // 4 + 1))[:B]
    vo = rnd(B, VMAX, 3) * 0.05 + torch.tensor([0.0, 0.0, 0.6], dtype=F64)
    part_ids = torch.full((B, VMAX), 2, dtype=torch.long)  # padding labelled 2 on purpose
    for b, n in enumerate(v_len.tolist()):
        vo[b, n:] = 0.0
        part_ids[b, : n // 2] = 1
    t = {"object.v.cam": vo, "object.v_len": v_len}
    for s, off in (("r", 0.1), ("l", -0.1)):
        vh = rnd(B, VH, 3) * 0.02 + torch.tensor([off, 0.0, 0.5], dtype=F64)
        vh[:, :NC] = vo[:, 2 : 2 + NC] + torch.tensor([contact_offset, 0.0, 0.0], dtype=F64)
        t[f"mano.v3d.cam.{s}"] = vh
        t[f"mano.j3d.cam.{s}"] = rnd(B, 21, 3) * 0.03 + torch.tensor([off, 0.0, 0.5], dtype=F64)
        t[f"dist.{s}o"], t[f"idx.{s}o"] = _nn(vh, vo, v_len)
        t[f"mano.pose.{s}"] = rnd(B, 48) * 0.4
        t[f"mano.beta.{s}"] = rnd(B, 10)
        t[f"mano.j2d.norm.{s}"] = rnd(B, 21, 2) * 0.5
        t[f"mano.cam_t.wp.{s}"] = rnd(B, 3)
        t[f"joints_valid_{s}"] = torch.ones(B, 21, dtype=F64)
    t.update(
        {
            "object.kp2d.norm.t": rnd(B, 16, 2),
            "object.kp2d.norm.b": rnd(B, 16, 2),
            "object.kp3d.cam": rnd(B, 32, 3) * 0.1,
            "object.rot": rnd(B, 3),
            "object.radian": rnd(B) * 0.5,
            "object.cam_t.wp": rnd(B, 3),
            "is_valid": torch.ones(B, dtype=F64),
            "right_valid": torch.ones(B, dtype=F64),
            "left_valid": torch.ones(B, dtype=F64),
        }
    )
    diam = torch.stack([torch.cdist(v[:n], v[:n]).max() for v, n in zip(vo, v_len)])
    meta = {"part_ids": part_ids, "diameter": diam}
    return t, meta, gt_prediction(t)


def gt_prediction(t):
    """A prediction that equals the ground truth (rotation matrices via scipy)."""
    p = {}
    for s in "rl":
        for k in ("beta", "j3d.cam", "v3d.cam", "j2d.norm"):
            p[f"mano.{k}.{s}"] = t[f"mano.{k}.{s}"].clone()
        mats = Rotation.from_rotvec(t[f"mano.pose.{s}"].reshape(-1, 3).numpy()).as_matrix()
        p[f"mano.pose.{s}"] = torch.from_numpy(mats).reshape(-1, 16, 3, 3)
        p[f"mano.cam_t.wp.{s}"] = t[f"mano.cam_t.wp.{s}"].clone()
        p[f"mano.cam_t.wp.init.{s}"] = t[f"mano.cam_t.wp.{s}"].clone()
    p["object.kp2d.norm"] = torch.cat((t["object.kp2d.norm.t"], t["object.kp2d.norm.b"]), 1)
    for k in ("kp3d.cam", "rot", "cam_t.wp", "v.cam"):
        p[f"object.{k}"] = t[f"object.{k}"].clone()
    p["object.radian"] = t["object.radian"].reshape(-1, 1).clone()
    p["object.cam_t.wp.init"] = t["object.cam_t.wp"].clone()
    return p


def _gt_contact_mean(t, s, b):
    d = t[f"dist.{s}o"][b]
    return float(d[d <= 3e-3].mean())


# ----------------------------------------------------------------------------- loss


def test_loss_keys_and_weights():
    assert dict(ARCTIC_SF_LOSS_WEIGHTS) == EXPECTED_WEIGHTS
    t, _, p = make_sample()
    out = arcticnet_sf_loss(p, t)
    assert set(out) == set(EXPECTED_WEIGHTS) | {"loss"}
    assert all(v.ndim == 0 for v in out.values())
    torch.testing.assert_close(out["loss"], sum(out[k] for k in EXPECTED_WEIGHTS))


def test_loss_zero_at_ground_truth_except_contact():
    t, _, p = make_sample(contact_offset=1e-3)
    out = arcticnet_sf_loss(p, t)
    for k in EXPECTED_WEIGHTS:
        if k != "loss/cd":
            assert abs(float(out[k])) < 1e-12, k
    # contact vertices sit 1 mm from their object vertex: cd = 1 mm per hand, summed
    assert float(out["loss/cd"]) == pytest.approx(2e-3, rel=1e-9)


def test_loss_terms_match_direct_formulas():
    t, _, p = make_sample(seed=1)
    g = torch.Generator().manual_seed(5)
    for k in p:
        p[k] = p[k] + 0.01 * torch.randn(p[k].shape, generator=g, dtype=F64)
    t["right_valid"] = torch.tensor([1.0, 0.0, 1.0, 1.0], dtype=F64)
    t["joints_valid_r"][0, :7] = 0.0
    out = arcticnet_sf_loss(p, t)
    keep = t["right_valid"].bool()
    gt_rot = torch.from_numpy(Rotation.from_rotvec(t["mano.pose.r"].reshape(-1, 3).numpy()).as_matrix())
    pose = ((p["mano.pose.r"] - gt_rot.reshape(-1, 16, 3, 3)) ** 2)[keep].mean()
    assert float(out["loss/mano/pose/r"]) == pytest.approx(10.0 * float(pose), rel=1e-9)
    kp2d = ((p["mano.j2d.norm.r"] - t["mano.j2d.norm.r"]) ** 2 * t["joints_valid_r"][..., None]).mean()
    assert float(out["loss/mano/kp2d/r"]) == pytest.approx(5.0 * float(kp2d), rel=1e-9)
    cam = sum(((p[k] - t["mano.cam_t.wp.r"]) ** 2)[keep].mean() for k in ("mano.cam_t.wp.r", "mano.cam_t.wp.init.r"))
    assert float(out["loss/mano/cam_t/r"]) == pytest.approx(float(cam), rel=1e-9)
    ra = lambda x: x - x[:, 16:17]  # noqa: E731  object root: first bottom keypoint
    kp3d_o = ((ra(p["object.kp3d.cam"]) - ra(t["object.kp3d.cam"])) ** 2).mean()
    assert float(out["loss/object/kp3d"]) == pytest.approx(5.0 * float(kp3d_o), rel=1e-9)
    d = lambda src: src["object.cam_t.wp"] - src["mano.cam_t.wp.r"]  # noqa: E731
    transl_o = ((d(p) - d(t)) ** 2)[keep].mean()
    assert float(out["loss/object/transl"]) == pytest.approx(float(transl_o), rel=1e-9)
    # contact: per-frame mean over GT contacts, then mean over frames with contact
    cd = []
    for s, valid in (("r", keep), ("l", torch.ones(4, dtype=torch.bool))):
        per = []
        for b in range(4):
            c = t[f"dist.{s}o"][b] <= 3e-3
            if valid[b] and c.any():
                vo = p["object.v.cam"][b, t[f"idx.{s}o"][b][c]]
                per.append((vo - p[f"mano.v3d.cam.{s}"][b][c]).norm(dim=-1).mean())
        cd.append(torch.stack(per).mean())
    assert float(out["loss/cd"]) == pytest.approx(float(sum(cd)), rel=1e-9)


def test_loss_perturbed_positive_finite_and_differentiable():
    t, _, p = make_sample(seed=2)
    g = torch.Generator().manual_seed(3)
    for k in p:
        p[k] = (p[k] + 0.05 * torch.randn(p[k].shape, generator=g, dtype=F64)).requires_grad_(True)
    out = arcticnet_sf_loss(p, t)
    for k, v in out.items():
        assert torch.isfinite(v) and float(v.detach()) > 0, k
    out["loss"].backward()
    for k, v in p.items():
        assert v.grad is not None and torch.isfinite(v.grad).all() and v.grad.abs().sum() > 0, k


def test_loss_all_zero_masks_give_zero_finite_terms():
    t, _, p = make_sample(seed=4)
    for k in ("is_valid", "right_valid", "left_valid"):
        t[k] = torch.zeros_like(t[k])
    for s in "rl":
        t[f"joints_valid_{s}"] = torch.zeros_like(t[f"joints_valid_{s}"])
    p = {k: (v + 0.1).requires_grad_(True) for k, v in p.items()}
    out = arcticnet_sf_loss(p, t)
    for k, v in out.items():
        assert torch.isfinite(v) and float(v.detach()) == 0.0, k
    out["loss"].backward()
    assert all(torch.isfinite(v.grad).all() for v in p.values() if v.grad is not None)


def test_loss_single_invalid_hand_drops_only_its_frames():
    t, _, p = make_sample(seed=6)
    t["left_valid"] = torch.tensor([0.0, 0.0, 0.0, 0.0], dtype=F64)
    p["mano.beta.l"] = p["mano.beta.l"] + 1.0
    p["mano.v3d.cam.l"] = p["mano.v3d.cam.l"] + 1.0
    out = arcticnet_sf_loss(p, t)
    assert float(out["loss/mano/beta/l"]) == 0.0 and float(out["loss/mano/transl/l"]) == 0.0
    assert float(out["loss/cd"]) == pytest.approx(1e-3, rel=1e-9)  # right hand only


# -------------------------------------------------------------------------- metrics


def test_metrics_at_ground_truth():
    t, meta, p = make_sample(contact_offset=0.0)
    m = per_frame_metrics(p, t, meta)
    hands = ("mpjpe/ra/r", "mpjpe/ra/l")
    assert set(m) == {"mpjpe/ra/h", *hands, "mrrpe/r/l", "mrrpe/r/o", "cdev/ho", "aae", "success_rate/0.05"}
    for k in ("mpjpe/ra/h", *hands, "mrrpe/r/l", "mrrpe/r/o", "cdev/ho", "aae"):
        np.testing.assert_allclose(m[k], 0.0, atol=1e-9, err_msg=k)
    np.testing.assert_allclose(m["success_rate/0.05"], 100.0)


def test_cdev_is_the_gt_contact_distance_and_a_known_shift():
    t, meta, p = make_sample(contact_offset=2e-3)
    m = per_frame_metrics(p, t, meta)
    want = [1000 * 0.5 * (_gt_contact_mean(t, "r", b) + _gt_contact_mean(t, "l", b)) for b in range(4)]
    np.testing.assert_allclose(m["cdev/ho"], want, rtol=1e-9)
    np.testing.assert_allclose(m["cdev/ho"], 2.0, rtol=1e-9)
    t, meta, p = make_sample(contact_offset=0.0)
    p["mano.v3d.cam.r"] = p["mano.v3d.cam.r"] + torch.tensor([0.0, 0.004, 0.0], dtype=F64)
    t["left_valid"][:] = 0.0
    np.testing.assert_allclose(per_frame_metrics(p, t, meta)["cdev/ho"], 4.0, rtol=1e-9)


def test_mpjpe_shifted_non_root_joints_right_hand_only():
    t, meta, p = make_sample()
    t["left_valid"] = torch.tensor([0.0, 0.0, 1.0, 1.0], dtype=F64)
    p["mano.j3d.cam.r"][:, 1:, 0] += 0.010
    m = per_frame_metrics(p, t, meta)
    np.testing.assert_allclose(m["mpjpe/ra/h"][:2], 10.0 * 20 / 21, rtol=1e-9)
    np.testing.assert_allclose(m["mpjpe/ra/h"][2:], 0.5 * 10.0 * 20 / 21, rtol=1e-9)


def test_translation_keeps_mpjpe_and_moves_mrrpe():
    t, meta, p = make_sample()
    shift = torch.tensor([0.003, -0.004, 0.012], dtype=F64)  # |shift| = 13 mm
    for k in ("mano.j3d.cam.l", "mano.v3d.cam.l"):
        p[k] = p[k] + shift
    m = per_frame_metrics(p, t, meta)
    np.testing.assert_allclose(m["mpjpe/ra/h"], 0.0, atol=1e-9)
    np.testing.assert_allclose(m["mrrpe/r/l"], 13.0, rtol=1e-9)
    np.testing.assert_allclose(m["mrrpe/r/o"], 0.0, atol=1e-9)
    p["object.v.cam"] = p["object.v.cam"] + torch.tensor([0.0, 0.005, 0.0], dtype=F64)
    m = per_frame_metrics(p, t, meta)
    np.testing.assert_allclose(m["mrrpe/r/o"], 5.0, rtol=1e-9)
    np.testing.assert_allclose(m["success_rate/0.05"], 100.0)


def test_mrrpe_object_root_is_bottom_part_mean():
    t, meta, p = make_sample()
    top = (meta["part_ids"] == 1).to(F64)[..., None]
    p["object.v.cam"] = p["object.v.cam"] + 0.05 * top * torch.tensor([1.0, 0.0, 0.0], dtype=F64)
    np.testing.assert_allclose(per_frame_metrics(p, t, meta)["mrrpe/r/o"], 0.0, atol=1e-9)


def test_aae_degrees_and_validity():
    t, meta, p = make_sample()
    p["object.radian"] = p["object.radian"] + 0.1
    t["is_valid"][1] = 0.0
    m = per_frame_metrics(p, t, meta)
    np.testing.assert_allclose(m["aae"][[0, 2, 3]], 0.1 * 180 / math.pi, rtol=1e-9)
    for k, v in m.items():
        assert np.isnan(v[1]), k


def test_success_rate_fractions():
    t, meta, p = make_sample()
    d = meta["diameter"][:, None, None]
    top = meta["part_ids"] == 1
    ex = torch.tensor([1.0, 0.0, 0.0], dtype=F64)
    p["object.v.cam"] = t["object.v.cam"] + 0.06 * d * top.to(F64)[..., None] * ex
    n_bottom = torch.tensor([(n - n // 2) for n in t["object.v_len"].tolist()], dtype=F64)
    want = 100 * n_bottom / t["object.v_len"].to(F64)
    np.testing.assert_allclose(per_frame_metrics(p, t, meta)["success_rate/0.05"], want.numpy(), rtol=1e-9)
    # bottom vertices pushed +/- alternately: the root stays, every vertex is off by 6%
    sign = torch.zeros_like(meta["part_ids"], dtype=F64)
    for b, n in enumerate(t["object.v_len"].tolist()):
        sign[b, n // 2 : n] = torch.tensor([1.0, -1.0], dtype=F64).repeat(n)[: n - n // 2]
    assert all((n - n // 2) % 2 == 0 for n in t["object.v_len"].tolist())
    p["object.v.cam"] = p["object.v.cam"] + 0.06 * d * sign[..., None] * ex
    np.testing.assert_allclose(per_frame_metrics(p, t, meta)["success_rate/0.05"], 0.0)


def test_hand_validity_rules():
    t, meta, p = make_sample()
    p["mano.j3d.cam.r"][:, 1:] += 0.01
    t["right_valid"] = torch.tensor([0.0, 1.0, 0.0, 1.0], dtype=F64)
    t["left_valid"] = torch.tensor([0.0, 0.0, 1.0, 1.0], dtype=F64)
    m = per_frame_metrics(p, t, meta)
    assert np.isnan(m["mpjpe/ra/h"][0]) and np.isnan(m["cdev/ho"][0])
    assert np.isnan(m["mrrpe/r/l"][[0, 1, 2]]).all() and not np.isnan(m["mrrpe/r/l"][3])
    assert np.isnan(m["mrrpe/r/o"][[0, 2]]).all() and not np.isnan(m["mrrpe/r/o"][[1, 3]]).any()
    assert m["mpjpe/ra/h"][2] == pytest.approx(0.0, abs=1e-9)
    assert not np.isnan(m["aae"]).any() and not np.isnan(m["success_rate/0.05"]).any()


def test_per_frame_metrics_match_direct_loops():
    t, meta, p = make_sample(seed=9)
    g = torch.Generator().manual_seed(10)
    keys = ("mano.j3d.cam.r", "mano.j3d.cam.l", "mano.v3d.cam.r", "mano.v3d.cam.l", "object.v.cam", "object.radian")
    for k in keys:
        p[k] = p[k] + 0.004 * torch.randn(p[k].shape, generator=g, dtype=F64)
    t["left_valid"][2] = 0.0
    m = per_frame_metrics(p, t, meta)
    for b in range(4):
        n = int(t["object.v_len"][b])
        vp, vg = p["object.v.cam"][b, :n].numpy(), t["object.v.cam"][b, :n].numpy()
        bot = meta["part_ids"][b, :n].numpy() == 2
        rp, rg = vp[bot].mean(0), vg[bot].mean(0)
        err = np.linalg.norm((vp - rp) - (vg - rg), axis=1)
        assert m["success_rate/0.05"][b] == pytest.approx(100 * np.mean(err < 0.05 * float(meta["diameter"][b])))
        jr = [p["mano.j3d.cam.r"][b].numpy(), t["mano.j3d.cam.r"][b].numpy()]
        assert m["mrrpe/r/o"][b] == pytest.approx(1000 * np.linalg.norm((rp - jr[0][0]) - (rg - jr[1][0])))
        hands = ["r"] + (["l"] if b != 2 else [])
        ra = {s: [src[f"mano.j3d.cam.{s}"][b].numpy() for src in (p, t)] for s in hands}
        mp = [np.linalg.norm((jp - jp[0]) - (jg - jg[0]), axis=1).mean() for jp, jg in ra.values()]
        assert m["mpjpe/ra/h"][b] == pytest.approx(1000 * np.mean(mp))
        assert m["mpjpe/ra/r"][b] == pytest.approx(1000 * mp[0])
        assert (m["mpjpe/ra/l"][b] == pytest.approx(1000 * mp[1])) if b != 2 else np.isnan(m["mpjpe/ra/l"][b])
        cd = []
        for s in hands:
            c = (t[f"dist.{s}o"][b] <= 3e-3).numpy()
            vo = p["object.v.cam"][b].numpy()[t[f"idx.{s}o"][b].numpy()[c]]
            cd.append(np.linalg.norm(vo - p[f"mano.v3d.cam.{s}"][b].numpy()[c], axis=1).mean())
        assert m["cdev/ho"][b] == pytest.approx(1000 * np.mean(cd))
        da = abs(float(p["object.radian"][b, 0] - t["object.radian"][b]))
        assert m["aae"][b] == pytest.approx(np.degrees(da))
    assert np.isnan(m["mrrpe/r/l"][2])


# ------------------------------------------------------------------------- temporal


def make_sequence(N: int = 40):
    """N frames of one object with no contact, and a prediction equal to it."""
    t, meta, _ = make_sample(B=1, seed=11)
    t = {k: v.expand(N, *v.shape[1:]).clone() if torch.is_tensor(v) else v for k, v in t.items()}
    meta = {k: v.expand(N, *v.shape[1:]).clone() for k, v in meta.items()}
    for s in "rl":
        t[f"dist.{s}o"] = torch.full((N, VH), 0.05, dtype=F64)
    return t, meta, gt_prediction(t)


def test_acc_zero_at_gt_and_for_constant_velocity_error():
    t, meta, p = make_sequence()
    out = sequence_metrics(p, t, meta)
    assert out["acc/h"].shape == (40,) and out["acc/o"].shape == (40,)
    assert np.isnan(out["acc/h"][[0, -1]]).all() and np.isnan(out["acc/o"][[0, -1]]).all()
    np.testing.assert_allclose(out["acc/h"][1:-1], 0.0, atol=1e-9)
    np.testing.assert_allclose(out["acc/o"][1:-1], 0.0, atol=1e-9)
    frames = torch.arange(40, dtype=F64)[:, None, None]
    p["mano.v3d.cam.r"] = p["mano.v3d.cam.r"] + 0.002 * frames * torch.tensor([1.0, 2.0, 0.0], dtype=F64)
    np.testing.assert_allclose(sequence_metrics(p, t, meta)["acc/h"][1:-1], 0.0, atol=1e-6)


def test_acc_known_acceleration_and_validity():
    t, meta, p = make_sequence()
    a = 2.0  # m/s^2 along z
    tt = torch.arange(40, dtype=F64)[:, None, None] / 30.0
    off = 0.5 * a * tt**2 * torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    p["mano.v3d.cam.r"] = p["mano.v3d.cam.r"] + off  # joints (and so the root) unchanged
    top = (meta["part_ids"][0] == 1).to(F64)[None, :, None]
    p["object.v.cam"] = p["object.v.cam"] + off * top
    t["left_valid"][10] = 0.0
    t["is_valid"][30] = 0.0
    out = sequence_metrics(p, t, meta)
    n = int(t["object.v_len"][0])
    want_o = a * (n // 2) / n
    acc_h, acc_o = out["acc/h"], out["acc/o"]
    np.testing.assert_allclose(acc_h[[5, 20]], a / 2, rtol=1e-6)  # right = a, left = 0
    np.testing.assert_allclose(acc_h[[9, 10, 11]], a, rtol=1e-6)  # left not usable there
    assert np.isnan(acc_h[[29, 30, 31]]).all() and np.isnan(acc_o[[29, 30, 31]]).all()
    np.testing.assert_allclose(acc_o[[5, 28, 32]], want_o, rtol=1e-6)


def _contact_sequence():
    """Right vertex 0 touches object vertex 3 in frames 5..24; decoys that do not count."""
    t, meta, p = make_sequence()
    d = t["dist.ro"]
    d[5:25, 0] = 1e-3  # a 20-frame window
    d[10:21, 1] = 1e-3  # 11 frames: too short
    d[25:40, 2] = 1e-3  # still in contact at the last frame: never closed
    d[0:20, 4] = 1e-3  # matched object vertices slide across the object
    t["idx.ro"] = torch.full((40, VH), 3, dtype=torch.long)
    t["idx.ro"][0:20, 4] = torch.arange(20) % 2 * 7  # alternating between vertex 0 and vertex 7
    return t, meta, p


def test_contact_windows_follow_arctic_rules():
    t, meta, _ = _contact_sequence()
    v_ref = t["object.v.cam"][0]
    assert float((v_ref[0] - v_ref[7]).norm()) > 3e-3
    assert contact_windows(t["dist.ro"], t["idx.ro"], v_ref) == [(5, 24, 0, 3)]


def test_mdev_known_relative_motion():
    t, meta, p = _contact_sequence()
    np.testing.assert_allclose(sequence_metrics(p, t, meta)["mdev/h"], [0.0], atol=1e-12)
    frames = torch.arange(40, dtype=F64)[:, None, None]
    move = 0.001 * frames * torch.tensor([3.0, 4.0, 0.0], dtype=F64)  # 5 mm per frame
    p["mano.v3d.cam.r"] = p["mano.v3d.cam.r"] + move
    p["object.v.cam"] = p["object.v.cam"] + 0.4 * move  # common motion does not count
    np.testing.assert_allclose(sequence_metrics(p, t, meta)["mdev/h"], [3.0], rtol=1e-9)
    # steps touching an invalid frame are skipped; direct computation for an uneven motion
    wobble = 0.001 * (frames**2) * torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    p["mano.v3d.cam.r"] = t["mano.v3d.cam.r"] + wobble
    p["object.v.cam"] = t["object.v.cam"].clone()
    valid = torch.ones(40, dtype=torch.bool)
    valid[12] = False
    got = motion_deviation([(5, 24, 0, 3)], p["mano.v3d.cam.r"], p["object.v.cam"], valid)
    steps = [k for k in range(5, 24) if k not in (11, 12)]
    want = np.mean([0.001 * ((k + 1) ** 2 - k**2) for k in steps])
    assert float(got[0]) == pytest.approx(want, rel=1e-9)


def test_summarize_pools_frames_across_sequences():
    seqs = [
        {"mpjpe/ra/h": np.array([1.0, 1.0, 1.0, np.nan]), "mdev/h": np.zeros(0)},
        {"mpjpe/ra/h": np.array([4.0]), "mdev/h": np.array([2.0, 4.0])},
    ]
    out = summarize(seqs)
    assert out["mpjpe/ra/h"] == pytest.approx(1.75)  # not the per-sequence mean 2.5
    assert out["mdev/h"] == pytest.approx(3.0)
    assert math.isnan(summarize({"aae": np.array([np.nan])})["aae"])
    t, meta, p = make_sample()
    assert summarize([per_frame_metrics(p, t, meta)])["success_rate/0.05"] == pytest.approx(100.0)
