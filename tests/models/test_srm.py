"""SRM (StyleUNet refinement): shapes/dtypes, alpha-exact output, losses (VGG substitute
warning, R1), checkpoint round trip and validation, a few training steps reduce L1, and
the trainer end to end (exact resume) on HOGS renders of the tiny world."""

from __future__ import annotations

import importlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import job

from hogsa_loader.errors import AssetError
from hogsa_loader.models.srm import SRM, StyleUNet, StyleUNetConfig, count_gflops, load_srm, save_srm
from hogsa_loader.models.srm.stylegan import HaarTransform, InverseHaarTransform, ModulatedConv2d
from hogsa_loader.train.srm_discriminator import ConditionalDiscriminator
from hogsa_loader.train.srm_losses import (
    LaplacianPyramidL1,
    SubstituteWarning,
    VGGPerceptualLoss,
    d_logistic,
    g_nonsaturating,
    load_vgg19_features,
    perceptual_loss,
    r1_penalty,
    vgg19_features,
)

ROOT = Path(__file__).resolve().parents[2]
SMALL = [16, 32, 32]  # 3 levels: inputs multiple of 8


def _srm(scale: int = 1, **kw) -> SRM:
    torch.manual_seed(0)
    return SRM(StyleUNetConfig(channels=SMALL, style_dim=16, mlp_num=2, scale=scale, extra_channels=8, **kw))


