"""HOGS training on the tiny world: loss/PSNR improve, alpha outside the mask drops,
kill-and-resume is exact, outputs are written, bad arguments fail clearly."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import job, tiny_hogs_config

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.assets.conventions import project, transform
from hogsa_loader.errors import AssetError
from hogsa_loader.models.gaussians import load_part
from hogsa_loader.train import FrameSelection, HogsTrainer, dilate_mask, hogs_loss, load_hogs_data

ROOT = Path(__file__).resolve().parents[2]


def _cli():
    mod = job("hogs")
    return mod


_cfg = tiny_hogs_config


def _photo(trainer: HogsTrainer, samples) -> float:
    with torch.no_grad():
        gt, _, region = trainer.targets(samples)
        rgb, alpha = trainer.render(samples)
        _, terms = hogs_loss(rgb, gt, alpha, region, trainer.l_r())
    return terms["photo"]


def test_data_alignment(tiny_world):
    """Crops, intrinsics and masks line up: projected object vertices land on object pixels."""
    root = ArcticRoot(tiny_world)
    data = load_hogs_data(root, "s01", "box", FrameSelection(frame_stride=8, image_size=128))
    assert set(data.eval_views) == {8} and 8 not in data.train_views
    assert all(s.view == 8 for s in data.eval) and all(s.view != 8 for s in data.train)
    train_frames = {(s.seq_index, s.frame) for s in data.train}
    assert all((s.seq_index, s.frame) not in train_frames for s in data.eval)
    layer = root.object_layer()
    hits = []
    for s in data.train[:: max(1, len(data.train) // 6)]:
        seq = data.sequences[s.seq_index]
        o = seq.object
        v = (
            layer(
                angles=torch.tensor([[o.arti[s.frame]]]),
                global_orient=torch.tensor(o.rot[s.frame : s.frame + 1]),
                transl=torch.tensor(o.trans[s.frame : s.frame + 1]),
                names=["box"],
            )["v"][0]
            .double()
            .numpy()
        )
        K = s.K.copy()
        K[:2, 2] -= 0.5  # render intrinsics -> pixel-index convention
        uv = np.rint(project(transform(s.world2cam, v), K)).astype(int)
        ok = (uv >= 0).all(1) & (uv < 128).all(1)
        hits.append(np.isin(s.mask[uv[ok, 1], uv[ok, 0]], (3, 4)).mean())
    assert np.mean(hits) > 0.6  # occluded / back-facing vertices land on hand pixels


def test_training_improves_and_writes_outputs(tiny_world, tmp_path):
    tr = HogsTrainer(_cfg(tiny_world, tmp_path / "run", iters=24), progress=False)
    fixed = tr.data.train[:: max(1, len(tr.data.train) // 4)][:4]
    photo0 = _photo(tr, fixed)
    ev0 = tr.evaluate()
    m = tr.train()
    assert _photo(tr, fixed) < photo0 - 0.01
    assert m["psnr"] > ev0["psnr"] + 0.5
    assert m["initial"]["psnr"] == pytest.approx(ev0["psnr"])
    out = tmp_path / "run"
    metrics = json.loads((out / "metrics.json").read_text())
    for key in ("psnr", "ssim", "lpips", "per_view", "iters", "timings"):
        assert key in metrics
    assert metrics["iters"] == 24 and metrics["per_view"][0]["view"] == 8
    assert metrics["timings"]["s_per_iter"] > 0
    for png in ("strip.png", "curves.png"):
        assert (out / png).stat().st_size > 1000
    root = ArcticRoot(tiny_world)
    obj = load_part(out / "object", root.object_templates()["box"], expected_part_type="object")
    assert torch.equal(obj.splats.sh_dc, tr.parts["object"].splats.sh_dc)
    hand = load_part(out / "hand_left", root.mano_layers()["left"], expected_part_type="hand_left")
    assert torch.equal(hand.splats.offsets, tr.parts["hand_left"].splats.offsets)


def test_alpha_outside_mask_goes_down(tiny_world, tmp_path):
    tr = HogsTrainer(_cfg(tiny_world, tmp_path / "run", iters=12, lr_scale=5.0), progress=False)
    with torch.no_grad():  # swollen object Gaussians spill over the background
        tr.parts["object"].splats.log_scale_factor += 1.5
    fixed = tr.data.train[:: max(1, len(tr.data.train) // 4)][:4]

    def outside() -> float:
        with torch.no_grad():
            _, _, region = tr.targets(fixed)
            _, alpha = tr.render(fixed)
            return float(alpha[~region].mean())

    a0 = outside()
    assert a0 > 0.005
    for _ in range(12):
        tr.train_step()
    assert outside() < 0.93 * a0


def test_resume_matches_unbroken_run(tiny_world, tmp_path):
    full = HogsTrainer(_cfg(tiny_world, tmp_path / "full", iters=6, ckpt_every=3), progress=False)
    full.train()
    cli = _cli()
    args = [
        "--data",
        str(tiny_world),
        "--subject",
        "s01",
        "--object",
        "box",
        "--out",
        str(tmp_path / "cut"),
        "--image-size",
        "64",
        "--frame-stride",
        "4",
        "--eval-every-frame",
        "2",
        "--max-eval",
        "3",
        "--run-eval-every",
        "0",
        "--run-ckpt-every",
        "3",
        "--optim-lr-scale",
        "10",
        "--model-k",
        "1",
        "--model-sh-degree",
        "1",
        "--optim-sh-warmup",
        "0",
        "--quiet",
    ]
    assert cli.main(args + ["--optim-iters", "3"]) == 0  # the "killed" run: its last checkpoint is step 3
    assert json.loads((tmp_path / "cut" / "checkpoints" / "latest.json").read_text())["step"] == 3
    resumed = HogsTrainer(_cfg(tiny_world, tmp_path / "cut", iters=6, ckpt_every=3), progress=False)
    assert resumed.resume() and resumed.step == 3
    resumed.train()
    for name, part in full.parts.items():
        for (pn, p), (_, q) in zip(part.splats.named_parameters(), resumed.parts[name].splats.named_parameters()):
            assert torch.equal(p, q), f"{name}.{pn} differs after resume"
    a = json.loads((tmp_path / "full" / "metrics.json").read_text())
    b = json.loads((tmp_path / "cut" / "metrics.json").read_text())
    assert a["psnr"] == b["psnr"] and a["ssim"] == b["ssim"]
    assert [h["loss"] for h in full.history] == [h["loss"] for h in resumed.history]
    # resuming with different training settings is refused
    with pytest.raises(ValueError, match="lr_scale"):
        HogsTrainer(_cfg(tiny_world, tmp_path / "cut", iters=8, lr_scale=1.0), progress=False).resume()


def test_resume_checkpoint_without_weld_seams_is_refused(tiny_world, tmp_path):
    """A pre-1.0 run checkpointed without ``weld_seams`` in its part configs is refused on
    resuming, with an error naming the part manifest and the missing setting."""
    cut = HogsTrainer(_cfg(tiny_world, tmp_path / "old", iters=3, ckpt_every=3), progress=False)
    cut.train()
    folder = tmp_path / "old" / "checkpoints"
    step = json.loads((folder / "latest.json").read_text())["folder"]
    for name in ("hand_right", "hand_left", "object"):
        man_path = folder / step / name / "manifest.json"
        man = json.loads(man_path.read_text())
        del man["config"]["weld_seams"]
        man_path.write_text(json.dumps(man))
    resumed = HogsTrainer(_cfg(tiny_world, tmp_path / "old", iters=5, ckpt_every=5), progress=False)
    with pytest.raises(AssetError, match=r"manifest.json: config.weld_seams is missing from the checkpoint"):
        resumed.resume()


def test_bad_arguments(tiny_world, tmp_path, capsys):
    with pytest.raises(ValueError, match="unknown subject 's99'"):
        HogsTrainer(_cfg(tiny_world, tmp_path / "r", subject="s99"), progress=False)
    with pytest.raises(ValueError, match="unknown object 'mug'"):
        HogsTrainer(_cfg(tiny_world, tmp_path / "r", object="mug"), progress=False)
    with pytest.raises(ValueError, match="do not exist"):
        HogsTrainer(_cfg(tiny_world, tmp_path / "r", sequences=["box_grab_07"]), progress=False)
    with pytest.raises(ValueError, match="eval views"):
        HogsTrainer(_cfg(tiny_world, tmp_path / "r", eval_views=[0]), progress=False)
    rc = _cli().main(["--data", str(tiny_world), "--subject", "s01", "--object", "mug", "--out", str(tmp_path / "r")])
    assert rc == 2 and "unknown object 'mug'" in capsys.readouterr().err
    mask = torch.zeros(1, 9, 9, dtype=torch.bool)
    mask[0, 4, 4] = True
    assert int(dilate_mask(mask, 2).sum()) == 25


def test_sigkill_and_resume(tiny_world, tmp_path):
    """A CLI run killed with SIGKILL after a checkpoint resumes to the unbroken run's result."""
    import os
    import signal
    import subprocess
    import sys
    import time

    args = [
        "--data",
        str(tiny_world),
        "--subject",
        "s01",
        "--object",
        "box",
        "--image-size",
        "64",
        "--frame-stride",
        "4",
        "--eval-every-frame",
        "2",
        "--max-eval",
        "3",
        "--run-eval-every",
        "0",
        "--run-ckpt-every",
        "2",
        "--optim-lr-scale",
        "10",
        "--model-k",
        "1",
        "--model-sh-degree",
        "1",
        "--optim-sh-warmup",
        "0",
        "--optim-iters",
        "14",
        "--quiet",
    ]
    cut = tmp_path / "cut"
    # the same intra-op thread count as this process: CPU float sums are reproducible per thread count
    env = {**os.environ, "OMP_NUM_THREADS": str(torch.get_num_threads())}
    proc = subprocess.Popen(
        [sys.executable, "-m", "hogsa_loader.cli.main", "train", "hogs", *args, "--out", str(cut)], env=env
    )
    latest = cut / "checkpoints" / "latest.json"
    deadline = time.monotonic() + 120
    while not latest.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    step = json.loads(latest.read_text())["step"]
    assert 2 <= step <= 14
    assert _cli().main(args + ["--out", str(cut), "--resume"]) == 0
    assert _cli().main(args + ["--out", str(tmp_path / "full")]) == 0
    a = json.loads((tmp_path / "full" / "metrics.json").read_text())
    b = json.loads((cut / "metrics.json").read_text())
    assert b["iters"] == 14 and a["psnr"] == b["psnr"] and a["ssim"] == b["ssim"]
    assert a["per_sample"] == b["per_sample"]


