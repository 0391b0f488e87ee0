"""``hogsa demo`` end to end on the tiny world at toy sizes: outputs, caching, the mixed batch."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from hogsa_loader.sample import is_synthetic
from hogsa_world.demo import DemoConfig, run_demo, unbatch

CFG = dict(
    pairs=(("s01", "box"),),
    hogs_iters=6,
    hogs_image_size=64,
    hogs_frame_stride=4,
    contactnet_iters=10,
    bank_per_sequence=2,
    srm_iters=2,
    srm_crop=32,
    samples=8,
    batch_size=4,
    num_workers=0,
    render_batch=4,
    grid_rows=2,
    grid_cols=4,
    orbit_views=4,
    orbit_size=32,
    progress=False,
)


@pytest.fixture(scope="module")
def demo(tiny_world, tmp_path_factory):
    before = torch.get_num_threads()
    torch.set_num_threads(1)  # restored below for the module's later tests
    try:
        out = tmp_path_factory.mktemp("demo")
        cfg = DemoConfig(data=str(tiny_world), **CFG)
        first = run_demo(out, cfg, log=None)
        second = run_demo(out, cfg, log=None)
    finally:
        torch.set_num_threads(before)
    return out, first, second


def test_demo_writes_grid_batch_and_record(demo):
    out, first, _ = demo
    assert first["reused_stages"] == []
    rec = json.loads((out / "demo.json").read_text())
    assert rec["stream"]["samples_kept"] + rec["stream"]["dropped"] == 8
    assert rec["stream"]["samples_kept"] > 0 and rec["stream"]["images_per_s"] > 0
    grid = cv2.imread(str(out / "samples.png"))
    # two synthetic rows (pose bank, perturbed grasps) + one real row of 4 cells of 224 px (the patch size)
    assert grid is not None and grid.shape[0] > 3 * 224 and grid.shape[1] > 4 * 224
    # labels are drawn: the right-hand red appears in the grid
    b, g, r = grid[..., 0].astype(int), grid[..., 1].astype(int), grid[..., 2].astype(int)
    assert ((r > 200) & (g < 90) & (b < 70)).sum() > 20
    z = np.load(out / "batch.npz")
    assert cv2.imread(str(out / "samples_clean.png")).shape == grid.shape
    assert z["inputs/img"].shape == (4, 3, 224, 224)
    names = z["meta_info/imgname"].tolist()
    assert sum(is_synthetic(n) for n in names) == 2  # ratio 0.5 of a batch of 4
    orbit = rec["outputs"]["orbit"]  # the 360° orbit of the first model, with and without SRM
    assert cv2.imread(orbit["png"]) is not None and orbit["video"].endswith(".gif")
    assert json.loads((out / "view" / "view.json").read_text())["orbits"]["s01"]["views"] == 4


def test_demo_second_run_reuses_every_stage(demo):
    _, first, second = demo
    built = set(first["stage_seconds"])
    assert {"hogs/s01_box", "contactnet", "bank", "srm", "bundle"} <= built
    assert set(second["reused_stages"]) == built
    assert all(v == 0.0 for v in second["stage_seconds"].values())


def test_demo_rebuilds_a_stage_whose_settings_changed(demo, tiny_world):
    out, _, _ = demo
    renders = sorted((out / "cache" / "srm").glob("coarse_*.safetensors"))
    assert renders
    stale = out / "cache" / "srm" / "coarse_s01_box_0123456789abcdef.safetensors"  # e.g. of older HOGS weights
    stale.write_bytes(renders[0].read_bytes())
    cfg = DemoConfig(data=str(tiny_world), **{**CFG, "srm_iters": 3, "samples": 4})
    rec = run_demo(out, cfg, log=None)
    assert "srm" not in rec["reused_stages"] and "bundle" not in rec["reused_stages"]
    # same HOGS: no new renders, and the entry the rebuild did not use is gone
    assert sorted((out / "cache" / "srm").glob("coarse_*.safetensors")) == renders
    assert {"hogs/s01_box", "contactnet", "bank"} <= set(rec["reused_stages"])


def test_free_gaussians_build_the_same_stages_in_their_own_folder(tiny_world, tmp_path, monkeypatch):
    """``gaussians="free"``: ``hogsa build`` with plain 3D Gaussians and every other setting
    the same, in ``OUT/free`` (streaming a bundle of free runs: tests/train/test_hogs_tools.py)."""
    import hogsa_world.demo as demo_module

    built = []
    monkeypatch.setattr(demo_module, "build", lambda config, **kw: (built.append(config), (Path("b"), {}))[1])
    cfg = DemoConfig(data=str(tiny_world), **CFG)
    for gaussians in ("mesh", "free"):
        demo_module.build_bundle_stages(tmp_path, cfg, log=None, gaussians=gaussians)
    mesh, free = built
    assert (Path(mesh.run.out), Path(free.run.out)) == (tmp_path, tmp_path / "free")
    assert (mesh.hogs.model.gaussians, free.hogs.model.gaussians) == ("mesh", "free")
    assert mesh == demo_module.build_config(cfg, Path(tiny_world), tmp_path)  # the demo's own build, as before
    same = dataclasses.replace(free, run=mesh.run, hogs=dataclasses.replace(free.hogs, model=mesh.hogs.model))
    assert same == mesh


def test_unbatch_inverts_default_collate():
    from torch.utils.data import default_collate

    items = [
        (
            {"img": torch.full((3, 2, 2), float(i))},
            {"v": float(i), "j": torch.ones(2) * i},
            {"name": f"n{i}", "q": ["a", "b"]},
        )
        for i in range(3)
    ]
    batch = default_collate(items)
    one = unbatch(batch, 2)
    assert torch.equal(one[0]["img"], items[2][0]["img"])
    assert float(one[1]["v"]) == 2.0 and torch.equal(one[1]["j"], items[2][1]["j"])
    assert one[2]["name"] == "n2"


def test_demo_world_preset_holds_what_the_demo_uses():
    from hogsa_world import get_preset

    cfg = DemoConfig()
    preset = get_preset(cfg.preset)
    have = {(s.sid, q.object) for s in preset.subjects for q in s.sequences if s.split == "train"}
    assert set(cfg.pairs) <= have  # every HOGS model trains on the world's training split
    assert any(s.split == "val" for s in preset.subjects)  # ContactNet validates on a held-out subject
    assert preset.cropped_size == 1000 and preset.num_frames >= 52  # ARCTIC's crop size, ARCTIC's frame floor
    assert sum(len(s.sequences) for s in preset.subjects) < sum(len(s.sequences) for s in get_preset("small").subjects)
