"""experiments/domain_gap.py: the task model's view of real and synthetic frames."""

from __future__ import annotations

import importlib
import math

import pytest
import torch

from hogsa_loader.errors import AssetError


def _gap():
    return importlib.import_module("experiments.domain_gap")


def _save_model(folder, backbone: str, manifest_backbone: str, img_res: int, root) -> dict:
    from hogsa_loader.assets.arctic import ArcticRoot
    from hogsa_loader.baselines.arcticnet_sf import ArcticNetSF
    from hogsa_loader.baselines.engine import BodyLayers
    from hogsa_loader.io.tensors import write_tensors_and_manifest

    layers = BodyLayers.from_root(ArcticRoot(root))
    torch.manual_seed(3)
    net = ArcticNetSF(backbone, layers.mano_r, layers.mano_l, layers.objects, focal_length=1000.0, img_res=img_res)
    state = {k: v.detach().clone().contiguous() for k, v in net.network_state_dict().items()}
    settings = {"model": {"backbone": manifest_backbone, "img_res": img_res}}
    write_tensors_and_manifest(folder, "model.safetensors", state, "model.json", {"settings": settings})
    return state


def test_task_model_is_a_downstream_runs_model_loaded_whole(tiny_world, tmp_path):
    """The default model is the real arm's seed-0 model; it loads with the backbone and patch
    side its manifest names, every tensor as saved; 'none' and a folder without runs skip it."""
    gap = _gap()
    folder = tmp_path / "runs" / "real" / "seed0"
    state = _save_model(folder, "resnet18", "resnet18", 32, tiny_world)
    assert gap.task_model_path(tmp_path, None) == folder / "model.safetensors"
    assert gap.task_model_path(tmp_path, "none") is None
    assert gap.task_model_path(tmp_path / "elsewhere", None) is None
    model, _, res = gap.load_task_model(folder / "model.safetensors", tiny_world)
    assert res == 32 and not model.training
    got = model.network_state_dict()
    assert got.keys() == state.keys() and all(torch.equal(got[k], state[k]) for k in state)


def test_task_model_files_that_do_not_fit_are_refused_by_name(tiny_world, tmp_path):
    gap = _gap()
    _save_model(tmp_path / "a", "resnet18", "resnet50", 32, tiny_world)  # manifest says another backbone
    with pytest.raises(AssetError, match="a/model.safetensors"):
        gap.load_task_model(tmp_path / "a" / "model.safetensors", tiny_world)
    _save_model(tmp_path / "b", "resnet18", "resnet18", 32, tiny_world)
    (tmp_path / "b" / "model.json").unlink()
    with pytest.raises(AssetError, match="b/model.json"):
        gap.load_task_model(tmp_path / "b" / "model.safetensors", tiny_world)


def test_task_view_measures_each_source_on_a_fixed_draw(tiny_world, tmp_path):
    """Each source is measured on ``n`` frames of a fixed draw: the same frames give the same
    metrics under any name, the training and held-out splits give their own."""
    gap = _gap()
    _save_model(tmp_path, "resnet18", "resnet18", 32, tiny_world)
    model, layers, res = gap.load_task_model(tmp_path / "model.safetensors", tiny_world)
    train = gap.real_dataset(tiny_world, "p1_train", res)
    sources = {"real_train": train, "again": train, "real_val": gap.real_dataset(tiny_world, "p1_val", res)}
    view = gap.task_view(model, layers, res, sources, 6, seed=0)
    assert set(view) == set(sources) and all(m["frames"] == 6 for m in view.values())
    assert view["real_train"] == view["again"]
    assert view["real_val"]["mpjpe/ra/h"] != view["real_train"]["mpjpe/ra/h"]
    assert all(math.isfinite(m[k]) for m in view.values() for k in ("mpjpe/ra/h", "mrrpe/r/l", "aae"))


def test_the_report_shows_the_task_model_and_the_exports_drops(tmp_path):
    """The markdown carries the task model's table (an undefined metric as a dash), and an export
    folder's drops are read from its own index and per-shard record, complete shards only."""
    import json

    gap = _gap()
    rec = {
        "world": "w",
        "config": {"img_res": 96, "per_class": 1, "test_per_class": 1, "steps": 1},
        "statistics": {"real_train": {"sharpness": 1.0, "sharpness_std": 0.0, "saturation": 1.0, "brightness": 1.0}},
        "classifier": {},
        "coverage": {},
        "articulation": {},
        "task_model": {
            "model": "m.safetensors",
            "img_res": 96,
            "metrics": {"real_val": {"frames": 8, "mpjpe/ra/h": 47.75, "cdev/ho": None, "mrrpe/r/l": 84.2, "aae": 3.2}},
        },
    }
    assert "| real_val | 8 | 47.8 | — | 84.2 | 3.2 |" in gap.markdown(rec)
    index = {
        "num": 30,
        "complete": True,
        "num_samples_written": 25,
        "dropped": {"empty_render": 2, "labels_out_of_crop": 3},
        "shards": [{"shard": 0}, {"shard": 2}],
    }
    (tmp_path / "index.json").write_text(json.dumps(index))
    assert gap.export_drops(tmp_path) == {
        "requested": 30,
        "written": 25,
        "dropped": 5,
        "empty_render": 2,
        "labels_out_of_crop": 3,
    }
    (tmp_path / "index.json").write_text(json.dumps({**index, "dropped": None}))  # reasons not recorded
    assert gap.export_drops(tmp_path) == {"requested": 30, "written": 25, "dropped": 5}


def test_the_world_is_the_one_root_of_the_exports_or_the_setup_world(tiny_world, tmp_path, monkeypatch):
    """The exports name the root they were rendered from (a folder made with --setup-data has no
    world of its own); exports of two roots, or a root without splits and no setup world, are
    refused with the roots found; exports that name none read setup/world; run() asks with the
    exports it found."""
    import json

    gap = _gap()
    exports = []
    for name, data in (("full-a", tiny_world), ("no_srm-b", tiny_world), ("no_pom-c", tmp_path), ("free-d", None)):
        (tmp_path / "synthetic" / name).mkdir(parents=True)
        info = {"data": str(data)} if data is not None else {}
        (tmp_path / "synthetic" / name / "index.json").write_text(json.dumps({"info": info}))
        exports.append(tmp_path / "synthetic" / name)
    assert gap.world_root(tmp_path, exports[:2]) == gap._with_splits(tiny_world) is not None
    with pytest.raises(SystemExit, match="several data roots"):
        gap.world_root(tmp_path, exports)
    with pytest.raises(SystemExit, match="no world with splits/"):
        gap.world_root(tmp_path, exports[2:])
    (tmp_path / "setup" / "world" / "splits").mkdir(parents=True)
    assert gap.world_root(tmp_path, exports[3:]) == tmp_path / "setup" / "world"
    assert gap.world_root(tmp_path, exports[:2]) == gap._with_splits(tiny_world)  # what they were rendered from
    seen = []

    class Stop(Exception):
        pass

    def world_root(downstream, found):
        seen.append(sorted(p.name for p in found))
        raise Stop

    monkeypatch.setattr(gap, "world_root", world_root)
    names = {"full": "full-a", "no_srm": "no_srm-b"}
    monkeypatch.setattr(gap, "find_export", lambda d, v, r: d / "synthetic" / names[v])
    with pytest.raises(Stop):
        gap.run(gap.GapConfig(downstream=str(tmp_path), variants=("full", "no_srm"), model="none", threads=1))
    assert seen == [["full-a", "no_srm-b"]]