def test_foreground_removed_before_resizing(tmp_path):
    """The background is cut at native resolution, so resized edge pixels hold the
    premultiplied foreground (what a render on black gives), never background colour."""
    import cv2

    from hogsa_loader.train.hogs_data import _read_foreground

    img = np.zeros((8, 8, 3), np.uint8)
    img[:] = (200, 200, 200)  # bright table
    img[:, :3] = (0, 0, 250)  # BGR red foreground in columns 0..2
    parts = np.zeros((8, 8), np.uint8)
    parts[:, :3] = 1
    cv2.imwrite(str(tmp_path / "i.png"), img)
    cv2.imwrite(str(tmp_path / "m.png"), parts)
    fg, mask = _read_foreground(tmp_path / "i.png", tmp_path / "m.png", 4)
    # column 1 of the 4-px image covers native columns 2 (fg) and 3 (table): half red, no grey
    np.testing.assert_array_equal(fg[:, 1], np.tile([125, 0, 0], (4, 1)))
    np.testing.assert_array_equal(fg[:, 0], np.tile([250, 0, 0], (4, 1)))
    assert (fg[:, 2:] == 0).all()
    assert (mask[:, :2] == 1).all() and (mask[:, 2:] == 0).all()  # partial pixels keep a part id
    fg_same, mask_same = _read_foreground(tmp_path / "i.png", tmp_path / "m.png", 8)
    assert (fg_same[:, 3:] == 0).all() and (mask_same == parts).all()


