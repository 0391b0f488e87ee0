"""InterField-SF: the model on real and mixed batches, its decimator reader, ARCTIC's field
loss, average distance error and acceleration error on known inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from hogsa_loader.baselines import (
    FIELD_KEYS,
    FIELD_METRICS,
    InterFieldSF,
    evaluate_field,
    field_acceleration,
    field_metrics,
    field_training_step,
    interfield_loss,
    prepare_targets,
    read_mano_decimator,
)
from hogsa_loader.errors import AssetError, UnsafePickleError
from hogsa_loader.sample import is_synthetic

RES = 64
CLAMP = 0.1

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def decimator_file(tiny_world):
    return tiny_world / "arctic_data" / "data" / "meta" / "mano_decimator_195.npy"


@pytest.fixture(scope="module")
def decimator(decimator_file, layers):
    return read_mano_decimator(decimator_file, int(layers.mano_r.v_template.shape[0]))


def _targets(batch, layers):
    _, targets, meta = batch
    t, m = prepare_targets(
        dict(targets), dict(meta), layers.mano_r, layers.mano_l, layers.objects, img_res=RES, max_dist=CLAMP
    )
    return t, m


def test_decimator_is_read_from_the_root_and_checked(decimator_file, decimator, layers, tmp_path):
    V = int(layers.mano_r.v_template.shape[0])
    assert decimator["right"].shape == decimator["left"].shape == (195, V)
    raw = np.load(decimator_file, allow_pickle=True).item()  # the file is the test world's own
    np.testing.assert_array_equal(decimator["right"].numpy(), raw["D_right"])
    with pytest.raises(AssetError, match=rf"mano_decimator_195.npy.*D_right must be an \(S, {V + 1}\) matrix"):
        read_mano_decimator(decimator_file, V + 1)
    bad = tmp_path / "bad.npy"
    np.save(bad, np.array({"D_right": raw["D_right"], "D_left": raw["D_left"][:, :-1]}, dtype=object))
    with pytest.raises(AssetError, match=r"bad.npy.*D_left must be"):
        read_mano_decimator(bad, V)
    nan = tmp_path / "nan.npy"
    np.save(nan, np.array({"D_right": raw["D_right"] * np.nan, "D_left": raw["D_left"]}, dtype=object))
    with pytest.raises(AssetError, match=r"nan.npy.*non-finite"):
        read_mano_decimator(nan, V)
    evil = tmp_path / "evil.npy"
    np.save(evil, np.array({"D_right": print}, dtype=object))
    with pytest.raises(UnsafePickleError):
        read_mano_decimator(evil, V)


def test_template_points_are_the_decimated_rest_hands_and_centred_object(decimator_file, decimator, layers):
    model = InterFieldSF("resnet18", layers.mano_r, layers.mano_l, layers.objects, decimator)
    ids = np.load(decimator_file, allow_pickle=True).item()["vertex_ids_left"]  # a selection matrix
    mano = layers.mano_l
    z = torch.zeros(1, 3, dtype=mano.v_template.dtype)
    rest = mano(global_orient=z, hand_pose=torch.zeros(1, 45, dtype=z.dtype), betas=torch.zeros(1, 10, dtype=z.dtype))
    expect = rest.vertices[0, ids] - rest.joints[0, 0]
    torch.testing.assert_close(model.points_l, expect.float(), atol=1e-6, rtol=0)
    assert not torch.allclose(model.points_r, model.points_l)  # each hand its own mesh
    pts = model.object_points(["box", "box"])
    assert pts.shape == (2, 600, 3)
    torch.testing.assert_close(pts.mean(1), torch.zeros(2, 3), atol=1e-6, rtol=0)
    sub = layers.objects.forward_template(["box"])["v_sub"][0]
    torch.testing.assert_close(pts[0], (sub - sub.mean(0)).float(), atol=1e-6, rtol=0)


def test_forward_and_backward_on_real_and_mixed_batches(batches, layers, decimator):
    real, mixed = batches
    assert sum(is_synthetic(n) for n in mixed[2]["imgname"]) == 2
    V, L = int(layers.mano_r.v_template.shape[0]), int(layers.objects.v_len.max())
    for batch in (real, mixed):
        torch.manual_seed(0)
        model = InterFieldSF("resnet18", layers.mano_r, layers.mano_l, layers.objects, decimator).train()
        t, m = _targets(batch, layers)
        pred = model(batch[0], m)
        assert pred["dist.ro"].shape == pred["dist.lo"].shape == (4, V)
        assert pred["dist.or"].shape == pred["dist.ol"].shape == (4, L)
        losses = interfield_loss(pred, t, CLAMP)
        assert set(losses) == {"loss", "loss/dist/ro", "loss/dist/lo", "loss/dist/or", "loss/dist/ol"}
        assert torch.isfinite(losses["loss"]) and float(losses["loss"]) > 0
        losses["loss"].backward()
        for name in ("backbone.conv1", "down.0", "point_backbone.shallow_layer.0", "upsampling_o.upsampling"):
            grad = dict(model.named_parameters())[f"{name}.weight"].grad
            assert grad is not None and grad.abs().sum() > 0, name
        for key in FIELD_KEYS:  # each head reaches its own output only
            head = getattr(model, f"dist_head_{key[-2:]}").network[0].weight
            assert head.grad is not None and head.grad.abs().sum() > 0, key
    with pytest.raises(ValueError, match="shorter than the longest object template"):
        InterFieldSF("resnet18", layers.mano_r, layers.mano_l, layers.objects, decimator, object_outputs=L - 1)
    with pytest.raises(ValueError, match="3 query_names for a batch of 4"):
        model(real[0], dict(real[2], query_names=real[2]["query_names"][:3]))


def _field(B=3, V=5, L=7, v_len=(7, 4, 6), seed=0):
    g = torch.Generator().manual_seed(seed)
    t = {k: torch.rand(B, V if k[-2] != "o" else L, generator=g, dtype=torch.float64) * 0.08 for k in FIELD_KEYS}
    t["object.v_len"] = torch.tensor(v_len)
    t["is_valid"] = torch.ones(B)
    for k in ("dist.or", "dist.ol"):
        for b, n in enumerate(v_len):
            t[k][b, n:] = 0.0
    return t


def test_loss_is_zero_on_targets_and_known_for_known_offsets():
    t = _field()
    pred = {k: t[k].clone() for k in FIELD_KEYS}
    assert float(interfield_loss(pred, t)["loss"]) == 0.0
    for k in ("dist.or", "dist.ol"):
        pred[k][1, 4:] = 5.0  # object padding: never counted
    assert float(interfield_loss(pred, t)["loss"]) == 0.0
    off = {k: pred[k] + 0.01 for k in FIELD_KEYS}
    got = interfield_loss(off, t)
    assert float(got["loss/dist/ro"]) == pytest.approx(100 * 0.01**2)
    counted = sum(t["object.v_len"].tolist()) / (3 * 7)  # padding is in the mean's denominator
    assert float(got["loss/dist/or"]) == pytest.approx(100 * 0.01**2 * counted)
    t["is_valid"] = torch.tensor([1.0, 0.0, 1.0])  # an invalid frame adds nothing
    assert float(interfield_loss(off, t)["loss/dist/lo"]) == pytest.approx(100 * 0.01**2 * 2 / 3)
    t["is_valid"] = torch.ones(3)
    t["dist.ro"][0] = CLAMP  # a frame at the clamp weighs 0.1
    off["dist.ro"] = t["dist.ro"] + 0.01
    assert float(interfield_loss(off, t, CLAMP)["loss/dist/ro"]) == pytest.approx(100 * 0.01**2 * (0.1 + 2) / 3)


def test_average_error_is_zero_on_targets_known_for_offsets_and_nan_when_invalid():
    t = _field()
    m = field_metrics({k: t[k].clone() for k in FIELD_KEYS}, t)
    np.testing.assert_array_equal(m["avg/ho"], 0.0)
    np.testing.assert_array_equal(m["avg/oh"], 0.0)
    pred = {k: t[k] + (0.004 if k[-2] == "r" else -0.002) for k in FIELD_KEYS}  # 4 mm right, 2 mm left
    pred["dist.or"] = t["dist.or"] + 0.006
    pred["dist.ol"] = t["dist.ol"].clone()
    pred["dist.ol"][:, 4:] += 1.0  # from vertex 4 on: padding of frame 1, real vertices of frame 0
    t["is_valid"] = torch.tensor([1.0, 1.0, 0.0])
    m = field_metrics(pred, t)
    np.testing.assert_allclose(m["avg/ho"][:2], 3.0, atol=1e-9)  # (4 + 2) / 2 mm
    assert math.isnan(m["avg/ho"][2]) and math.isnan(m["avg/oh"][2])
    np.testing.assert_allclose(m["avg/oh"][1], (6 + 0) / 2, atol=1e-9)
    np.testing.assert_allclose(m["avg/oh"][0], (6 + 1000 * 3 / 7) / 2, atol=1e-9)


def test_acceleration_error_is_zero_for_offsets_and_known_for_a_parabola():
    F, fps = 6, 30.0
    t = _field(B=F, v_len=(6,) * F)
    t["right_valid"], t["left_valid"] = torch.ones(F), torch.ones(F)
    still = field_acceleration({k: t[k] + 0.01 for k in FIELD_KEYS}, t, fps)  # a constant offset
    np.testing.assert_allclose(still["acc/ho"][1:-1], 0.0, atol=1e-9)
    assert math.isnan(still["acc/ho"][0]) and math.isnan(still["acc/oh"][-1])
    frames = torch.arange(F, dtype=torch.float64)[:, None]
    c = 1e-4
    pred = {k: t[k] + c * frames**2 for k in FIELD_KEYS}  # second difference 2c per frame
    pred["dist.or"][:, 6:] = 9.0  # padding past the clip's object
    acc = field_acceleration(pred, t, fps)
    np.testing.assert_allclose(acc["acc/ho"][1:-1], 2 * c * fps**2, rtol=1e-9)
    np.testing.assert_allclose(acc["acc/oh"][1:-1], 2 * c * fps**2, rtol=1e-9)
    t["right_valid"] = torch.tensor([1.0, 1, 1, 0, 1, 1])
    t["left_valid"] = torch.tensor([1.0, 1, 0, 1, 1, 1])
    acc = field_acceleration(pred, t, fps)
    # frames 2..4 have an invalid right neighbour, frames 1..3 a left one: frame 1 keeps the
    # right hand's error, frame 4 the left's; the object counts everywhere
    assert math.isnan(acc["acc/ho"][2]) and math.isnan(acc["acc/ho"][3])
    np.testing.assert_allclose(acc["acc/ho"][[1, 4]], 2 * c * fps**2, rtol=1e-9)
    assert np.isfinite(acc["acc/oh"][1:-1]).all()


def test_a_training_step_prepares_both_directions_and_moves_the_weights(batches, layers, decimator):
    torch.manual_seed(0)
    model = InterFieldSF("resnet18", layers.mano_r, layers.mano_l, layers.objects, decimator)
    before = model.dist_head_ol.network[0].weight.detach().clone()
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)
    rec = field_training_step(model, batches[1], layers, opt, RES)
    assert set(rec) == {"loss", "loss/dist/ro", "loss/dist/lo", "loss/dist/or", "loss/dist/ol"}
    assert all(np.isfinite(v) and v > 0 for v in rec.values())
    assert rec["loss"] == pytest.approx(sum(v for k, v in rec.items() if k != "loss"), rel=1e-5)
    assert not torch.equal(before, model.dist_head_ol.network[0].weight)


def _frames(pred, targets, part):
    """Frames ``part`` of a batch as one clip: the object directions cut to the shortest object."""
    n = int(targets["object.v_len"][part].min())

    def cut(d):
        return {k: (v[part, :n] if k in ("dist.or", "dist.ol") else v[part]) for k, v in d.items()}

    keep = ("is_valid", "right_valid", "left_valid", "object.v_len", *FIELD_KEYS)
    return cut({k: pred[k] for k in FIELD_KEYS}), cut({k: targets[k] for k in keep})


def test_split_figures_are_the_per_frame_and_per_clip_figures_of_the_whole_split(tiny_world, layers, decimator):
    from torch.utils.data import DataLoader, Subset

    from hogsa_loader.baselines import temporal_order
    from hogsa_loader.baselines.engine import prepare_batch
    from hogsa_loader.sample.arctic_dataset import ArcticDataset, parse_imgname
    from hogsa_loader.sample.augment import ArcticConfig

    val = ArcticDataset(tiny_world, "p1_val", seed=0, augment=False, config=ArcticConfig(img_res=RES))
    order = temporal_order(val.imgnames)
    clips = [parse_imgname(val.imgnames[i])[:3] for i in order]
    first = clips.index(clips[-1]) if clips[0] == clips[-1] else next(i for i, c in enumerate(clips) if c != clips[0])
    picked = order[first - 5 : first + 6]  # the last 5 frames of one clip and the first 6 of the next
    assert len({parse_imgname(val.imgnames[i])[:3] for i in picked}) == 2
    torch.manual_seed(0)
    longer = int(layers.objects.v_len.max()) + 7  # object outputs past every template: cut per frame
    model = InterFieldSF("resnet18", layers.mano_r, layers.mano_l, layers.objects, decimator, object_outputs=longer)
    out = evaluate_field(model, DataLoader(Subset(val, picked), batch_size=3), layers, RES)
    assert out["frames"] == 11 and set(out["summary"]) == set(FIELD_METRICS)
    # the same figures from one batch of the whole subset, split into its two clips by hand
    model.eval()
    with torch.no_grad():
        (batch,) = DataLoader(Subset(val, picked), batch_size=11)
        inputs, targets, meta = prepare_batch(batch, layers, RES, "cpu", max_dist=CLAMP, field="both")
        pred = model(inputs, meta)
    avg = field_metrics(pred, targets)
    acc = {k: [] for k in ("acc/ho", "acc/oh")}
    for part in (slice(0, 5), slice(5, 11)):
        a = field_acceleration(*_frames(pred, targets, part))
        for k in acc:
            acc[k].append(a[k])
    assert pred["dist.or"].shape[1] == longer > int(targets["object.v_len"].max())
    for k in ("avg/ho", "avg/oh"):
        np.testing.assert_allclose(out["per_frame"][k], avg[k], rtol=1e-5)
    for k in ("avg/ho", "avg/oh"):
        assert out["summary"][k] == pytest.approx(float(np.nanmean(avg[k])), rel=1e-5)
    for k in acc:
        whole = np.concatenate(acc[k])
        assert np.isnan(whole[[0, 4, 5, 10]]).all()  # each clip's first and last frame
        assert out["summary"][k] == pytest.approx(float(np.nanmean(whole)), rel=1e-5)
    # a clip boundary ignored would take a second difference across it
    joined = field_acceleration(*_frames(pred, targets, slice(0, 11)))
    assert float(np.nanmean(joined["acc/ho"])) != pytest.approx(out["summary"]["acc/ho"], rel=1e-3)
    flat = evaluate_field(model, DataLoader(Subset(val, picked), batch_size=4), layers, RES, temporal=False)
    assert set(flat["summary"]) == {"avg/ho", "avg/oh"}
    assert flat["summary"]["avg/ho"] == pytest.approx(out["summary"]["avg/ho"], rel=1e-5)
