"""HOGS tooling around the trainer: HogsModel loading, the render-quality benchmark,
train_all_hogs (selection, job array, skip finished), learning-rate overrides."""

from __future__ import annotations

import importlib
import json
import shutil
from pathlib import Path

import pytest
import torch
from conftest import job, tiny_hogs_config

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.errors import AssetError
from hogsa_loader.models.gaussians.hogs_model import HogsModel
from hogsa_loader.train import HogsTrainer

ROOT = Path(__file__).resolve().parents[2]


def _module(path: Path, name: str):
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


FAST = [
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
    "0",
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


_cfg = tiny_hogs_config


@pytest.fixture(scope="module")
def trained_runs(tiny_world, tmp_path_factory):
    """A 4-step mesh run and a 2-step free run of s01/box."""
    base = tmp_path_factory.mktemp("hogs_runs")
    mesh = HogsTrainer(_cfg(tiny_world, base / "mesh", iters=4), progress=False)
    mesh.train()
    free = HogsTrainer(_cfg(tiny_world, base / "free", iters=2, gaussians="free"), progress=False)
    free.train()
    return base / "mesh", base / "free", mesh


def test_a_bundle_of_free_runs_streams_labelled_samples(tiny_world, trained_runs, tmp_path):
    """Plain-3DGS runs (the paper's "3DGS" row) bundle and stream like mesh-bound ones."""
    from conftest import tiny_srm

    from hogsa_loader import HOGSADataset
    from hogsa_loader.models.bundle import write_bundle
    from hogsa_loader.sample import LoaderConfig, is_synthetic, with_options
    from hogsa_loader.view.pictures import demo_photographs

    _, free_run, _ = trained_runs
    bundle = write_bundle(tmp_path / "bundle", tiny_world, [free_run], srm=tiny_srm(tmp_path / "srm"))
    for part in ("hand_right", "hand_left", "object"):
        assert json.loads((bundle / "hogs" / "s01_box" / part / "manifest.json").read_text())["variant"] == "free"
    options = dict(srm=True, poses="perturb", batch_size=2, num_samples=2)
    options["background_folder"] = str(demo_photographs(tmp_path / "photos"))
    samples = list(HOGSADataset(bundle, tiny_world, with_options(LoaderConfig(), **options)))
    assert len(samples) == 2
    for inputs, targets, meta in samples:
        assert inputs["img"].shape[0] == 3 and torch.isfinite(inputs["img"]).all() and inputs["img"].std() > 0
        assert is_synthetic(meta["imgname"]) and torch.isfinite(targets["mano.j3d.full.r"]).all()


def test_hogs_model_renders_like_the_trainer(tiny_world, trained_runs):
    mesh_run, _, trainer = trained_runs
    root = ArcticRoot(tiny_world)
    model = HogsModel.from_run(mesh_run, root.mano_layers(), root.object_templates())
    assert model.object_name == "box" and model.source["subject"] == "s01"
    assert model.num_gaussians == sum(p.num_gaussians for p in trainer.parts.values())
    samples = trainer.data.eval[:2]
    rgb_t, alpha_t = trainer.render(samples)
    poses = trainer.data.poses(samples)
    vm = torch.as_tensor(torch.stack([torch.as_tensor(s.world2cam) for s in samples]), dtype=torch.float32)[:, None]
    K = torch.as_tensor(torch.stack([torch.as_tensor(s.K) for s in samples]), dtype=torch.float32)[:, None]
    out = model.render(poses, vm, K, 64, 64, render_mode="RGB")
    torch.testing.assert_close(out.rgb[:, 0], rgb_t, atol=1e-5, rtol=0)
    torch.testing.assert_close(out.alpha[:, 0, ..., 0], alpha_t, atol=1e-5, rtol=0)
    assert out.part_alpha.shape[-1] == 3
    with pytest.raises(KeyError, match="obj_arti"):
        model.scene({k: v for k, v in poses.items() if k != "obj_arti"})


def test_hogs_model_errors(tiny_world, trained_runs, tmp_path):
    mesh_run, _, _ = trained_runs
    root = ArcticRoot(tiny_world)
    broken = tmp_path / "broken"
    shutil.copytree(mesh_run, broken)
    shutil.rmtree(broken / "hand_left")
    with pytest.raises(AssetError, match=r"missing part checkpoint\(s\) \['hand_left'\]"):
        HogsModel.from_run(broken, root.mano_layers(), root.object_templates())
    templates = {k: v for k, v in root.object_templates().items() if k != "box"}
    with pytest.raises(AssetError, match="'box' is not among the given templates"):
        HogsModel.from_run(mesh_run, root.mano_layers(), templates)
    swapped = {"right": root.mano_layers()["left"], "left": root.mano_layers()["right"]}
    with pytest.raises(AssetError, match="hand_right"):
        HogsModel.from_run(mesh_run, swapped, root.object_templates())


def test_render_quality_matches_training_metrics(tiny_world, trained_runs, tmp_path):
    mesh_run, free_run, _ = trained_runs
    rq = importlib.import_module("experiments.render_quality")
    out = tmp_path / "q.json"
    png = tmp_path / "q.png"
    assert (
        rq.main(
            [
                "--data",
                str(tiny_world),
                "--run",
                f"{mesh_run},{free_run}",
                "--json",
                str(out),
                "--png",
                str(png),
                "--max-eval",
                "3",
                "--png-rows",
                "2",
            ]
        )
        == 0
    )
    q = json.loads(out.read_text())
    for key in ("psnr", "ssim", "lpips", "per_view", "runs", "lpips_note"):
        assert key in q
    assert q["lpips"] is None or 0.0 <= q["lpips"] <= 1.0
    assert [r["label"] for r in q["runs"]] == ["mesh", "free"]
    assert q["per_view"][0]["view"] == 8 and q["per_view"][0]["n"] == 3
    for run, r in zip((mesh_run, free_run), q["runs"]):
        m = json.loads((run / "metrics.json").read_text())
        # same split, same metric code: the benchmark reproduces the trainer's final figures
        assert r["psnr"] == pytest.approx(m["psnr"], abs=1e-6)
        assert r["ssim"] == pytest.approx(m["ssim"], abs=1e-6)
    assert png.stat().st_size > 2000


def test_train_all_hogs_selection_array_and_skip(tiny_world, tmp_path, capsys, monkeypatch):
    ta = job("train_all_hogs")
    root = ArcticRoot(tiny_world)
    every = ["--data", str(tiny_world), "--out", str(tmp_path), "--split", "all", "--allow-held-out", "s05"]
    args, _ = ta.parse_args(every)
    with pytest.warns(UserWarning, match="held-out"):
        pairs = ta.list_pairs(root, args)
    assert pairs == sorted(pairs) and {(s, o) for s, o, _ in pairs} == {
        (sid_seq.split("/")[0], sid_seq.split("/")[1].split("_")[0]) for sid_seq in root.sequences()
    }
    default, _ = ta.parse_args(["--data", str(tiny_world), "--out", str(tmp_path)])  # the training split
    assert [(s, o) for s, o, _ in ta.list_pairs(root, default)] == [("s01", "box")]
    monkeypatch.setenv("SLURM_ARRAY_TASK_ID", "1")
    monkeypatch.setenv("SLURM_ARRAY_TASK_COUNT", "2")
    assert ta.array_slot(args) == (1, 2)
    monkeypatch.delenv("SLURM_ARRAY_TASK_ID")
    monkeypatch.setenv("WORLD_SIZE", "3")
    monkeypatch.setenv("RANK", "2")
    assert ta.array_slot(args) == (2, 3)
    monkeypatch.delenv("WORLD_SIZE")
    monkeypatch.delenv("RANK")
    monkeypatch.delenv("SLURM_ARRAY_TASK_COUNT")

    out = tmp_path / "runs"
    sel = ["--data", str(tiny_world), "--out", str(out), "--subjects", "s01", "--objects", "box"]
    assert ta.main(sel + ["--", "--optim-iters", "2", *FAST]) == 0
    assert HogsModel.is_run(out / "s01_box") and (out / "s01_box" / "metrics.json").is_file()
    stamp = (out / "s01_box" / "metrics.json").stat().st_mtime_ns
    capsys.readouterr()
    assert ta.main(sel + ["--", "--optim-iters", "2", *FAST]) == 0
    assert "s01_box: finished, skipped" in capsys.readouterr().out
    assert (out / "s01_box" / "metrics.json").stat().st_mtime_ns == stamp
    summary = json.loads((out / "summary.json").read_text())
    assert summary["num_finished"] == 1 and summary["runs"][0]["subject"] == "s01"
    assert ta.main(["--data", str(tiny_world), "--out", str(out), "--objects", "mug", "--dry-run"]) == 2


def test_lr_overrides_and_opacity_warmup(tiny_world, tmp_path):
    with pytest.raises(ValueError, match="unknown parameters \\['opacity'\\]"):
        HogsTrainer(_cfg(tiny_world, tmp_path / "r", lr_overrides={"opacity": 0.1}), progress=False)
    tr = HogsTrainer(_cfg(tiny_world, tmp_path / "r", lr_overrides={"sh_dc": 0.0}, opacity_warmup=2), progress=False)
    op0 = tr.parts["object"].splats.opacity_logits.detach().clone()
    dc0 = tr.parts["object"].splats.sh_dc.detach().clone()
    sc0 = tr.parts["object"].splats.log_scale_factor.detach().clone()
    tr.train_step()
    tr.train_step()
    assert torch.equal(tr.parts["object"].splats.opacity_logits, op0)  # frozen during warm-up
    assert torch.equal(tr.parts["object"].splats.sh_dc, dc0)  # lr 0 by override
    assert not torch.equal(tr.parts["object"].splats.log_scale_factor, sc0)
    tr.train_step()
    assert not torch.equal(tr.parts["object"].splats.opacity_logits, op0)


def test_directional_light_shading_and_checkpoint(tmp_path):
    from hogsa_loader.models.gaussians import GaussianSet, rgb_to_sh
    from hogsa_loader.models.gaussians.shading import DirectionalLight, load_light, save_light

    light = DirectionalLight(direction=(0.0, 0.0, 2.0), ambient=0.3, diffuse=0.6)
    n = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    # facing the light: ambient + diffuse; facing away / grazing: ambient only
    torch.testing.assert_close(light.shade(n).flatten(), torch.tensor([0.9, 0.3, 0.3]), atol=1e-5, rtol=0)
    rgb = torch.tensor([[0.8, 0.4, 0.2], [0.5, 0.5, 0.5], [0.1, 0.9, 0.3]])
    scene = GaussianSet(
        means=torch.zeros(1, 3, 3),
        quats=torch.tensor([[1.0, 0, 0, 0]]).expand(1, 3, 4),
        scales=torch.full((1, 3, 3), 0.01),
        opacities=torch.ones(1, 3),
        sh=rgb_to_sh(rgb)[None, :, None, :],
        sh_degree=0,
        part_ids=torch.zeros(3, dtype=torch.long),
        normals=n[None],
    )
    vm = torch.eye(4)[None, None].clone()
    vm[..., 2, 3] = 1.0
    cols = light(scene, vm)
    torch.testing.assert_close(cols[0, 0], rgb * torch.tensor([[0.9], [0.3], [0.3]]), atol=1e-5, rtol=0)
    save_light(light, tmp_path / "light")
    back = load_light(tmp_path / "light")
    for (k, a), (_, b) in zip(light.state_dict().items(), back.state_dict().items()):
        assert torch.equal(a, b), k
    man = (tmp_path / "light" / "manifest.json").read_text()
    (tmp_path / "light" / "manifest.json").write_text(man.replace('"model"', '"ambient_note": NaN, "model"'))
    with pytest.raises(AssetError, match="manifest.json.*NaN is not a JSON value"):
        load_light(tmp_path / "light")
    good = (tmp_path / "light" / "light.safetensors").read_bytes()
    bad_light = DirectionalLight(direction=(0.0, 0.0, 2.0), ambient=0.3, diffuse=0.6)
    with torch.no_grad():
        next(bad_light.parameters()).fill_(float("nan"))
    with pytest.raises(ValueError, match="NaN or infinity; not saved"):  # refused before anything is written
        save_light(bad_light, tmp_path / "light")
    assert (tmp_path / "light" / "light.safetensors").read_bytes() == good
    # the manifest's checksum ties it to its tensors: another light's tensors are refused
    save_light(DirectionalLight(direction=(1.0, 0.0, 0.0)), tmp_path / "other")
    (tmp_path / "light" / "manifest.json").write_text(man)
    (tmp_path / "light" / "light.safetensors").write_bytes((tmp_path / "other" / "light.safetensors").read_bytes())
    with pytest.raises(AssetError, match="light.safetensors.*sha256 does not match manifest.json"):
        load_light(tmp_path / "light")
    (tmp_path / "light" / "manifest.json").write_text('{"format": "hogsa-light", "schema_version": 9}')
    with pytest.raises(AssetError, match="schema_version 9"):
        load_light(tmp_path / "light")
    with pytest.raises(ValueError, match="normals"):
        light(GaussianSet(**{**scene.__dict__, "normals": None}), vm)


def test_lambert_run_saves_and_reloads_its_light(tiny_world, tmp_path):
    tr = HogsTrainer(_cfg(tiny_world, tmp_path / "lit", iters=3, shading="lambert"), progress=False)
    d0 = tr.model.light.unit_direction().detach().clone()
    # starts as the mean viewing direction of the training cameras
    fwd = torch.tensor([s.world2cam[2, :3] for s in tr.data.train]).float().mean(0)
    torch.testing.assert_close(d0, fwd / fwd.norm(), atol=1e-5, rtol=0)
    m = tr.train()
    assert m["shading"] == "lambert" and m["light"]["ambient"] > 0
    assert not torch.equal(tr.model.light.unit_direction().detach(), d0)  # learnt
    root = ArcticRoot(tiny_world)
    model = HogsModel.from_run(tmp_path / "lit", root.mano_layers(), root.object_templates())
    assert model.light is not None
    samples = tr.data.eval[:1]
    rgb_t, _ = tr.render(samples)
    vm = torch.as_tensor(samples[0].world2cam, dtype=torch.float32)[None, None]
    K = torch.as_tensor(samples[0].K, dtype=torch.float32)[None, None]
    out = model.render(tr.data.poses(samples), vm, K, 64, 64, render_mode="RGB")
    torch.testing.assert_close(out.rgb[:, 0], rgb_t, atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="shading must be one of"):
        HogsTrainer(_cfg(tiny_world, tmp_path / "x", shading="phong"), progress=False)