def test_alpha_inside_term_makes_translucent_silhouettes_cost():
    """On a black background a half-transparent render with doubled colour matches the GT
    photometrically; only the alpha-inside term tells it from an opaque one."""
    H = W = 16
    mask = torch.zeros(1, H, W, dtype=torch.bool)
    mask[:, 4:12, 4:12] = True
    gt = torch.zeros(1, H, W, 3)
    gt[mask] = 0.4
    region = dilate_mask(mask, 2)
    inside = ~dilate_mask(~mask, 1)
    l_r = torch.zeros(())
    opaque_a = mask.float()
    half_a = mask.float() * 0.5
    # premultiplied renders: both equal the GT colour-wise
    for kw in ({}, {"inside": inside, "lambda_alpha_in": 0.0}):
        lo, _ = hogs_loss(gt, gt, opaque_a, region, l_r, **kw)
        lh, _ = hogs_loss(gt, gt, half_a, region, l_r, **kw)
        assert float(lo) == pytest.approx(float(lh), abs=1e-7)  # indistinguishable without the term
    lo, to = hogs_loss(gt, gt, opaque_a, region, l_r, inside=inside, lambda_alpha_in=1.0)
    lh, th = hogs_loss(gt, gt, half_a, region, l_r, inside=inside, lambda_alpha_in=1.0)
    assert to["alpha_in"] == pytest.approx(0.0) and th["alpha_in"] == pytest.approx(0.5)
    assert float(lh) - float(lo) == pytest.approx(0.5, abs=1e-6)
    assert int(inside.sum()) == 36  # the 8x8 mask eroded by one pixel
