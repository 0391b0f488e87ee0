"""experiments/heldout.py: finished models on a held-out root, with the uncertainty over clips."""

from __future__ import annotations

import importlib
import json
import shutil

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader, Subset

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.baselines import ArcticNetSF, BodyLayers, evaluate, load_arctic_checkpoint, temporal_order
from hogsa_loader.io.tensors import write_tensors_and_manifest
from hogsa_loader.sample.arctic_dataset import ArcticDataset
from hogsa_loader.sample.augment import ArcticConfig

RES = 32


def _heldout():
    return importlib.import_module("experiments.heldout")


def _save(folder, root, seed: int, **extra) -> None:
    layers = BodyLayers.from_root(ArcticRoot(root))
    torch.manual_seed(seed)
    net = ArcticNetSF("resnet18", layers.mano_r, layers.mano_l, layers.objects, focal_length=1000.0, img_res=RES)
    state = {k: v.detach().clone().contiguous() for k, v in net.network_state_dict().items()}
    settings = {"data": str(root), "seed": seed, "model": {"backbone": "resnet18", "img_res": RES}}
    settings.update(extra)
    write_tensors_and_manifest(folder, "model.safetensors", state, "model.json", {"settings": settings})
    (folder / "result.json").write_text(json.dumps({"settings": settings, "summary": {}}))


def test_runs_are_evaluated_once_and_paired_over_clips(tiny_world, tmp_path, monkeypatch):
    """Each label's models are evaluated on the split as ``evaluate`` does; the paired
    difference is the difference of the summaries, with an interval over the split's clips;
    a second run reads the cache."""
    hd = _heldout()
    for label, seeds in (("real", (1, 2)), ("hogsa", (3, 4))):
        for s, init in zip((0, 1), seeds):
            _save(tmp_path / label / f"seed{s}", tiny_world, init)
    cfg = hd.HeldoutConfig(
        data=str(tiny_world),
        runs=(f"real={tmp_path / 'real'}", f"hogsa={tmp_path / 'hogsa'}"),
        splits=("p1_val",),
        out=str(tmp_path / "out"),
        threads=1,
    )
    rec = hd.run(cfg)["reports"]["p1_val"]
    ds = ArcticDataset(tiny_world, split="p1_val", seed=0, augment=False, config=ArcticConfig(img_res=RES))
    layers = BodyLayers.from_root(ArcticRoot(tiny_world))
    model = ArcticNetSF("resnet18", layers.mano_r, layers.mano_l, layers.objects, focal_length=1000.0, img_res=RES)
    load_arctic_checkpoint(model, tmp_path / "real" / "seed0" / "model.safetensors")
    loader = DataLoader(Subset(ds, temporal_order(ds.imgnames)), batch_size=32)
    direct = evaluate(model, loader, layers, RES, temporal=False)["summary"]
    views = {n.split("/")[-2] for n in ds.imgnames}
    assert rec["frames"] == len(ds) and rec["clips"] == len(views) > 1
    saved = json.loads((tmp_path / "out" / "heldout.json").read_text())["reports"]["p1_val"]
    cached = sorted((tmp_path / "out" / "cache").glob("*-p1_val.json"))
    assert len(cached) == 4
    real0 = next(json.loads(p.read_text()) for p in cached if "real/seed0" in json.loads(p.read_text())["model"])
    assert real0["summary"]["mpjpe/ra/h"] == pytest.approx(direct["mpjpe/ra/h"], rel=1e-5)
    assert real0["summary"]["cdev/ho"] == pytest.approx(direct["cdev/ho"], rel=1e-5)
    for hand in ("mpjpe/ra/r", "mpjpe/ra/l"):  # each hand's MPJPE, also paired over clips
        assert real0["summary"][hand] == pytest.approx(direct[hand], rel=1e-5)
        dh = saved["paired"]["hogsa"][hand]
        assert dh["mean"] == pytest.approx(np.mean(list(dh["per_seed"].values())))
        assert dh["clips"]["estimate"] == pytest.approx(dh["mean"], abs=1e-4)
    d = saved["paired"]["hogsa"]["mpjpe/ra/h"]
    assert d["mean"] == pytest.approx(np.mean(list(d["per_seed"].values())))
    assert d["clips"]["estimate"] == pytest.approx(d["mean"], abs=1e-4)  # the clip sums form the summaries again
    assert d["clips"]["ci95"][0] <= d["clips"]["estimate"] <= d["clips"]["ci95"][1]
    md = (tmp_path / "out" / "heldout.md").read_text()
    assert f"**p1_val** ({len(ds)} frames, {len(views)} clips)" in md and md.count("| hogsa | ") == 3
    assert "| − real, per hand | ΔMPJPE right per seed |" in md
    right = saved["paired"]["hogsa"]["mpjpe/ra/r"]["per_seed"].values()
    lines = md.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("| − real, per hand"))
    hand_row = next(line for line in lines[start:] if line.startswith("| hogsa | "))
    assert hand_row.startswith("| hogsa | " + ", ".join(f"{v:+.2f}" for v in right) + " | ")

    def no_evaluation(*a, **k):
        raise AssertionError("evaluated again")

    monkeypatch.setattr(hd, "evaluate", no_evaluation)
    assert hd.run(cfg)["reports"]["p1_val"]["paired"]["hogsa"]["mpjpe/ra/h"]["mean"] == pytest.approx(d["mean"])