def _inputs(b: int, h: int, w: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    alpha = (torch.rand(b, h, w, generator=g) * 1.4 - 0.2).clamp(0, 1)
    alpha[:, : h // 4] = 0.0  # an empty band
    rgb = torch.rand(b, h, w, 3, generator=g) * alpha[..., None]
    return rgb, alpha


def test_haar_roundtrip_and_modconv_equivalence():
    x = torch.randn(2, 3, 16, 12)
    y = HaarTransform()(x)
    assert y.shape == (2, 12, 8, 6)
    assert torch.allclose(InverseHaarTransform()(y), x, atol=1e-5)
    assert torch.allclose(y.square().sum(), x.square().sum(), rtol=1e-5)  # orthonormal
    # fused (activation-scaling) form == per-sample modulated, demodulated weights
    conv = ModulatedConv2d(5, 7, 3, 8)
    xs, st = torch.randn(3, 5, 10, 10), torch.randn(3, 8)
    out = conv(xs, st)
    s = conv.modulation(st)
    ref = []
    for b in range(3):
        w = conv.weight * conv.scale * s[b][None, :, None, None]
        w = w / torch.sqrt(w.square().sum((1, 2, 3), keepdim=True) + 1e-8)
        ref.append(torch.nn.functional.conv2d(xs[b : b + 1], w, padding=1))
    assert torch.allclose(out, torch.cat(ref), atol=1e-5)
    up = ModulatedConv2d(5, 4, 3, 8, upsample=True)(xs, st)
    assert up.shape == (3, 4, 20, 20)


@pytest.mark.parametrize("scale", [1, 2])
@pytest.mark.parametrize("hw", [(32, 32), (40, 24), (64, 96)])
def test_refine_shapes_dtype_and_alpha(scale, hw):
    srm = _srm(scale)
    rgb, alpha = _inputs(2, *hw)
    out = srm.refine(rgb, alpha)
    assert out.shape == (2, hw[0] * scale, hw[1] * scale, 3) and out.dtype == torch.float32
    assert torch.isfinite(out).all() and out.min() >= 0 and out.max() <= 1
    out2, a_out = srm.refine(rgb, alpha[..., None], return_alpha=True)  # (B,H,W,1) alpha accepted
    assert torch.equal(out, out2)
    assert (out <= a_out[..., None] + 1e-6).all()
    if scale == 1:
        assert torch.equal(a_out, alpha)
        assert (out[alpha == 0] == 0).all()  # background untouched: compositing stays exact
    else:
        assert (out[a_out == 0] == 0).all()
    assert srm.refine(rgb.double(), alpha.double()).dtype == torch.float64
    # deterministic inference (no noise, stored style code)
    assert torch.equal(out, srm.refine(rgb, alpha))


@pytest.mark.parametrize("scale", [1, 2])
def test_refine_test_time_augmentation(scale):
    """tta averages the refinements of symmetric copies mapped back: with all 8 the result
    is exactly equivariant (refining a turned image = turning the refined one), which one
    pass is not; shapes, alpha bound and empty background hold as without it."""
    from hogsa_loader.models.srm.model import TTA_CODES, dihedral, dihedral_inverse

    x = torch.rand(2, 3, 5, 7)
    for c in range(8):
        assert torch.equal(dihedral_inverse(dihedral(x, c), c), x), c
    assert len({tuple(dihedral(x[..., :5], c).flatten().tolist()) for c in TTA_CODES[8]}) == 8
    srm = _srm(scale)
    rgb, alpha = _inputs(2, 40, 24)
    turn = lambda t: t.movedim(-1, 1).rot90(1, (-2, -1)).movedim(1, -1) if t.ndim == 4 else t.rot90(1, (-2, -1))  # noqa: E731
    with torch.no_grad():  # a visibly non-equivariant network
        for prm in srm.parameters():
            prm.add_(0.05 * torch.randn_like(prm))
    one = srm.refine(rgb, alpha)
    assert (srm.refine(turn(rgb), turn(alpha)) - turn(one)).abs().max() > 1e-3
    for n in (2, 4, 8):
        out, a_out = srm.refine(rgb, alpha, tta=n, return_alpha=True)
        assert out.shape == one.shape and (out <= a_out[..., None] + 1e-6).all()
        assert (out[a_out == 0] == 0).all()
        if scale == 1:
            assert torch.equal(a_out, alpha)
    full = srm.refine(rgb, alpha, tta=8)
    torch.testing.assert_close(srm.refine(turn(rgb), turn(alpha), tta=8), turn(full), atol=1e-5, rtol=0)
    for bad in (3, True):
        with pytest.raises(ValueError, match="tta must be one of"):
            srm.refine(rgb, alpha, tta=bad)


def test_training_forward_grad_and_wavelet_options():
    for wavelet in (True, False):
        srm = _srm(1, wavelet=wavelet)
        rgb, alpha = _inputs(2, 16, 16)
        x = rgb.permute(0, 3, 1, 2).requires_grad_(True)
        y = srm(x, alpha[:, None], z=torch.randn(2, 16))
        assert y.shape == (2, 3, 16, 16)
        y.mean().backward()
        assert all(p.grad is not None for n, p in srm.named_parameters() if "noise" not in n)


def test_default_size_gflops():
    g = count_gflops(StyleUNet(), 256)
    assert 2.0 < g < 8.0, g  # "a few GFLOPs" at 256² (5.2 for the default widths)


def test_losses_substitute_warning_and_r1():
    with pytest.warns(SubstituteWarning):
        perc = perceptual_loss(None)
    assert isinstance(perc, LaplacianPyramidL1) and perc.kind == "laplacian"
    x, y = torch.rand(2, 3, 32, 32) * 2 - 1, torch.rand(2, 3, 32, 32) * 2 - 1
    assert float(perc(x, x)) == 0.0 and float(perc(x, y)) > 0
    d = ConditionalDiscriminator(32, cond_channels=4, channels=[8, 16, 16])
    cond = torch.rand(2, 4, 32, 32)
    r1, logits = r1_penalty(lambda im: d(im, cond), x)
    assert logits.shape == (2,) and torch.isfinite(r1) and float(r1) > 0
    r1.backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in d.parameters())
    assert float(d_logistic(logits.detach(), logits.detach())) > 0 and float(g_nonsaturating(logits.detach())) > 0


def test_vgg_weights_file(tmp_path):
    from safetensors.torch import save_file

    feats = vgg19_features()
    sd = {f"features.{k}": v for k, v in feats.state_dict().items()} | {"classifier.0.weight": torch.zeros(2, 2)}
    save_file(sd, str(tmp_path / "vgg19.safetensors"))
    torch.save(sd, tmp_path / "vgg19.pth")
    for name in ("vgg19.safetensors", "vgg19.pth"):
        loss = perceptual_loss(tmp_path / name)
        assert isinstance(loss, VGGPerceptualLoss) and loss.kind == "vgg"
        x = torch.rand(1, 3, 32, 32, requires_grad=True)
        v = loss(x, torch.rand(1, 3, 32, 32))
        v.backward()
        assert float(v) > 0 and x.grad is not None
    bad = dict(sd)
    bad.pop("features.0.weight")
    save_file(bad, str(tmp_path / "bad.safetensors"))
    with pytest.raises(AssetError, match="bad.safetensors"):
        load_vgg19_features(tmp_path / "bad.safetensors")
    with pytest.raises(AssetError, match="missing"):
        load_vgg19_features(tmp_path / "none.pth")


def test_checkpoint_roundtrip_and_validation(tmp_path):
    srm = _srm(2)
    with torch.no_grad():
        for p in srm.parameters():
            p.add_(torch.randn_like(p) * 0.01)
    save_srm(srm, tmp_path / "ck", extra={"note": "test"})
    back = load_srm(tmp_path / "ck", device="cpu")
    a, b = srm.net.state_dict(), back.net.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    rgb, alpha = _inputs(1, 24, 16)
    assert torch.equal(srm.refine(rgb, alpha), back.refine(rgb, alpha))
    for dt, tol in ((torch.bfloat16, 0.03), (torch.float16, 0.005)):  # half-precision weights run too
        half = load_srm(tmp_path / "ck", dtype=dt)
        assert next(half.parameters()).dtype == dt
        out = half.refine(rgb, alpha)
        assert out.dtype == rgb.dtype and float((out - srm.refine(rgb, alpha)).abs().max()) < tol
    man = json.loads((tmp_path / "ck" / "manifest.json").read_text())
    assert man["format"] == "hogsa-srm" and man["schema_version"] == 1 and man["io"]["scale"] == 2
    # validation: bad schema, torn tensors, missing file
    (tmp_path / "v2").mkdir()
    (tmp_path / "v2" / "manifest.json").write_text(json.dumps(man | {"schema_version": 2}))
    with pytest.raises(AssetError, match="manifest.json.*schema_version"):
        load_srm(tmp_path / "v2")
    (tmp_path / "nan").mkdir()  # NaN is not JSON (Python's reader would accept it)
    (tmp_path / "nan" / "manifest.json").write_text(json.dumps(man | {"extra": {"psnr": float("nan")}}))
    with pytest.raises(AssetError, match="manifest.json.*NaN is not a JSON value"):
        load_srm(tmp_path / "nan")
    blob = bytearray((tmp_path / "ck" / "srm.safetensors").read_bytes())
    blob[-1] ^= 1
    (tmp_path / "ck" / "srm.safetensors").write_bytes(bytes(blob))
    with pytest.raises(AssetError, match="srm.safetensors.*sha256"):
        load_srm(tmp_path / "ck")
    (tmp_path / "ck" / "srm.safetensors").unlink()
    with pytest.raises(AssetError, match="srm.safetensors"):
        load_srm(tmp_path / "ck")
    with pytest.raises(AssetError, match="missing"):
        load_srm(tmp_path / "nowhere")


def test_few_steps_reduce_l1():
    """Plain L1 training on a fixed blurred/darkened batch: the refined L1 drops."""
    torch.manual_seed(0)
    srm = _srm(1)
    g = torch.Generator().manual_seed(1)
    gt = torch.rand(4, 3, 32, 32, generator=g)
    gt = torch.nn.functional.avg_pool2d(gt, 3, 1, 1)
    alpha = torch.ones(4, 1, 32, 32)
    coarse = torch.nn.functional.avg_pool2d(gt, 5, 1, 2) * 0.8
    opt = torch.optim.Adam(srm.parameters(), lr=2e-3, betas=(0.0, 0.99))
    with torch.no_grad():
        l0 = float((srm(coarse, alpha, noise_mode="none") - gt).abs().mean())
    for _ in range(25):
        loss = (srm(coarse, alpha, z=torch.randn(4, 16)) - gt).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        l1 = float((srm(coarse, alpha, noise_mode="none") - gt).abs().mean())
    assert l1 < 0.8 * l0, (l0, l1)


# ----------------------------------------------------------------------------- trainer
def _cli():
    return job("srm")


@pytest.fixture(scope="module")
def hogs_runs(tiny_world, tmp_path_factory):
    """A briefly trained HOGS run on the tiny world (64², few frames) inside a runs folder."""
    from hogsa_loader.train import HogsConfig, HogsTrainer

    runs = tmp_path_factory.mktemp("hogs_runs")
    cfg = HogsConfig.from_json(
        dict(
            data=str(tiny_world),
            subject="s01",
            object="box",
            out=str(runs / "s01_box"),
            iters=3,
            image_size=64,
            frame_stride=8,
            eval_every_frame=2,
            max_eval=2,
            eval_every=0,
            ckpt_every=0,
            lr_scale=10.0,
            k=1,
            sh_degree=0,
            sh_warmup=0,
            strip_views=1,
        )
    )
    HogsTrainer(cfg, progress=False).train()
    (runs / "unfinished").mkdir()  # skipped: no part manifests
    return runs


@pytest.fixture(scope="module")
def folds(tiny_world, tmp_path_factory):
    """Two view folds of the tiny-world run: 'odd' saw views 1,3,5,7 and 'even' 2,4,6."""
    from hogsa_loader.train import HogsConfig, HogsTrainer

    folds = tmp_path_factory.mktemp("folds")
    for name, views in (("odd", [1, 3, 5, 7, 8]), ("even", [2, 4, 6, 8])):
        HogsTrainer(
            HogsConfig.from_json(
                dict(out=str(folds / name), views=views, seed=len(name), data=str(tiny_world), **_FOLD_COMMON)
            ),
            progress=False,
        ).train()
    return folds


@pytest.fixture(scope="module")
def srm_cache(tmp_path_factory):
    """One coarse-render cache shared by the SRM runs of this module (``--cache``)."""
    return tmp_path_factory.mktemp("srm_cache")


def _args(world, runs, out, iters):
    return [
        "--data",
        str(world),
        "--hogs",
        str(runs),
        "--out",
        str(out),
        "--optim-iters",
        str(iters),
        "--batch-size",
        "2",
        "--crop",
        "32",
        "--model-channels",
        "8,16,16",
        "--run-eval-every",
        "0",
        "--run-ckpt-every",
        "2",
        "--run-strip-views",
        "1",
        "--quiet",
    ]


def test_trainer_end_to_end_and_exact_resume(tiny_world, hogs_runs, tmp_path):
    cli = _cli()
    with pytest.warns(SubstituteWarning):
        assert cli.main(_args(tiny_world, hogs_runs, tmp_path / "a", 4)) == 0
    out = tmp_path / "a"
    m = json.loads((out / "metrics.json").read_text())
    for tag in ("without_srm", "with_srm"):
        assert set(m[tag]) >= {"psnr", "ssim", "lpips"} and np.isfinite(m[tag]["psnr"])
    assert m["perceptual"]["kind"] == "laplacian" and m["runs"][0]["name"] == "s01_box" and len(m["runs"]) == 1
    assert m["per_view"] and all(r["view"] == 8 for r in m["per_view"])
    assert (out / "samples.png").is_file() and (out / "curves.png").is_file()
    assert list((out / "cache").glob("coarse_s01_box_*.safetensors"))
    srm = load_srm(out)  # the run folder is a checkpoint folder
    assert srm.refine(torch.zeros(1, 32, 32, 3), torch.zeros(1, 32, 32)).abs().max() == 0
    assert any(
        "r1" in h for h in json.loads(next((out / "checkpoints").glob("step_*/trainer.json")).read_text())["history"]
    )
    # interrupted at step 2 (checkpoint), resumed to 4: identical to the straight run
    with pytest.warns(SubstituteWarning):
        assert cli.main(_args(tiny_world, hogs_runs, tmp_path / "b", 2)) == 0
        assert cli.main(_args(tiny_world, hogs_runs, tmp_path / "b", 4) + ["--resume"]) == 0
    a, b = load_srm(out).net.state_dict(), load_srm(tmp_path / "b").net.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    # refusing to overwrite a run without --resume, before any data is read (no substitute warning)
    assert cli.main(_args(tiny_world, hogs_runs, tmp_path / "b", 4)) == 2


def test_cross_view_pairs(tiny_world, hogs_runs, folds, srm_cache, tmp_path):
    """View folds render the training samples whose view they never saw; leaks are refused."""
    from hogsa_loader.errors import AssetError
    from hogsa_loader.train import HogsConfig, HogsTrainer
    from hogsa_loader.train.srm_pairs import find_runs, fold_runs, load_pairs

    run = hogs_runs / "s01_box"
    found = fold_runs(run, find_runs(folds))
    assert sorted(f.name for f in found) == ["even", "odd"]
    own = load_pairs(tiny_world, run, srm_cache, mode="own")
    both = load_pairs(tiny_world, run, srm_cache, mode="both", folds=found)
    cross = load_pairs(tiny_world, run, srm_cache, mode="cross", folds=found)
    n = len(own.data.train)
    assert own.train_rows.tolist() == list(range(n))
    # every training sample once from the run, once from the fold that did not see its view
    assert sorted(both.train_rows.tolist()) == sorted(list(range(n)) * 2)
    assert sorted(cross.train_rows.tolist()) == list(range(n)) and cross.sources == {
        "odd": both.sources["odd"],
        "even": both.sources["even"],
    }
    start = 0
    for name, count in cross.sources.items():  # rows in source order
        views = {own.data.train[int(i)].view for i in cross.train_rows[start : start + count]}
        assert views and views.isdisjoint({"odd": {1, 3, 5, 7}, "even": {2, 4, 6}}[name])
        start += count
    assert not torch.equal(cross.train_rgb, own.train_rgb[cross.train_rows])  # other models, other pixels
    assert torch.equal(both.eval_rgb, own.eval_rgb)  # evaluation always uses the run's own renders
    with pytest.raises(AssetError, match="view-fold runs"):
        load_pairs(tiny_world, run, srm_cache, mode="cross", folds=[])
    leak = tmp_path / "leak"
    HogsTrainer(
        HogsConfig.from_json(
            {**_FOLD_COMMON, "out": str(leak), "views": [1, 2, 3, 8], "data": str(tiny_world), "eval_views": [3]}
        ),
        progress=False,
    ).train()
    with pytest.raises(AssetError, match="held-out view"):
        fold_runs(run, find_runs(folds) + find_runs(leak))


_FOLD_COMMON = dict(
    subject="s01",
    object="box",
    iters=1,
    image_size=64,
    frame_stride=8,
    eval_every_frame=2,
    max_eval=2,
    eval_every=0,
    ckpt_every=0,
    k=1,
    sh_degree=0,
    sh_warmup=0,
    strip_views=1,
    eval_views=[8],
)


def test_render_cache_key_follows_labels_cameras_and_body_model(tiny_world, hogs_runs):
    """A shared render cache never serves renders of other labels (a world-noise copy),
    other cameras or another MANO file: each of them changes the key."""
    import dataclasses

    from hogsa_loader.train.hogs_source import load_run_data
    from hogsa_loader.train.srm_pairs import _inputs_hash

    source, data = load_run_data(json.loads((hogs_runs / "s01_box" / "config.json").read_text()), data=tiny_world)
    parts = {"train": list(data.train[:3]), "eval": list(data.eval)}
    key = lambda: _inputs_hash(source, "box", data, parts)  # noqa: E731
    ref = key()
    assert key() == ref
    first = parts["train"][0]
    trans = data.sequences[first.seq_index].right.trans
    trans[first.frame, 0] += 1e-3  # 1 mm on one hand of one frame
    moved = key()
    trans[first.frame, 0] -= 1e-3
    parts["train"][0] = dataclasses.replace(first, K=first.K * 1.001)
    zoomed = key()
    parts["train"][0] = first
    assert key() == ref
    source.mano_layers["left"].v_template.add_(1e-4)
    other_mano = key()
    assert len({ref, moved, zoomed, other_mano}) == 4


def test_render_cache_key_follows_weights_settings_and_code(hogs_runs, tmp_path, monkeypatch):
    """The run part of the key changes with the part settings (e.g. ``weld_seams``, which
    changes how the same weights render), the learned light and the render-code version."""
    import shutil

    from hogsa_loader.train import srm_pairs as pairs

    run = tmp_path / "run"
    shutil.copytree(hogs_runs / "s01_box", run)
    ref = pairs._run_hash(run)
    man_path = run / "object" / "manifest.json"
    man = json.loads(man_path.read_text())
    man_path.write_text(
        json.dumps({**man, "config": {**man["config"], "weld_seams": not man["config"].get("weld_seams", False)}})
    )
    other_cfg = pairs._run_hash(run)
    man_path.write_text(json.dumps(man))
    assert pairs._run_hash(run) == ref
    from hogsa_loader.models.gaussians.shading import DirectionalLight, save_light

    save_light(DirectionalLight(direction=(0.0, 0.3, 1.0)), run / "light")
    with_light = pairs._run_hash(run)
    save_light(DirectionalLight(direction=(0.3, 0.0, 1.0)), run / "light")
    other_light = pairs._run_hash(run)
    monkeypatch.setattr(pairs, "RENDER_CACHE_VERSION", pairs.RENDER_CACHE_VERSION + 1)
    other_code = pairs._run_hash(run)
    monkeypatch.setattr("hogsa_loader.__version__", "0.0.0-other")
    other_library = pairs._run_hash(run)
    assert len({ref, other_cfg, with_light, other_light, other_code, other_library}) == 6


def test_validation_views_split(tiny_world, hogs_runs, folds, srm_cache):
    """Validation views leave training entirely; their inputs come from the fold that never saw them."""
    from hogsa_loader.train.srm_pairs import find_runs, fold_runs, load_pairs

    run = hogs_runs / "s01_box"
    found = fold_runs(run, find_runs(folds))
    cache = srm_cache
    own = load_pairs(tiny_world, run, cache, mode="own")
    cross = load_pairs(tiny_world, run, cache, mode="cross", folds=found)
    both = load_pairs(tiny_world, run, cache, mode="both", folds=found, val_views=[2, 5])
    views = lambda rows: {own.data.train[int(i)].view for i in rows}  # noqa: E731
    assert views(both.val_rows) == {2, 5} and not views(both.train_rows) & {2, 5}
    n_val = sum(own.data.train[i].view in (2, 5) for i in range(len(own.data.train)))
    assert len(both.val_rows) == n_val  # once each: from the one fold that did not see the view
    # the validation inputs are exactly the cross (fold) renders of those samples, not the run's own
    pos = {int(r): i for i, r in enumerate(cross.train_rows)}
    assert torch.equal(both.val_rgb, cross.train_rgb[[pos[int(r)] for r in both.val_rows]])
    assert not torch.equal(both.val_rgb, own.train_rgb[both.val_rows])
    # without folds, own renders validate
    own_v = load_pairs(tiny_world, run, cache, mode="own", val_views=[3])
    assert torch.equal(own_v.val_rgb, own.train_rgb[own_v.val_rows]) and views(own_v.val_rows) == {3}
    assert len(own_v.train_rows) + len(own_v.val_rows) == len(own.data.train)
    with pytest.raises(ValueError, match="not training views"):
        load_pairs(tiny_world, run, cache, mode="own", val_views=[8])  # the held-out view stays unseen
    with pytest.raises(ValueError, match="leave no training view"):
        load_pairs(tiny_world, run, cache, mode="own", val_views=list(range(1, 8)))


def test_trainer_keeps_best_validated_checkpoint(tiny_world, hogs_runs, folds, srm_cache, tmp_path):
    """With --val-views the saved model is the EMA generator of the best validation step,
    chosen without the held-out views, and resuming keeps the choice exactly."""
    cli = _cli()
    extra = [
        "--cross-hogs",
        str(folds),
        "--val-views",
        "2,5",
        "--run-eval-every",
        "1",
        "--optim-lr",
        "0.02",
        "--cache",
        str(srm_cache),
    ]
    with pytest.warns(SubstituteWarning):
        assert cli.main(_args(tiny_world, hogs_runs, tmp_path / "a", 6) + extra) == 0
    out = tmp_path / "a"
    m = json.loads((out / "metrics.json").read_text())
    vals = {e["step"]: e["val_with_srm"] for e in m["evals"]}
    assert sorted(vals) == list(range(7))
    best = max(vals, key=vals.get)
    assert m["selected_step"] == best and m["selection"]["best"]["psnr"] == pytest.approx(vals[best])
    assert m["selection"]["val_views"] == [2, 5] and set(m["selection"]["last_step"]) >= {"with_srm", "delta_psnr"}
    assert not (out / "cache").exists() and len(list(srm_cache.glob("coarse_*.safetensors"))) >= 3  # shared cache
    srm = load_srm(out)
    from hogsa_loader.models.srm.io import read_srm_manifest

    assert read_srm_manifest(out)["extra"]["step"] == best
    _check_recorded_targets_and_render_quality_refusal(tiny_world, hogs_runs / "s01_box", out, tmp_path)
    # the saved weights score exactly the recorded validation PSNR (they are that step's EMA)
    from hogsa_loader.train.srm_trainer import SRMTrainConfig, SRMTrainer

    cfg = SRMTrainConfig.from_json(json.loads((out / "config.json").read_text()))
    tr = SRMTrainer(cfg, progress=False)
    assert tr.validate(srm)["with_srm"]["psnr"] == pytest.approx(vals[best], abs=1e-9)
    assert m["with_srm"]["psnr"] == pytest.approx(tr.evaluate(srm)["with_srm"]["psnr"], abs=1e-9)
    # interrupted at step 2 and resumed: same selection, same weights
    with pytest.warns(SubstituteWarning):
        assert cli.main(_args(tiny_world, hogs_runs, tmp_path / "b", 2) + extra) == 0
        assert cli.main(_args(tiny_world, hogs_runs, tmp_path / "b", 6) + extra + ["--resume"]) == 0
    a, b = srm.net.state_dict(), load_srm(tmp_path / "b").net.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert json.loads((tmp_path / "b" / "metrics.json").read_text())["selected_step"] == best
    # the rule itself: a later, worse validation score does not replace the kept weights
    fake_ev = {"step": 0, "without_srm": {"psnr": 1.0, "ssim": 0.5}, "with_srm": {"psnr": 1.0, "ssim": 0.5}}
    tr.best, tr.best_state = None, None
    for step, score in ((1, 20.0), (2, 25.0), (3, 23.0)):
        tr.step = step
        with torch.no_grad():
            for t in tr.g_ema.net.parameters():
                t.fill_(float(step))
        tr.validate = lambda s=score: {
            "n": 1,
            "without_srm": {"psnr": 0.0, "ssim": 0.0},
            "with_srm": {"psnr": s, "ssim": 0.9},
        }
        tr._eval_point(fake_ev)
    assert tr.best["step"] == 2 and tr.best["psnr"] == 25.0
    assert all(float(t.flatten()[0]) == 2.0 for t in tr.best_model().net.parameters())


def _check_recorded_targets_and_render_quality_refusal(world, run, srm_dir, tmp_path):
    """The SRM records which views it trained and selected on; render_quality scores it on
    the held-out view and refuses it on a view it saw."""
    import shutil
    import types

    from hogsa_loader.models.srm.io import SRM_MANIFEST, read_srm_manifest, seen_views

    man = read_srm_manifest(srm_dir)
    (t,) = man["extra"]["targets"]
    assert (t["run"], t["subject"], t["object"]) == ("s01_box", "s01", "box")
    assert t["val_views"] == [2, 5] and not {2, 5, 8} & set(t["views"]) and t["views"]
    for ck in (srm_dir / "checkpoints").glob("step_*/g_ema"):  # the step checkpoints record them too
        assert read_srm_manifest(ck)["extra"]["targets"] == man["extra"]["targets"]
    assert seen_views(man, "s01", "box") == set(t["views"]) | {2, 5}
    assert seen_views(man, "s02", "box") == set() and seen_views({"extra": {}}, "s01", "box") is None

    mod = importlib.import_module("experiments.render_quality")
    js = tmp_path / "q.json"
    assert (
        mod.main(["--data", str(world), "--run", str(run), "--srm", str(srm_dir), "--json", str(js), "--max-eval", "2"])
        == 0
    )
    q1 = json.loads(js.read_text())
    assert q1["srm_views_check"].startswith("held-out:") and q1["srm_tta"] == 1
    assert (
        mod.main(
            [
                "--data",
                str(world),
                "--run",
                str(run),
                "--srm",
                str(srm_dir),
                "--json",
                str(js),
                "--max-eval",
                "2",
                "--srm-tta",
                "8",
            ]
        )
        == 0
    )
    q8 = json.loads(js.read_text())
    assert (
        q8["srm_tta"] == 8
        and q8["without_srm"] == q1["without_srm"]
        and q8["with_srm"]["psnr"] != q1["with_srm"]["psnr"]
    )
    # the same SRM claiming it trained on view 8: refused, or scored and marked with the flag
    seen = tmp_path / "seen_srm"
    shutil.copytree(srm_dir, seen, ignore=shutil.ignore_patterns("checkpoints", "cache"))
    m2 = json.loads((seen / SRM_MANIFEST).read_text())
    m2["extra"]["targets"][0]["views"].append(8)
    (seen / SRM_MANIFEST).write_text(json.dumps(m2))
    data = types.SimpleNamespace(subject="s01", object_name="box", eval_views=[8])
    with pytest.raises(SystemExit, match=r"view\(s\) \[8\] of s01/box"):
        mod.check_srm_views(mod.parse_args(["--run", str(run), "--json", str(js), "--srm", str(seen)]), data)
    args = mod.parse_args(["--run", str(run), "--json", str(js), "--srm", str(seen), "--allow-seen-views"])
    assert mod.check_srm_views(args, data).startswith("not held-out:")
    del m2["extra"]["targets"]
    (seen / SRM_MANIFEST).write_text(json.dumps(m2))
    assert mod.check_srm_views(args, data).startswith("unchecked")


def test_dihedral_augment_moves_input_and_target_together(tiny_world, hogs_runs, srm_cache, tmp_path):
    from hogsa_loader.models.srm.model import dihedral
    from hogsa_loader.train.srm_trainer import SRMTrainConfig, SRMTrainer

    x = torch.arange(16.0).reshape(1, 4, 4)
    outs = [dihedral(x, c) for c in range(8)]
    assert len({tuple(o.flatten().tolist()) for o in outs}) == 8  # the 8 symmetries of the square
    assert torch.equal(dihedral(x, 1), x.flip(-1)) and torch.equal(dihedral(x, 2), torch.rot90(x, 1, (-2, -1)))
    base = dict(
        data=str(tiny_world),
        hogs=str(hogs_runs),
        batch_size=6,
        crop=32,
        channels=[8, 16, 16],
        lambda_gan=0.0,
        cache=str(srm_cache),
    )
    plain = SRMTrainer(
        SRMTrainConfig.from_json(dict(out=str(tmp_path / "p"), augment="none", **base)),
        progress=False,
        log=lambda m: None,
    )
    aug = SRMTrainer(
        SRMTrainConfig.from_json(dict(out=str(tmp_path / "a"), augment="d4", **base)),
        progress=False,
        log=lambda m: None,
    )
    moved = 0
    for _ in range(3):  # same windows (same seed); the augmented ones are one symmetry of them, shared by all three
        p, a = plain.batch(), aug.batch()
        aug.gen.set_state(plain.gen.get_state())
        for b in range(6):
            codes = [c for c in range(8) if all(torch.equal(dihedral(tp[b], c), ta[b]) for tp, ta in zip(p, a))]
            assert codes, "input, alpha and target were not transformed alike"
            moved += 0 not in codes
    assert moved > 0
    with pytest.raises(ValueError, match="augment"):
        SRMTrainer(SRMTrainConfig.from_json(dict(out=str(tmp_path / "x"), augment="rot45", **base)), progress=False)


def test_discriminator_real_is_reachable_by_the_generator(tiny_world, hogs_runs, srm_cache, tmp_path):
    """D's real images are the GT clipped to the rendered alpha: no outline the generator
    (output c · alpha) cannot match, and the GT itself wherever it can."""
    from hogsa_loader.train.srm_trainer import SRMTrainConfig, SRMTrainer

    tr = SRMTrainer(
        SRMTrainConfig.from_json(
            dict(
                data=str(tiny_world),
                hogs=str(hogs_runs),
                out=str(tmp_path / "d"),
                batch_size=6,
                crop=0,
                channels=[8, 16, 16],
                cache=str(srm_cache),
            )
        ),
        progress=False,
        log=lambda m: None,
    )
    rgb, alpha, gt = tr.batch()
    assert float(gt.amax()) > 0.2
    for a in (alpha, 0.5 * alpha, torch.zeros_like(alpha)):  # the last two: GT silhouette beyond the render
        real = tr.discriminator_real(gt, a)
        assert bool((real <= a).all())  # like every generator output
        keep = gt <= a
        assert torch.equal(real[keep], gt[keep]) and torch.equal(real[~keep], a.expand_as(gt)[~keep])
    assert float(tr.discriminator_real(gt, torch.zeros_like(alpha)).abs().max()) == 0.0
