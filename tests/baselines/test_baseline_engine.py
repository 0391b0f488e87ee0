"""ArcticNet-SF training steps on real and mixed real + synthetic batches, and evaluation."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader, Subset

from hogsa_loader.baselines import (
    ARCTIC_SF_LOSS_WEIGHTS,
    ArcticNetSF,
    BodyLayers,
    evaluate,
    mean_cameras,
    per_frame_metrics,
    prepare_targets,
    temporal_order,
    training_step,
)
from hogsa_loader.sample import is_synthetic
from hogsa_loader.sample.arctic_dataset import ArcticDataset, parse_imgname
from hogsa_loader.sample.augment import ArcticConfig

RES = 64
CFG = ArcticConfig(img_res=RES)

pytestmark = pytest.mark.usefixtures("one_thread")


def _model(layers: BodyLayers) -> ArcticNetSF:
    torch.manual_seed(0)
    return ArcticNetSF("resnet18", layers.mano_r, layers.mano_l, layers.objects, img_res=RES)


def test_training_step_on_real_and_mixed_batches(batches, layers):
    real, mixed = batches
    assert sum(is_synthetic(n) for n in mixed[2]["imgname"]) == 2
    for batch in (real, mixed):
        model = _model(layers)
        before = model.head_r.hmr_layer.refine[0].weight.detach().clone()
        opt = torch.optim.Adam(model.parameters(), lr=1e-4)
        rec = training_step(model, batch, layers, opt, RES)
        assert set(rec) == set(ARCTIC_SF_LOSS_WEIGHTS) | {"loss"}
        assert all(np.isfinite(v) for v in rec.values()) and rec["loss"] > 0
        assert rec["loss"] == pytest.approx(sum(v for k, v in rec.items() if k != "loss"), rel=1e-5)
        assert not torch.equal(before, model.head_r.hmr_layer.refine[0].weight)


def test_training_fits_a_fixed_batch(batches, layers):
    """From the camera prior (as every fine-tuning starts), 12 Adam steps on one batch lower the
    loss steadily. From a random camera the loss is dominated by metre-scale translations and
    swings between 90 and 350 from step to step, so that start is no test of fitting."""
    real, _ = batches
    model = _model(layers)
    model.init_cameras(mean_cameras([real], layers, RES))
    opt = torch.optim.Adam(model.parameters(), lr=3e-4)
    losses = [training_step(model, real, layers, opt, RES)["loss"] for _ in range(12)]
    assert np.mean(losses[-3:]) < 0.7 * np.mean(losses[:3])
    assert all(b < a for a, b in zip(losses[2:], losses[3:]))  # steady from the third step on


def test_mean_cameras_are_the_mean_over_valid_frames(batches, layers):
    real, _ = batches
    inputs, targets, meta = real
    # frame 0 loses its right hand: it must not count in the right prior
    targets = dict(targets, right_valid=targets["right_valid"].clone())
    targets["right_valid"][0] = 0

    def part(d: dict, i: int) -> dict:
        return {k: v[i : i + 2] if torch.is_tensor(v) else v for k, v in d.items()}

    halves = [(part(inputs, i), part(targets, i), {k: v[i : i + 2] for k, v in meta.items()}) for i in (0, 2)]
    prior = mean_cameras(halves, layers, RES)
    full, _ = prepare_targets(
        dict(targets), dict(meta), layers.mano_r, layers.mano_l, layers.objects, img_res=RES, field="hands"
    )
    for side, cam, valid in (
        ("r", "mano.cam_t.wp.r", "right_valid"),
        ("l", "mano.cam_t.wp.l", "left_valid"),
        ("o", "object.cam_t.wp", "is_valid"),
    ):
        ok = full[valid].reshape(-1).bool()
        assert ok.sum() == (3 if side == "r" else 4)
        torch.testing.assert_close(prior[side], full[cam][ok].mean(0), atol=1e-5, rtol=1e-5)
    assert (prior["r"] != full["mano.cam_t.wp.r"].mean(0)).any()  # frame 0 really left out
    none = (inputs, dict(targets, is_valid=torch.zeros_like(targets["is_valid"])), meta)
    with pytest.raises(ValueError, match=r"no valid frame for \['o'\]"):
        mean_cameras([none], layers, RES)


def test_camera_prior_starts_every_head_at_the_prior(batches, layers):
    """A random head starts near s = 0, under the clamp s >= 0.1 (translations of metres, the
    contact loss at its largest); init_cameras puts every image's initial camera at the prior."""
    real, _ = batches
    prior = mean_cameras([real], layers, RES)
    model = _model(layers).eval()
    with torch.no_grad():
        before = model(real[0], real[2])
        model.init_cameras(prior)
        after = model(real[0], real[2])
    for side, key in (("r", "mano.cam_t.wp.init.r"), ("l", "mano.cam_t.wp.init.l"), ("o", "object.cam_t.wp.init")):
        assert before[key][:, 0].abs().max() < 0.5 < prior[side][0]
        torch.testing.assert_close(
            after[key], prior[side].expand_as(after[key]), atol=0.05 * float(prior[side][0]), rtol=0
        )
    model.train()
    targets, _ = prepare_targets(
        dict(real[1]), dict(real[2]), layers.mano_r, layers.mano_l, layers.objects, img_res=RES, field="hands"
    )
    from hogsa_loader.baselines import arcticnet_sf_loss

    fresh = _model(layers).train()
    torch.manual_seed(1)
    cd_before = arcticnet_sf_loss(fresh(real[0], real[2]), targets)["loss/cd"]
    torch.manual_seed(1)
    cd_after = arcticnet_sf_loss(model(real[0], real[2]), targets)["loss/cd"]
    assert cd_after < 0.1 * cd_before
    with pytest.raises(ValueError, match="priors for heads"):
        model.init_cameras({"r": prior["r"], "l": prior["l"]})
    with pytest.raises(ValueError, match="3 finite numbers"):
        model.init_cameras(dict(prior, o=torch.tensor([float("nan"), 0.0, 0.0])))


