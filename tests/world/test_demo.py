"""``hogsa demo`` end to end on the tiny world at toy sizes: outputs, caching, the mixed batch."""

from __future__ import annotations

import json
import os
import sys

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
    torch.set_num_threads(1)  # restored below: later tests compare against 2-thread subprocesses
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


def test_bank_stage_key_holds_finger_noise_variants_and_frames_only_when_asked(tiny_world, monkeypatch):
    from dataclasses import replace
    from pathlib import Path

    from hogsa_world.demo import _bank_node

    cfg = DemoConfig(data=str(tiny_world), pairs=(("s01", "box"),), bank_per_sequence=2)

    def key(c: DemoConfig) -> str:
        return _bank_node(c, Path("/x/bank"), Path(tiny_world), Path("/x/cn"), "k").key

    # pinned: the default finger scale (0), variants (1) and frames ("contact") add nothing to the key; the
    # frame margin (10) is keyed, since the banks built before it could start from a sequence's ends
    assert key(cfg) == "be8477e3deb340e0"
    # pinned: the key of a finger scale alone, unchanged by the keying of variants
    assert key(replace(cfg, bank_finger_scale=0.5)) == "74243f9e94bd04b6"
    keys = {
        key(replace(cfg, bank_finger_scale=f, bank_variants=v, bank_frames=w))
        for f in (0.0, 0.25, 0.5)
        for v in (1, 3)
        for w in ("contact", "all")
    }
    assert len(keys) == 12
    # and the stage builds its bank with them
    seen = []
    monkeypatch.setattr(
        "hogsa_world.demo.build_pose_bank",
        lambda c, progress: seen.append((c.pom.finger_scale, c.data.variants, c.data.frames)),
    )
    _bank_node(
        replace(cfg, bank_finger_scale=0.5, bank_variants=3, bank_frames="all"),
        Path("/x/bank"),
        Path(tiny_world),
        Path("/x/cn"),
        "k",
    ).build()
    assert seen == [(0.5, 3, "all")]


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


def _timed_stage(folder, log, name: str, seconds: float):
    """A stage build that logs its start and end times and creates its output folder."""
    import time

    def build() -> str:
        with open(log, "a") as f:
            f.write(f"start {name} {time.time()}\n")
        time.sleep(seconds)
        (folder / name).mkdir()
        with open(log, "a") as f:
            f.write(f"end {name} {time.time()}\n")
        return name

    return build


def test_stage_graph_runs_each_stage_after_what_it_needs(tmp_path):
    """Stages start only once the stages they need have ended (side by side on forked
    processes where there are two cores, else in order); a second run reuses all of them."""
    from hogsa_world.demo import _run_stage_graph, _StageNode, _Stages

    log = tmp_path / "log.txt"
    nodes = [
        _StageNode("a", "ka", [tmp_path / "a"], _timed_stage(tmp_path, log, "a", 0.4)),
        _StageNode("b", "kb", [tmp_path / "b"], _timed_stage(tmp_path, log, "b", 0.1)),
        _StageNode("c", "kc", [tmp_path / "c"], _timed_stage(tmp_path, log, "c", 0.0), needs=("a", "b")),
        _StageNode("d", "kd", [tmp_path / "d"], _timed_stage(tmp_path, log, "d", 0.0), needs=("b",)),
    ]
    stages = _Stages(tmp_path / "out", lambda s: None)
    _run_stage_graph(stages, nodes, DemoConfig(progress=False), lambda s: None)
    t = {tuple(line.split()[:2]): float(line.split()[2]) for line in log.read_text().splitlines()}
    assert len(t) == 8
    assert t["start", "c"] >= max(t["end", "a"], t["end", "b"])
    assert t["start", "d"] >= t["end", "b"]
    if sys.platform.startswith("linux") and len(os.sched_getaffinity(0)) > 1:  # side by side
        assert t["start", "b"] < t["end", "a"] and t["start", "a"] < t["end", "b"]
    assert set(stages.seconds) == {"a", "b", "c", "d"} and stages.reused == []
    again = _Stages(tmp_path / "out", lambda s: None)
    _run_stage_graph(again, nodes, DemoConfig(progress=False), lambda s: None)
    assert sorted(again.reused) == ["a", "b", "c", "d"]
    assert len(log.read_text().splitlines()) == 8  # nothing was built again

    def broken() -> None:
        raise RuntimeError("stage failed on purpose")

    bad = [
        _StageNode("e", "ke", [tmp_path / "e"], broken),
        _StageNode("f", "kf", [tmp_path / "f"], _timed_stage(tmp_path, log, "f", 0.0)),
    ]
    with pytest.raises(RuntimeError, match="on purpose"):
        _run_stage_graph(_Stages(tmp_path / "out", lambda s: None), bad, DemoConfig(progress=False), lambda s: None)
    with pytest.raises(ValueError, match="not listed before it"):
        _run_stage_graph(
            _Stages(tmp_path / "out", lambda s: None),
            [_StageNode("g", "kg", [tmp_path / "g"], broken, needs=("h",))],
            DemoConfig(progress=False),
            lambda s: None,
        )


def test_srm_stage_key_holds_the_adversarial_weight_only_when_asked(tiny_world, monkeypatch):
    """Without an adversarial term the SRM stage keeps the key it had before the setting existed
    (its cached builds stay valid); with one it is another stage, trained with that weight."""
    from dataclasses import replace
    from pathlib import Path

    from hogsa_world.demo import _key, _srm_node, _StageNode

    cfg = DemoConfig(data=str(tiny_world), pairs=(("s01", "box"),), srm_iters=4)
    hogs = [_StageNode("hogs/s01_box", "h1", [Path("/x/hogs/s01_box")], lambda: None)]

    def node(c: DemoConfig) -> _StageNode:
        return _srm_node(c, Path("/x"), Path(tiny_world), hogs)

    assert node(cfg).key == _key("srm", ["h1"], 4, cfg.srm_crop, cfg.srm_augment)
    assert node(replace(cfg, srm_gan=1.0)).key not in {node(cfg).key, node(replace(cfg, srm_gan=0.5)).key}
    assert node(replace(cfg, srm_gan=1)).key == node(replace(cfg, srm_gan=1.0)).key
    seen = []

    class Built(Exception):
        pass

    def trainer(c, **kwargs):
        seen.append(c.loss.lambda_gan)
        raise Built

    monkeypatch.setattr("hogsa_world.demo.SRMTrainer", trainer)
    for gan in (0.0, 1.0):
        with pytest.raises(Built):
            node(replace(cfg, srm_gan=gan)).build()
    assert seen == [0.0, 1.0] and node(cfg).needs == ("hogs/s01_box",)