def test_two_splits_are_also_reported_together(tiny_world, tmp_path):
    """Two splits give a third report over the clips of both, frame-weighted."""
    hd = _heldout()
    recs = [
        {"frames": 3, "clips": {"s05/a/1": {"mpjpe/ra/h": [30.0, 3.0], "cdev/ho": [3.0, 3.0]}}},
        {"frames": 1, "clips": {"s03/a/1": {"mpjpe/ra/h": [50.0, 1.0], "cdev/ho": [0.0, 0.0]}}},
    ]
    hands = ({"mpjpe/ra/r": [24.0, 3.0], "mpjpe/ra/l": [36.0, 3.0]}, {"mpjpe/ra/r": [50.0, 1.0], "mpjpe/ra/l": [0, 0]})
    for rec, h in zip(recs, hands):
        next(iter(rec["clips"].values())).update(h)
    both = hd.merged(recs)
    assert both["frames"] == 4 and both["summary"]["mpjpe/ra/h"] == pytest.approx(20.0)
    assert both["summary"]["mpjpe/ra/r"] == pytest.approx(18.5) and both["summary"]["mpjpe/ra/l"] == pytest.approx(12)
    assert both["summary"]["cdev/ho"] == pytest.approx(1.0) and len(both["clips"]) == 2


@pytest.mark.parametrize(
    ("runs", "message"),
    [
        (("real",), "LABEL=FOLDER"),
        (("real={empty}",), "no finished run"),
        (("other={ok}",), "--reference 'real'"),
        ((), "no runs given"),
    ],
)
def test_bad_runs_are_refused_with_what_is_wrong(tiny_world, tmp_path, capsys, runs, message):
    hd = _heldout()
    _save(tmp_path / "ok" / "seed0", tiny_world, 0)
    (tmp_path / "empty").mkdir()
    runs = tuple(r.format(empty=tmp_path / "empty", ok=tmp_path / "ok") for r in runs)
    with pytest.raises(SystemExit, match=message):
        hd.run(hd.HeldoutConfig(data=str(tiny_world), runs=runs, out=str(tmp_path / "out")))


def test_a_missing_split_and_other_bodies_are_refused(tiny_world, tmp_path):
    hd = _heldout()
    _save(tmp_path / "real" / "seed0", tiny_world, 0)
    runs = (f"real={tmp_path / 'real'}",)
    with pytest.raises(SystemExit, match="p1_test.npy does not exist"):
        hd.run(hd.HeldoutConfig(data=str(tiny_world), runs=runs, splits=("p1_test",), out=str(tmp_path / "o")))
    with pytest.raises(SystemExit, match="names like p1_val"):
        hd.run(hd.HeldoutConfig(data=str(tiny_world), runs=runs, splits=("val",), out=str(tmp_path / "o")))
    other = tmp_path / "other"
    shutil.copytree(tiny_world, other, ignore=shutil.ignore_patterns("cropped_images", "masks"))
    ctx = hd._context(hd.HeldoutConfig(data=str(other), runs=runs, splits=("p1_val",), out=str(tmp_path / "o")))
    hd.check_bodies({"data": str(tiny_world)}, tmp_path / "m", ctx)
    hd.check_bodies({"data": str(tmp_path / "gone")}, tmp_path / "m2", ctx)  # a training root not on disk
    assert ctx.unchecked == [str(tmp_path / "m2")]
    meta = other / "arctic_data" / "data" / "meta" / "object_meta.json"
    diameters = json.loads(meta.read_text())
    diameters["box"]["diameter"] = float(diameters["box"]["diameter"]) * 1.01  # the success rate's scale
    meta.write_text(json.dumps(diameters))
    ctx = hd._context(hd.HeldoutConfig(data=str(other), runs=runs, splits=("p1_val",), out=str(tmp_path / "o")))
    with pytest.raises(SystemExit, match="MANO models or object templates differ"):
        hd.check_bodies({"data": str(tiny_world)}, tmp_path / "m", ctx)


def test_only_finished_runs_of_one_setting_are_read(tiny_world, tmp_path):
    """A seed folder whose run diverged, is unfinished or left an older model is skipped; seeds
    run with other settings are refused."""
    hd = _heldout()
    for s in range(4):
        _save(tmp_path / "a" / f"seed{s}", tiny_world, s)
    diverged = json.loads((tmp_path / "a" / "seed1" / "result.json").read_text())
    (tmp_path / "a" / "seed1" / "result.json").write_text(json.dumps({**diverged, "diverged": 3}))
    (tmp_path / "a" / "seed2" / "result.json").unlink()
    (tmp_path / "a" / "seed3" / "result.json").write_text(json.dumps({"settings": {"other": 1}}))
    assert list(hd.finished_models("a", tmp_path / "a")) == [0]
    _save(tmp_path / "c" / "seed0", tiny_world, 0, model={"backbone": "resnet18", "img_res": RES, "init_sha256": "a"})
    _save(tmp_path / "c" / "seed1", tiny_world, 1, model={"backbone": "resnet18", "img_res": RES, "init_sha256": "b"})
    assert list(hd.finished_models("c", tmp_path / "c")) == [0, 1]  # seeds start from their own files
    _save(tmp_path / "b" / "seed0", tiny_world, 0, train={"steps": 10})
    _save(tmp_path / "b" / "seed1", tiny_world, 1, train={"steps": 5})
    with pytest.raises(SystemExit, match="differ in settings beyond their seeds"):
        hd.finished_models("b", tmp_path / "b")


def test_a_cache_entry_is_used_only_for_its_model_and_split_data(tmp_path):
    hd = _heldout()
    path = tmp_path / "c.json"
    rec = {"version": hd.CACHE_VERSION, "model_sha256": "m", "data_fingerprint": "d", "summary": {}}
    path.write_text(json.dumps(rec))
    assert hd._read_cache(path, "m", "d") == rec
    assert hd._read_cache(path, "m", "other data") is None and hd._read_cache(path, "other model", "d") is None
    path.write_text(json.dumps(rec)[:20])  # an interrupted write
    assert hd._read_cache(path, "m", "d") is None