def test_non_finite_loss_is_refused_before_the_update(batches, layers):
    real, _ = batches
    model = _model(layers)
    bad = (dict(real[0]), dict(real[1]), dict(real[2]))
    bad[1]["mano.beta.r"] = real[1]["mano.beta.r"].clone()
    bad[1]["mano.beta.r"][0, 0] = float("nan")
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)
    before = model.head_r.hmr_layer.refine[0].weight.detach().clone()
    with pytest.raises(FloatingPointError, match="loss/mano/beta/r"):
        training_step(model, bad, layers, opt, RES)
    assert torch.equal(before, model.head_r.hmr_layer.refine[0].weight)


def test_evaluate_in_temporal_order(tiny_world, layers):
    val = ArcticDataset(tiny_world, "p1_val", seed=0, augment=False, config=CFG)
    keys = [parse_imgname(n) for n in val.imgnames]
    order = temporal_order(val.imgnames)
    assert [keys[i] for i in order] == sorted(keys)
    view = keys[order[0]][:3]
    frames = [i for i in order if keys[i][:3] == view][:12]  # 12 consecutive frames of one view
    model = _model(layers).eval()
    res = evaluate(model, DataLoader(Subset(val, frames), batch_size=5), layers, RES)
    assert res["frames"] == 12 and [parse_imgname(n) for n in res["imgnames"]] == [keys[i] for i in frames]
    for k in ("mpjpe/ra/h", "cdev/ho", "mrrpe/r/l", "aae", "success_rate/0.05", "acc/h", "acc/o", "mdev/h"):
        assert k in res["summary"], k
    assert np.isfinite(res["summary"]["mpjpe/ra/h"]) and np.isfinite(res["summary"]["acc/h"])
    # the per-frame values are those of per_frame_metrics on the prepared batch
    batch = next(iter(DataLoader(Subset(val, frames[:5]), batch_size=5)))
    t, m = prepare_targets(dict(batch[1]), dict(batch[2]), layers.mano_r, layers.mano_l, layers.objects, img_res=RES)
    with torch.no_grad():
        direct = per_frame_metrics(model(batch[0], m), t, m)
    np.testing.assert_allclose(res["per_frame"]["mpjpe/ra/h"][:5], direct["mpjpe/ra/h"], rtol=1e-5)
    assert np.isfinite(res["per_frame"]["mpjpe/ra/h"]).sum() == 12  # both hands are in every val frame


def test_sequence_frames_padded_differently_by_their_batches_stack():
    """A sequence's frames may sit in batches padded to different object lengths (a batch
    that also holds another, larger object): the kept frames are trimmed to their own count."""
    from hogsa_loader.baselines.engine import SEQUENCE_KEYS, _sequence_entries

    def batch(pad: int):
        pred = {k: torch.zeros(2, pad if k == "object.v.cam" else 30, 3) for k in SEQUENCE_KEYS}
        targets = dict(pred, **{"object.v_len": torch.tensor([5, pad]), "is_valid": torch.ones(2)})
        return pred, targets, {"part_ids": torch.ones(2, pad, dtype=torch.long)}

    entries = [_sequence_entries(*batch(pad))[0] for pad in (5, 9)]  # frame 0 of each: 5 object vertices
    stacked = torch.stack([e["targets"]["object.v.cam"] for e in entries])
    assert stacked.shape == (2, 5, 3) and torch.stack([e["part_ids"] for e in entries]).shape == (2, 5)
    assert torch.stack([e["pred"]["object.v.cam"] for e in entries]).shape == (2, 5, 3)
    assert _sequence_entries(*batch(9))[1]["targets"]["object.v.cam"].shape == (9, 3)  # frame 1: its own 9
