"""The downstream experiment's machinery: config flags, arms, aggregation, tables."""

from __future__ import annotations

import argparse
import importlib
import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional

import numpy as np
import pytest
import torch

from hogsa_loader.cli.dataclass_args import add_dataclass_arguments, dataclass_from_args, flag_name


def _downstream():
    return importlib.import_module("experiments.downstream")


@dataclass
class _Inner:
    """Inner group."""

    size: int = 3
    mode: Literal["a", "b"] = "a"
    path: Optional[str] = None


@dataclass
class _Outer:
    """Outer config."""

    name: str = "x"
    seeds: tuple[int, ...] = (0, 1)
    flag: bool = False
    rate: float = field(default=0.5, metadata={"help": "a rate"})
    inner: _Inner = field(default_factory=_Inner)


def test_dataclass_flags_round_trip():
    p = argparse.ArgumentParser()
    add_dataclass_arguments(p, _Outer)
    assert dataclass_from_args(_Outer, p.parse_args([])) == _Outer()
    got = dataclass_from_args(
        _Outer,
        p.parse_args(
            [
                "--name",
                "y",
                "--seeds",
                "4,5,6",
                "--flag",
                "--rate",
                "0.25",
                "--inner-size",
                "7",
                "--inner-mode",
                "b",
                "--inner-path",
                "/p",
            ]
        ),
    )
    assert got == _Outer("y", (4, 5, 6), True, 0.25, _Inner(7, "b", "/p"))
    with pytest.raises(SystemExit):
        p.parse_args(["--inner-mode", "c"])  # a Literal's values are the flag's choices
    assert flag_name(("train", "batch_size")) == "--train-batch-size"


def test_dataclass_flags_take_defaults_from_an_instance():
    p = argparse.ArgumentParser()
    add_dataclass_arguments(p, _Outer, _Outer(name="q", inner=_Inner(size=9)))
    assert dataclass_from_args(_Outer, p.parse_args([])) == _Outer(name="q", inner=_Inner(size=9))


def test_quick_defaults_yield_to_explicit_flags(monkeypatch):
    ds = _downstream()
    seen = {}
    monkeypatch.setattr(ds, "run", lambda cfg: seen.setdefault("cfg", cfg))
    ds.main(["--quick", "--train-steps", "11", "--out", "/tmp/x"])
    cfg = seen["cfg"]
    assert cfg.train.steps == 11 and cfg.setup.preset == "tiny" and cfg.seeds == (0,) and cfg.out == "/tmp/x"
    seen.clear()
    ds.main([])
    assert seen["cfg"] == ds.DownstreamConfig()
    seen.clear()
    ds.main(["--device", "cuda", "--train-steps", "5"])  # ARCTIC's network settings on a GPU
    cfg = seen["cfg"]
    assert (cfg.model.backbone, cfg.model.img_res, cfg.train.batch_size, cfg.train.steps) == ("resnet50", 224, 64, 5)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--arms", "real,bogus"], "unknown arms"),
        (["--low-data", "0"], "low-data"),
        (["--synthetic-share", "1.0"], "synthetic-share"),
        (["--train-batch-size", "1"], "batch-size"),
        (["--setup-bundle", "b"], "needs --setup-data"),
        (["--setup-free", "--setup-free-bundle", "f"], "not both"),
        (["--setup-free", "--arms", "real,hogsa"], "not in --arms"),
        (["--setup-free", "--setup-data", "d", "--setup-bundle", "b"], "give --setup-free-bundle"),
        (["--train-batch-size", "2", "--synthetic-share", "0.75"], "no real sample"),
        (["--train-checkpoint-every", "-1"], "checkpoint-every"),
        (["--setup-bank-finger-scale", "-0.5"], "finger-scale"),
        (["--setup-bank-variants", "0"], "bank-variants"),
        (["--setup-bank-per-sequence", "0"], "bank-per-sequence"),
        (["--model-init", "/m{seed}.ckpt", "--model-weights", "/w.pth"], "exclude each other"),
        (["--model-kind", "interfield_sf", "--synthetic-supervise", "touching"], "does not read"),
        (["--model-init", "/nowhere/seed{seed}/m.safetensors", "--seeds", "2,3"], "/nowhere/seed2/m.safetensors"),
    ],
)
def test_bad_settings_are_refused_before_work(argv, message, tmp_path):
    ds = _downstream()
    with pytest.raises(SystemExit, match=message):
        ds.main(argv + ["--out", str(tmp_path / "o")])
    assert not (tmp_path / "o").exists()


def test_setup_builds_its_pose_bank_with_the_finger_scale(tmp_path, monkeypatch):
    ds = _downstream()
    seen = []

    def stages(out, demo, log, gaussians="mesh"):
        seen.append(demo)
        assert gaussians == "mesh"
        return tmp_path, tmp_path, {}

    monkeypatch.setattr(ds, "build_bundle_stages", stages)
    monkeypatch.setattr(ds, "background_folder", lambda cfg, data, out: data)
    cfg = ds.DownstreamConfig()
    cfg.setup.bank_finger_scale, cfg.setup.bank_per_sequence, cfg.setup.bank_variants = 0.5, 64, 3
    cfg.setup.bank_frames, cfg.setup.srm_gan = "all", 1.0
    ds.build_setup(cfg, tmp_path)
    got = seen[0]
    assert (got.bank_finger_scale, got.bank_per_sequence, got.bank_variants, got.bank_frames) == (0.5, 64, 3, "all")
    assert got.srm_gan == 1.0


def test_setup_free_builds_free_gaussians_beside_the_setup_for_the_free_arm(tmp_path, monkeypatch):
    """``--setup-free``: the same stages again with plain 3D Gaussians (``OUT/setup/free``), read by
    the ``hogsa_free`` arm alone; the other arms' keys do not change."""
    ds = _downstream()
    calls = []

    def stages(out, demo, log, gaussians="mesh"):
        calls.append((out, demo, gaussians))
        bundle = out / ("free" if gaussians == "free" else "") / "bundle"
        bundle.mkdir(parents=True, exist_ok=True)
        (bundle / "manifest.json").write_text(json.dumps({"hogs": [gaussians]}))
        (out / "world" / "meta").mkdir(parents=True, exist_ok=True)
        return out / "world", bundle, {"hogs/s01_box": 1.0}

    monkeypatch.setattr(ds, "build_bundle_stages", stages)
    monkeypatch.setattr(ds, "background_folder", lambda cfg, data, out: data)
    cfg = ds.DownstreamConfig()
    mesh = ds.build_setup(cfg, tmp_path)
    assert [c[2] for c in calls] == ["mesh"] and mesh["free_bundle"] is None
    mesh["fingerprints"] = ds.setup_fingerprints(cfg, mesh)
    assert ds.variant_options("free", cfg, mesh) is None
    cfg.setup.free = True
    ds.validate(cfg)  # (every arm, hogsa_free among them)
    free = ds.build_setup(cfg, tmp_path)
    assert [c[2] for c in calls] == ["mesh", "mesh", "free"] and calls[1][1] == calls[2][1]  # the same settings
    assert free["free_bundle"] == (tmp_path / "setup" / "free" / "bundle").resolve()
    assert set(free["stage_seconds"]) == {"hogs/s01_box", "free/hogs/s01_box"}
    free["fingerprints"] = ds.setup_fingerprints(cfg, free)
    assert ds.variant_options("free", cfg, free)["bundle"] == str(free["free_bundle"])
    changed = {k for k in mesh["fingerprints"] if mesh["fingerprints"][k] != free["fingerprints"][k]}
    assert changed == {"free"}
    for arm in ("real", "hogsa", "hogsa_no_srm", "hogsa_no_pom", "real_low", "hogsa_low"):
        mesh_cfg = ds.replace(cfg, setup=ds.replace(cfg.setup, free=False))
        assert ds.run_settings(arm, 0, cfg, free) == ds.run_settings(arm, 0, mesh_cfg, mesh), arm
    assert ds.export_dir("free", cfg, free, tmp_path).name.startswith("free-")


def test_low_data_subset_is_fixed_and_sized():
    ds = _downstream()
    a, b = ds.low_data_indices(1000, 0.25), ds.low_data_indices(1000, 0.25)
    assert a == b and len(a) == 250 and len(set(a)) == 250 and a == sorted(a) and max(a) < 1000
    assert ds.low_data_indices(3, 0.1) and len(ds.low_data_indices(3, 0.1)) == 1


def _prints(world: str, bundle: str, everything: str, free: str = "f0") -> dict[str, str]:
    return {"world": world, "bundle": bundle, "all": everything, "free": free}


def test_every_arm_has_a_variant_spec():
    ds = _downstream()
    cfg = ds.DownstreamConfig()
    setup = {"bundle": Path("/b"), "data": Path("/d"), "fingerprints": _prints("w0", "b0", "a0")}
    assert set(ds.ARM_SPECS) == set(ds.ARMS)
    assert ds.variant_options("full", cfg, setup) == {"bundle": "/b", "srm": True, "poses": "bank"}
    assert ds.variant_options("no_srm", cfg, setup)["srm"] is False
    nopom = ds.variant_options("no_pom", cfg, setup)
    assert nopom["poses"] == "perturb" and nopom["pose_options"] == {"finger_std": 0.0}  # annotated poses
    assert ds.variant_options("free", cfg, setup) is None  # no free-3DGS bundle given
    # a run's cache key changes with anything its result depends on, not with other arms' settings
    k = ds.run_settings("real", 0, cfg, setup)
    assert k["synthetic"] is None and k["variant"] is None
    assert ds.run_settings("hogsa", 0, cfg, setup)["variant"]["poses"] == "bank"
    assert ds.run_settings("real", 1, cfg, setup) != k
    assert ds.run_settings("real", 0, cfg, dict(setup, fingerprints=_prints("w1", "b0", "a0"))) != k  # new world
    # a run's key follows the part of the setup it reads: a new pose bank re-runs the bank arms only
    new_bank = dict(setup, fingerprints=_prints("w0", "b0", "a1"))
    for arm, changed in (
        ("real", False),
        ("real_low", False),
        ("hogsa_no_pom", False),
        ("hogsa_free", False),
        ("hogsa", True),
        ("hogsa_no_srm", True),
        ("hogsa_low", True),
    ):
        assert (ds.run_settings(arm, 0, cfg, new_bank) != ds.run_settings(arm, 0, cfg, setup)) == changed, arm
    assert ds.run_settings(
        "hogsa_no_pom", 0, cfg, dict(setup, fingerprints=_prints("w0", "b1", "a1"))
    ) != ds.run_settings("hogsa_no_pom", 0, cfg, setup)  # new HOGS/SRM
    # an export's folder changes with anything its frames depend on
    a = ds.export_dir("full", cfg, setup, Path("/o"))
    assert a != ds.export_dir("full", cfg, new_bank, Path("/o"))
    assert ds.export_dir("no_pom", cfg, new_bank, Path("/o")) == ds.export_dir("no_pom", cfg, setup, Path("/o"))
    assert a != ds.export_dir("full", ds.quick_config(cfg), setup, Path("/o"))
    assert a == ds.export_dir("full", cfg, setup, Path("/o")) and a.name.startswith("full-")


def test_setup_fingerprints_follow_what_changed(tmp_path):
    ds = _downstream()
    cfg = ds.DownstreamConfig()
    (tmp_path / "d" / "meta").mkdir(parents=True)
    (tmp_path / "b").mkdir()
    world, manifest = tmp_path / "d" / "meta" / "hogsa_world.json", tmp_path / "b" / "manifest.json"
    setup = {"data": tmp_path / "d", "bundle": tmp_path / "b"}
    world.write_text('{"seed": 0}')
    manifest.write_text(json.dumps({"hogs": [{"files": {"a": "1"}}], "pose_banks": [{"files": {"p": "1"}}]}))
    first = ds.setup_fingerprints(cfg, setup)
    assert first == ds.setup_fingerprints(cfg, setup) and len(set(first.values())) == 4
    # pinned: the keys of this settings schema (every setup setting keyed; CACHE_VERSION 2)
    assert first == {"world": "46b48e092b5dcb90", "bundle": "4ab7715de9d20d51", "all": "89c44b375b5678f9"} | {
        "free": "54ea99098af417a2"
    }
    cfg.setup.bank_finger_scale = 0.5  # another pose bank: only the runs that draw from it change
    fingers = ds.setup_fingerprints(cfg, setup)
    assert {k: v for k, v in fingers.items() if k != "all"} == {k: v for k, v in first.items() if k != "all"}
    assert fingers["all"] == "9df640ca6546ee01"  # pinned: the key of a finger-noise setup
    cfg.setup.bank_variants = 4
    variants = ds.setup_fingerprints(cfg, setup)
    assert {k: v for k, v in variants.items() if k != "all"} == {k: v for k, v in first.items() if k != "all"}
    assert variants["all"] not in (first["all"], fingers["all"])
    cfg.setup.bank_frames = "all"
    every = ds.setup_fingerprints(cfg, setup)
    assert {k: v for k, v in every.items() if k != "all"} == {k: v for k, v in first.items() if k != "all"}
    assert every["all"] not in (first["all"], fingers["all"], variants["all"])
    cfg.setup.bank_finger_scale, cfg.setup.bank_variants, cfg.setup.bank_frames = 0.0, 1, "contact"
    cfg.setup.srm_gan = 1.0  # another SRM: the bundle's runs change, the world's do not
    gan = ds.setup_fingerprints(cfg, setup)
    assert gan["world"] == first["world"] and gan["bundle"] != first["bundle"] and gan["all"] != first["all"]
    cfg.setup.srm_gan = 0.0
    manifest.write_text(json.dumps({"hogs": [{"files": {"a": "1"}}], "pose_banks": [{"files": {"p": "2"}}]}))
    bank = ds.setup_fingerprints(cfg, setup)  # a new pose bank
    assert bank["world"] == first["world"] and bank["bundle"] == first["bundle"] and bank["all"] != first["all"]
    assert bank["free"] == first["free"]
    manifest.write_text(json.dumps({"hogs": [{"files": {"a": "2"}}], "pose_banks": [{"files": {"p": "2"}}]}))
    hogs = ds.setup_fingerprints(cfg, setup)  # a new HOGS
    assert hogs["world"] == first["world"] and hogs["bundle"] != bank["bundle"] and hogs["all"] != bank["all"]
    world.write_text('{"seed": 1}')
    assert all(
        a != b for a, b in zip(ds.setup_fingerprints(cfg, setup).values(), hogs.values(), strict=True)
    )  # a new world


def _result(mpjpe: float, cdev: float) -> dict:
    summ = {m: 1.0 for m in _downstream().METRICS}
    summ.update({"mpjpe/ra/h": mpjpe, "cdev/ho": cdev})
    return {"summary": summ, "curve": [{"step": 5, **summ}, {"step": 10, **summ}]}


def test_aggregate_means_stds_and_paired_differences(tmp_path):
    ds = _downstream()
    results = {
        "real": {0: _result(30.0, 50.0), 1: _result(32.0, 54.0), 2: _result(31.0, 52.0)},
        "hogsa": {0: _result(28.0, 45.0), 1: _result(31.0, 50.0), 2: _result(29.0, 49.0)},
        "real_low": {0: _result(40.0, 60.0), 1: _result(41.0, 61.0), 2: _result(42.0, 62.0)},
        "hogsa_low": {0: _result(35.0, 58.0), 1: _result(36.0, 59.0), 2: _result(40.0, 61.0)},
    }
    agg = ds.aggregate(results)
    assert agg["arms"]["real"]["mpjpe/ra/h"]["mean"] == pytest.approx(31.0)
    assert agg["arms"]["real"]["mpjpe/ra/h"]["std"] == pytest.approx(1.0)  # sample std over seeds
    d = agg["paired"]["hogsa - real"]["mpjpe/ra/h"]
    assert d["per_seed"] == {0: -2.0, 1: -1.0, 2: -2.0} and d["mean"] == pytest.approx(-5 / 3)
    assert d["std"] == pytest.approx(np.std([-2, -1, -2], ddof=1))
    low = agg["paired"]["hogsa_low - real_low"]["cdev/ho"]  # low-data arms pair with the low-data baseline
    assert low["per_seed"] == {0: -2.0, 1: -2.0, 2: -1.0}
    md = ds.markdown(agg, ds.DownstreamConfig(), "2 CPU cores", {"hogsa_free": "no free-3DGS bundle"})
    assert "| ArcticNet-SF (real) | 31.00 ± 1.00 | 52.00 ± 2.00 |" in md
    assert "no free-3DGS bundle" in md and "| hogsa - real | -2.00, -1.00, -2.00 | -1.67 ± 0.58 |" in md
    ds.plot(results, agg, tmp_path / "d.png")
    assert (tmp_path / "d.png").stat().st_size > 10_000


def _clips(per_clip: dict[str, tuple[float, int]]) -> dict:
    """Clip sums of runs whose every frame of a clip has the same MPJPE_h and CDev_ho."""
    return {c: {"mpjpe/ra/h": [v * n, float(n)], "cdev/ho": [2 * v * n, float(n)]} for c, (v, n) in per_clip.items()}


def test_paired_differences_carry_their_uncertainty_over_clips():
    ds = _downstream()
    names = [f"s05/laptop_grab_01/{v}" for v in range(4)]
    ref = _clips({c: (40.0, 10) for c in names})
    arm = _clips({c: (60.0 if c.endswith("/1") else 40.0, 10) for c in names})  # +20 mm on one clip
    results = {
        "real": {s: {**_result(40.0, 80.0), "clips": ref} for s in range(2)},
        "hogsa": {s: {**_result(45.0, 90.0), "clips": arm} for s in range(2)},
        "hogsa_no_srm": {0: _result(44.0, 88.0), 1: {**_result(45.0, 90.0), "clips": arm}},  # one run without
    }
    agg = ds.aggregate(results)
    rec = agg["paired"]["hogsa - real"]["mpjpe/ra/h"]["clips"]
    assert rec["estimate"] == pytest.approx(5.0) and rec["leave_one_out"]["min"][1] == "s05/laptop_grab_01/1"
    assert agg["paired"]["hogsa - real"]["cdev/ho"]["clips"]["estimate"] == pytest.approx(10.0)
    assert agg["paired"]["hogsa_no_srm - real"]["mpjpe/ra/h"]["clips"] is None
    md = ds.markdown(agg, ds.DownstreamConfig(), "2 CPU cores", {})
    lo, hi = rec["ci95"]
    assert "**Over validation clips** (4 clips" in md
    assert f"| hogsa - real | [{lo:+.2f}, {hi:+.2f}] | +0.00 (without s05/laptop_grab_01/1) … +6.67" in md
    assert "| hogsa_no_srm - real | n/a | n/a | n/a | n/a |" in md


def test_finished_runs_are_found_only_with_their_settings(tmp_path):
    """``--report-only`` tabulates the runs whose saved key matches the current settings."""
    ds = _downstream()
    cfg = ds.DownstreamConfig()
    setup = {"bundle": Path("/b"), "data": Path("/d"), "fingerprints": _prints("w0", "b0", "a0")}
    assert ds.finished_run("real", 0, cfg, setup, tmp_path) is None  # never run
    res = tmp_path / "runs" / "real" / "seed0" / "result.json"
    res.parent.mkdir(parents=True)
    res.write_text(json.dumps({"key": ds._key(ds.run_settings("real", 0, cfg, setup)), **_result(30.0, 50.0)}))
    assert ds.finished_run("real", 0, cfg, setup, tmp_path)["summary"]["mpjpe/ra/h"] == 30.0
    assert ds.finished_run("real", 0, cfg, dict(setup, fingerprints=_prints("w1", "b1", "a1")), tmp_path) is None
    longer = ds.replace(cfg, train=ds.replace(cfg.train, steps=cfg.train.steps + 1))
    assert ds.finished_run("real", 0, longer, setup, tmp_path) is None
    assert ds.finished_run("real", 1, cfg, setup, tmp_path) is None
    # the camera start is part of the key; a random start (0) keeps the keys runs had before the prior existed
    random_start = ds.replace(cfg, model=ds.replace(cfg.model, camera_prior=0))
    assert ds.finished_run("real", 0, random_start, setup, tmp_path) is None
    assert "camera_prior" not in ds.run_settings("real", 0, random_start, setup)["model"]
    assert ds.run_settings("real", 0, cfg, setup)["model"]["camera_prior"] == 256


def test_appended_synthetic_samples_key_the_runs_not_the_frames(tmp_path):
    """--synthetic-mix add: HOGSA runs get their own key and folder; exports, real runs and
    the replace runs' keys stay as they were."""
    ds = _downstream()
    cfg = ds.DownstreamConfig()
    add = ds.replace(cfg, synthetic=ds.replace(cfg.synthetic, mix="add"))
    setup = {"bundle": Path("/b"), "data": Path("/d"), "fingerprints": _prints("w0", "b0", "a0")}
    assert ds.export_dir("full", add, setup, tmp_path) == ds.export_dir("full", cfg, setup, tmp_path)
    assert ds.run_settings("hogsa", 0, add, setup) != ds.run_settings("hogsa", 0, cfg, setup)
    assert ds.run_settings("hogsa", 0, cfg, setup)["synthetic"]["mix"] == "replace"  # every setting is keyed
    assert ds.run_settings("real", 0, add, setup) == ds.run_settings("real", 0, cfg, setup)
    assert ds.run_dir("hogsa", 0, add, tmp_path) != ds.run_dir("hogsa", 0, cfg, tmp_path)
    assert ds.run_dir("real", 0, add, tmp_path) == ds.run_dir("real", 0, cfg, tmp_path) == tmp_path / "runs/real/seed0"
    res = ds.run_dir("hogsa", 0, cfg, tmp_path) / "result.json"  # a replace run ...
    res.parent.mkdir(parents=True)
    res.write_text(json.dumps({"key": ds._key(ds.run_settings("hogsa", 0, cfg, setup)), **_result(30.0, 50.0)}))
    assert ds.finished_run("hogsa", 0, cfg, setup, tmp_path) is not None
    assert ds.finished_run("hogsa", 0, add, setup, tmp_path) is None  # ... is not an add run


def test_dataset_cameras_key_their_own_exports_and_reach_the_loader(tmp_path, monkeypatch):
    """--synthetic-cameras dataset renders every frame from a training subject's own camera
    (its own export and run keys); the default keeps the keys runs had before the choice."""
    ds = _downstream()
    cfg = ds.DownstreamConfig()
    rig = ds.replace(cfg, synthetic=ds.replace(cfg.synthetic, cameras="dataset"))
    setup = {"bundle": Path("/b"), "data": Path("/d"), "fingerprints": _prints("w0", "b0", "a0")}
    assert ds.run_settings("hogsa", 0, cfg, setup)["synthetic"]["cameras"] == "novel"
    assert ds.run_settings("hogsa", 0, rig, setup)["synthetic"]["cameras"] == "dataset"
    assert ds.export_dir("full", rig, setup, tmp_path) != ds.export_dir("full", cfg, setup, tmp_path)
    assert ds.run_settings("real", 0, rig, setup) == ds.run_settings("real", 0, cfg, setup)
    seen = []

    class _Recorder:
        def __init__(self, bundle, data, config):
            seen.append((config.cameras, config.backgrounds.camera_plates))

        def total_stats(self):
            return ds.argparse.Namespace(dropped={})

    monkeypatch.setattr(ds, "HOGSADataset", _Recorder)
    monkeypatch.setattr(ds, "dataset_frames_for_shard", lambda *a: iter(()))
    index = tmp_path / "index.json"
    done = {"samples": 0, "written": [], "skipped": [], "index": str(index), "complete": False}
    monkeypatch.setattr(
        ds, "write_shards", lambda *a, **k: {**done, "num_samples_written": 0, "num_dropped": 0, "dropped": None}
    )
    setup = dict(setup, backgrounds=tmp_path)
    plates = ds.replace(rig, synthetic=ds.replace(rig.synthetic, backgrounds="camera_plates"))
    assert ds.export_dir("full", plates, setup, tmp_path) != ds.export_dir("full", rig, setup, tmp_path)
    for c in (cfg, rig, plates):
        ds.export_variant("full", c, setup, tmp_path)
    assert [(c.dataset_prob, p) for c, p in seen] == [
        (ds.CameraConfig().dataset_prob, False),
        (1.0, False),
        (1.0, True),
    ]


def test_background_folder_builds_plates_once_and_keys_exports(tiny_world, tmp_path, monkeypatch):
    """Plates (the default) are built from the world once and reused; the background choice
    is part of each synthetic export's name, so photo and plate frames never mix."""
    import functools

    from hogsa_loader.compose import plates

    small = functools.partial(plates.PlateConfig, views=(1, 2), width=160, frames_per_sequence=2)  # a quick build
    monkeypatch.setattr(plates, "PlateConfig", small)
    ds = _downstream()
    cfg = ds.DownstreamConfig()
    assert cfg.synthetic.backgrounds == "plates"
    folder = ds.background_folder(cfg, Path(tiny_world), tmp_path)
    manifest = folder / "plates.json"
    first = manifest.stat().st_mtime_ns
    assert json.loads(manifest.read_text())["plates"] and sorted(folder.glob("*_view*.png"))
    assert ds.background_folder(cfg, Path(tiny_world), tmp_path) == folder
    assert manifest.stat().st_mtime_ns == first  # reused, not rebuilt
    other = tmp_path / "other"
    other.mkdir()
    (other / "setup").symlink_to(tmp_path / "setup")  # another OUT sharing the setup
    ds.background_folder(cfg, Path(tiny_world), other)
    assert manifest.stat().st_mtime_ns == first  # the plates' own path is not part of their key
    photos = ds.replace(cfg, synthetic=ds.replace(cfg.synthetic, backgrounds="photos"))
    assert ds.background_folder(photos, Path(tiny_world), tmp_path) != folder
    setup = {"bundle": Path("/b"), "data": Path("/d"), "fingerprints": _prints("w0", "b0", "a0")}
    assert ds.export_dir("full", cfg, setup, tmp_path) != ds.export_dir("full", photos, setup, tmp_path)
    # a run is keyed by every synthetic setting
    assert ds.run_settings("hogsa", 0, photos, setup)["synthetic"] == ds.asdict(photos.synthetic)


class _Shuffled:
    """A stand-in synthetic export: the held-out frames, augmented per (seed, epoch, index) like the shard reader."""

    def __init__(self, root: Path, seed: int) -> None:
        from hogsa_loader.sample.arctic_dataset import ArcticDataset
        from hogsa_loader.sample.augment import ArcticConfig

        self.ds = ArcticDataset(root, "p1_val", seed=seed, augment=True, config=ArcticConfig(img_res=32))

    def set_epoch(self, epoch: int) -> None:
        self.ds.set_epoch(epoch)

    def __len__(self) -> int:
        return 10  # a short export: several passes within a test

    def __getitem__(self, i: int):
        return self.ds[i]


def _tiny_cfg(ds, **train):
    cfg = ds.DownstreamConfig(low_data=0.02)  # 12 real frames of the tiny world
    return ds.replace(
        cfg,
        model=ds.replace(cfg.model, img_res=32, camera_prior=8),
        train=ds.replace(cfg.train, **{"batch_size": 4, "workers": 0, **train}),
    )


@pytest.mark.parametrize("mix", ["replace", "add"])
def test_training_stream_starts_at_any_batch(tiny_world, monkeypatch, mix):
    """Batch k of a stream started at batch s < k is batch k of the stream started at 0 (same
    frames, same augmented pixels), across real epochs and synthetic passes: an interrupted
    run resumes on exactly the batches it would have seen."""
    ds = _downstream()
    monkeypatch.setattr(ds, "SynthShardSamples", lambda folder, seed, cfg: _Shuffled(tiny_world, seed))
    monkeypatch.setattr(ds, "export_dir", lambda *a: Path("/unused"))
    cfg = _tiny_cfg(ds)
    cfg = ds.replace(cfg, synthetic=ds.replace(cfg.synthetic, mix=mix))
    setup = {"data": tiny_world}
    assert ds.batch_composition("hogsa_low", cfg) == ((2, 2) if mix == "replace" else (4, 4))
    assert ds.batch_composition("real_low", cfg) == (4, 0)

    def take(arm: str, start: int, n: int) -> list:
        it = ds.train_batches(arm, 3, cfg, setup, Path("/unused"), start=start)
        return [next(it) for _ in range(n)]

    for arm in ("real_low", "hogsa_low"):
        whole = take(arm, 0, 9)  # 3 real epochs of 3 batches (real_low) or 6 (replace)
        names = [b[2]["imgname"] for b in whole]
        assert len(set(map(tuple, names))) == 9  # reshuffled every epoch
        for start in (2, 4, 7):
            later = take(arm, start, 9 - start)
            for a, b in zip(whole[start:], later):
                assert list(a[2]["imgname"]) == list(b[2]["imgname"])
                assert torch.equal(a[0]["img"], b[0]["img"])


def test_touching_hands_only_marks_the_hands_away_from_the_object_invalid(tiny_world, monkeypatch):
    """With ``--synthetic-supervise touching`` the synthetic samples' hands with no vertex within
    5 mm of the object are invalid and the others keep their validity; real frames keep theirs,
    and the default adds nothing to the keys."""
    from torch.utils.data import Subset, default_collate

    from hogsa_loader.assets.arctic import ArcticRoot
    from hogsa_loader.baselines.loss import arcticnet_sf_loss

    ds = _downstream()
    layers = ds.BodyLayers.from_root(ArcticRoot(tiny_world))
    frames = _Shuffled(tiny_world, 3).ds
    plain = Subset(frames, range(0, len(frames), 4))
    plain.set_epoch = frames.set_epoch
    wrapped = ds.TouchingHandsOnly(plain, layers, 32)
    counts = {"kept": 0, "dropped": 0}
    dropped_r: list[int] = []
    for i in range(len(plain)):
        _, targets, meta = plain[i]
        t, _ = ds.prepare_targets(
            default_collate([targets]), default_collate([meta]), layers.mano_r, layers.mano_l, layers.objects, 32
        )
        got = wrapped[i][1]
        for side, key in (("r", "right_valid"), ("l", "left_valid")):
            touching = float(t[f"dist.{side}o"].min()) < 0.005
            assert float(got[key]) == (float(targets[key]) if touching else 0.0)
            np.testing.assert_array_equal(got[f"joints_valid_{side}"], targets[f"joints_valid_{side}"] * touching)
            if float(targets[key]) > 0:
                counts["kept" if touching else "dropped"] += 1
                if not touching and side == "r":
                    dropped_r.append(i)
    assert counts["kept"] > 0 and counts["dropped"] > 0  # the held-out frames have both kinds of hands
    # the flags do not depend on the augmentation: another epoch's draws give the same, and are not prepared again
    first = dict(wrapped._touching)
    plain.set_epoch(1)
    prepare = ds.prepare_targets
    for i in range(len(plain)):
        _, targets, meta = plain[i]
        t, _ = prepare(
            default_collate([targets]), default_collate([meta]), layers.mano_r, layers.mano_l, layers.objects, 32
        )
        assert first[i] == tuple(float(t[f"dist.{s}o"].min()) < 0.005 for s in "rl")
    monkeypatch.setattr(ds, "prepare_targets", lambda *a, **k: (_ for _ in ()).throw(AssertionError("prepared again")))
    for i in range(len(plain)):  # epoch 1, every flag from the remembered ones
        got, raw = wrapped[i][1], plain[i][1]
        for k, key in enumerate(("right_valid", "left_valid")):
            assert float(got[key]) == (float(raw[key]) if first[i][k] else 0.0)
    monkeypatch.setattr(ds, "prepare_targets", prepare)
    plain.set_epoch(0)

    # ArcticNet-SF's loss sees nothing of a dropped hand: every right-hand term is 0 on those frames
    cfg32 = _tiny_cfg(ds)
    model = ds.build_model(cfg32, layers)
    batch = default_collate([wrapped[i] for i in dropped_r])
    inputs, targets, meta = batch
    targets, meta = ds.prepare_targets(dict(targets), dict(meta), layers.mano_r, layers.mano_l, layers.objects, 32)
    terms = arcticnet_sf_loss(model(inputs, meta), targets)
    for name in ("pose", "beta", "kp2d", "kp3d", "cam_t"):
        assert float(terms[f"loss/mano/{name}/r"]) == 0.0
    plain_batch = default_collate([plain[i] for i in dropped_r])
    targets, meta = ds.prepare_targets(
        dict(plain_batch[1]), dict(plain_batch[2]), layers.mano_r, layers.mano_l, layers.objects, 32
    )
    assert float(arcticnet_sf_loss(model(plain_batch[0], meta), targets)["loss/mano/kp3d/r"]) > 0.0

    monkeypatch.setattr(ds, "SynthShardSamples", lambda folder, seed, cfg: _Shuffled(tiny_world, seed))
    monkeypatch.setattr(ds, "export_dir", lambda *a: Path("/unused"))
    base = _tiny_cfg(ds)
    every = ds.replace(base, synthetic=ds.replace(base.synthetic, mix="add"))
    touch = ds.replace(every, synthetic=ds.replace(every.synthetic, supervise="touching"))
    n_real, n_syn = ds.batch_composition("hogsa_low", touch)
    b_every = next(ds.train_batches("hogsa_low", 3, every, {"data": tiny_world}, Path("/unused")))
    b_touch = next(ds.train_batches("hogsa_low", 3, touch, {"data": tiny_world}, Path("/unused")))
    assert list(b_every[2]["imgname"]) == list(b_touch[2]["imgname"])
    for key in ("right_valid", "left_valid"):
        assert torch.equal(b_every[1][key][:n_real], b_touch[1][key][:n_real])
    assert (b_touch[1]["right_valid"][n_real:] <= b_every[1]["right_valid"][n_real:]).all()
    assert ds.synthetic_key(every)["supervise"] == "all" and ds.synthetic_key(touch)["supervise"] == "touching"
    assert ds.synthetic_key(touch, frames_only=True) == ds.synthetic_key(every, frames_only=True)
    assert ds.run_dir("hogsa", 0, touch, Path("/o")) == Path("/o/runs/hogsa+add+touching/seed0")
    assert ds.run_dir("hogsa", 0, every, Path("/o")) == Path("/o/runs/hogsa+add/seed0")
    assert ds.run_dir("real", 0, touch, Path("/o")) == Path("/o/runs/real/seed0")


def test_loader_workers_change_no_batch_nor_run_key(tiny_world, monkeypatch):
    """The batches are the same whether one process loads them or several, so the worker count
    is not part of a run's key."""
    ds = _downstream()
    monkeypatch.setattr(ds, "SynthShardSamples", lambda folder, seed, cfg: _Shuffled(tiny_world, seed))
    monkeypatch.setattr(ds, "export_dir", lambda *a: Path("/unused"))
    setup = {"data": tiny_world}
    batches = {}
    for workers in (0, 2):
        cfg = _tiny_cfg(ds, workers=workers)
        it = ds.train_batches("hogsa_low", 3, cfg, setup, Path("/unused"), start=1)
        batches[workers] = [next(it) for _ in range(8)]  # across a real epoch and a synthetic pass
    for a, b in zip(batches[0], batches[2]):
        assert list(a[2]["imgname"]) == list(b[2]["imgname"])
        assert torch.equal(a[0]["img"], b[0]["img"])
    assert ds.train_key(_tiny_cfg(ds, workers=0)) == ds.train_key(_tiny_cfg(ds, workers=6))
    assert ds.train_key(_tiny_cfg(ds, workers=0))["workers"] == 1  # the default's: earlier runs keep their keys
    assert ds.train_key(_tiny_cfg(ds, workers=0)) != ds.train_key(_tiny_cfg(ds, lr=1e-4))


def test_interrupted_run_resumes_to_the_same_result(tiny_world, tmp_path, monkeypatch):
    """A run with synthetic samples stopped after a saved state and started again ends with the
    weights, curve and metrics of the unbroken run; its saved states are removed when it finishes."""
    ds = _downstream()
    monkeypatch.setattr(ds, "SynthShardSamples", lambda folder, seed, cfg: _Shuffled(tiny_world, seed))
    monkeypatch.setattr(ds, "export_dir", lambda *a: Path("/unused"))
    monkeypatch.setattr(ds, "variant_options", lambda *a: {"bundle": "/unused"})
    cfg = _tiny_cfg(ds, steps=5, evals=2, eval_stride=8, checkpoint_every=2)
    setup = {"data": tiny_world, "bundle": Path("/unused"), "fingerprints": _prints("w0", "b0", "a0")}
    val_dataset = ds.val_dataset
    monkeypatch.setattr(ds, "val_dataset", lambda *a: (lambda v: (v[0], v[1][:24]))(val_dataset(*a)))  # a short val
    unbroken = ds.run_arm("hogsa_low", 0, cfg, setup, tmp_path / "a")

    step = ds.training_step
    calls = []

    def stop_at_five(*a, **k):
        calls.append(1)
        if len(calls) == 5:
            raise KeyboardInterrupt
        return step(*a, **k)

    monkeypatch.setattr(ds, "training_step", stop_at_five)
    with pytest.raises(KeyboardInterrupt):
        ds.run_arm("hogsa_low", 0, cfg, setup, tmp_path / "b")
    folder = ds.run_dir("hogsa_low", 0, cfg, tmp_path / "b")
    assert json.loads((folder / "checkpoints" / "latest.json").read_text())["step"] == 4
    monkeypatch.setattr(ds, "training_step", step)
    resumed = ds.run_arm("hogsa_low", 0, cfg, setup, tmp_path / "b")
    assert resumed["resumed_at"] == [4] and unbroken["resumed_at"] == []
    assert not (folder / "checkpoints").exists()
    assert resumed["curve"] == unbroken["curve"] and resumed["summary"] == unbroken["summary"]
    assert resumed["loss_curve"] == unbroken["loss_curve"]
    from safetensors.torch import load_file

    a = load_file(ds.run_dir("hogsa_low", 0, cfg, tmp_path / "a") / "model.safetensors")
    b = load_file(folder / "model.safetensors")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    for m in ds.CLIP_METRICS:  # the per-clip sums form the split's frame-weighted value again
        sums = np.array([c[m] for c in resumed["clips"].values()])  # (C, 2)
        assert sums[:, 0].sum() / sums[:, 1].sum() == pytest.approx(resumed["summary"][m], abs=1e-6)
    saved = json.loads((folder / "result.json").read_text())
    assert saved["clips"] == resumed["clips"]
    del saved["clips"]  # a result saved before clips were kept: its model is evaluated once more
    (folder / "result.json").write_text(json.dumps(saved))
    again = ds.with_clips("hogsa_low", 0, cfg, setup, tmp_path / "b", saved)
    assert again["clips"].keys() == resumed["clips"].keys()
    for clip, rec in again["clips"].items():
        for m in ds.CLIP_METRICS:
            assert rec[m][1] == resumed["clips"][clip][m][1]
            assert rec[m][0] == pytest.approx(resumed["clips"][clip][m][0], rel=1e-4)
    assert json.loads((folder / "result.json").read_text())["clips"] == again["clips"]
    saved["summary"] = {**saved["summary"], "mpjpe/ra/h": saved["summary"]["mpjpe/ra/h"] + 1.0}
    (folder / "result.json").write_text(json.dumps(saved))  # weights that do not give their result's values
    assert "clips" not in ds.with_clips("hogsa_low", 0, cfg, setup, tmp_path / "b", saved)
    assert "clips" not in json.loads((folder / "result.json").read_text())  # the result is left as it was


def test_linear_schedule_keys_its_runs_and_ends_near_zero():
    """--train-lr-schedule linear: the rate falls from lr to lr/steps, as a function of the step
    alone; constant runs keep their keys and folders."""
    ds = _downstream()
    cfg = ds.DownstreamConfig()
    lin = ds.replace(cfg, train=ds.replace(cfg.train, lr_schedule="linear", steps=4))
    assert [ds.learning_rate(k, lin) for k in (1, 2, 3, 4)] == pytest.approx([3e-4, 2.25e-4, 1.5e-4, 0.75e-4])
    assert ds.learning_rate(3, cfg) == cfg.train.lr
    setup = {"bundle": Path("/b"), "data": Path("/d"), "fingerprints": _prints("w0", "b0", "a0")}
    assert ds.run_settings("real", 0, cfg, setup)["train"]["lr_schedule"] == "constant"
    assert "checkpoint_every" not in ds.run_settings("real", 0, cfg, setup)["train"]
    long = ds.replace(lin, train=ds.replace(lin.train, steps=cfg.train.steps))
    assert ds.run_settings("real", 0, long, setup)["train"]["lr_schedule"] == "linear"
    assert ds.run_settings("real", 0, long, setup) != ds.run_settings("real", 0, cfg, setup)
    # in their own folders: a linear run never overwrites a constant one
    assert ds.run_dir("real", 0, long, Path("/o")) == Path("/o/runs/real+linear/seed0")
    assert ds.run_dir("real", 0, cfg, Path("/o")) == Path("/o/runs/real/seed0")
    ft = ds.replace(
        long, model=ds.replace(cfg.model, init="/m{seed}.pt"), synthetic=ds.replace(cfg.synthetic, mix="add")
    )
    assert re.fullmatch(r"hogsa\+add\+ft-[0-9a-f]{8}\+linear", ds.run_dir("hogsa", 0, ft, Path("/o")).parent.name)


def test_run_keys_are_pinned():
    """Run keys of the defaults and of the non-default synthetic and schedule choices, pinned
    (this settings schema, with the model kind, CACHE_VERSION 2): a change of any key is a change
    of the schema."""
    ds = _downstream()
    cfg = ds.DownstreamConfig()
    setup = {"bundle": Path("/b"), "data": Path("/d"), "fingerprints": _prints("w0", "b0", "a0")}
    other = ds.replace(
        cfg,
        synthetic=ds.replace(cfg.synthetic, mix="add", backgrounds="camera_plates", cameras="dataset"),
        train=ds.replace(cfg.train, lr_schedule="linear"),
    )
    keys = [
        [ds._key(ds.run_settings(arm, 0, c, setup)) for arm in ("real", "hogsa", "hogsa_no_pom")] for c in (cfg, other)
    ]
    assert keys == [
        ["f8f334f02265bb32", "3016035019c71673", "7163534f20587017"],
        ["ac1ae183896eb611", "04da73f273793f7a", "3e085c36c0b82543"],
    ]


def test_linear_runs_in_the_shared_folder_move_to_their_own(tmp_path, monkeypatch):
    ds = _downstream()
    cfg = ds.DownstreamConfig(arms=("real", "hogsa"), seeds=(0, 1))
    lin = ds.replace(cfg, train=ds.replace(cfg.train, lr_schedule="linear"))
    setup = {"bundle": Path("/b"), "data": Path("/d"), "fingerprints": _prints("w0", "b0", "a0")}

    def save(arm, seed, c):  # a finished run of c, in the folder it is looked for in today
        folder = ds.run_dir(arm, seed, c, tmp_path)
        folder.mkdir(parents=True)
        (folder / "result.json").write_text(json.dumps({"key": ds._key(ds.run_settings(arm, seed, c, setup))}))
        return folder

    shared = save("real", 0, cfg)  # a linear run written where the constant runs live
    (shared / "result.json").write_text(json.dumps({"key": ds._key(ds.run_settings("real", 0, lin, setup))}))
    constant = save("hogsa", 0, cfg)  # a constant-rate run: stays
    ds.adopt_shared_folder_runs(lin, setup, tmp_path)
    assert ds.finished_run("real", 0, lin, setup, tmp_path) is not None and not shared.exists()
    assert ds.finished_run("hogsa", 0, cfg, setup, tmp_path) is not None and constant.exists()
    assert not ds.run_dir("hogsa", 0, lin, tmp_path).exists()
    ds.adopt_shared_folder_runs(cfg, setup, tmp_path)  # constant settings move nothing
    assert ds.finished_run("hogsa", 0, cfg, setup, tmp_path) is not None


def test_a_checkpoint_start_keys_runs_by_the_files_bytes(tmp_path):
    """--model-init: each seed's run is keyed by the bytes of its own checkpoint ('{seed}' in the
    path), wherever the file lies, without the camera prior it does not use; runs from random
    weights keep their keys; each --model-init has its own run folders."""
    import hashlib
    import os

    ds = _downstream()
    cfg = ds.DownstreamConfig()
    for k in (0, 1):
        (tmp_path / f"seed{k}").mkdir()
        (tmp_path / f"seed{k}" / "m.safetensors").write_bytes(b"weights of seed %d" % k)
    init = ds.replace(cfg, model=ds.replace(cfg.model, init=str(tmp_path / "seed{seed}" / "m.safetensors")))
    setup = {"bundle": Path("/b"), "data": Path("/d"), "fingerprints": _prints("w0", "b0", "a0")}
    assert set(ds.run_settings("real", 0, cfg, setup)["model"]) == {
        "kind",
        "backbone",
        "img_res",
        "weights",
        "camera_prior",
    }
    m0, m1 = (ds.run_settings("hogsa", k, init, setup)["model"] for k in (0, 1))
    assert m0["init_sha256"] == hashlib.sha256(b"weights of seed 0").hexdigest()
    assert m1["init_sha256"] == hashlib.sha256(b"weights of seed 1").hexdigest()
    assert "camera_prior" not in m0
    moved = ds.replace(init, model=ds.replace(init.model, init=os.path.relpath(init.model.init)))
    assert ds.run_settings("hogsa", 0, moved, setup) == ds.run_settings("hogsa", 0, init, setup)

    folder = ds.run_dir("hogsa", 1, init, tmp_path)
    assert folder.parent.name.startswith("hogsa+ft-") and folder.name == "seed1"
    add = ds.replace(init, synthetic=ds.replace(init.synthetic, mix="add"))
    assert ds.run_dir("hogsa", 1, add, tmp_path).parent.name.startswith("hogsa+add+ft-")
    assert ds.run_dir("real", 1, cfg, tmp_path) == tmp_path / "runs" / "real" / "seed1"
    chained = ds.replace(cfg, model=ds.replace(cfg.model, init=str(folder.parent / "seed{seed}" / "model.safetensors")))
    assert ds.run_dir("hogsa", 1, chained, tmp_path) != folder  # fine-tuning a fine-tuned model never overwrites it

    before = ds._key(ds.run_settings("real", 0, init, setup))
    path = tmp_path / "seed0" / "m.safetensors"
    stat = path.stat()
    path.write_bytes(b"weights of seed 9")  # the same length; only the modification time tells
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1))
    assert ds._key(ds.run_settings("real", 0, init, setup)) != before
    ds._validate_init(ds.replace(init, seeds=(0, 1)))  # both seeds' files exist: accepted


def test_a_run_starts_from_its_seeds_checkpoint(tiny_world, tmp_path, monkeypatch):
    """start_weights loads the whole network of the seed's checkpoint (a run's model.safetensors)
    and skips the camera prior; a checkpoint missing a tensor is refused, naming the file."""
    from hogsa_loader.assets.arctic import ArcticRoot
    from hogsa_loader.baselines.engine import BodyLayers
    from hogsa_loader.errors import AssetError
    from hogsa_loader.io.tensors import write_tensors_and_manifest

    ds = _downstream()
    cfg = _tiny_cfg(ds)
    layers = BodyLayers.from_root(ArcticRoot(tiny_world))
    torch.manual_seed(5)
    saved = {k: v.detach().clone() for k, v in ds.build_model(cfg, layers).network_state_dict().items()}
    write_tensors_and_manifest(tmp_path / "seed3", "model.safetensors", saved, "model.json", {"kind": "arcticnet_sf"})
    init = ds.replace(cfg, model=ds.replace(cfg.model, init=str(tmp_path / "seed{seed}" / "model.safetensors")))
    monkeypatch.setattr(ds, "camera_prior", lambda *a: pytest.fail("the camera prior is not for a checkpoint"))
    torch.manual_seed(6)
    model = ds.build_model(cfg, layers)
    assert not all(torch.equal(v, saved[k]) for k, v in model.network_state_dict().items())
    ds.start_weights(model, "real", 3, init, {"data": tiny_world}, layers)
    loaded = model.network_state_dict()
    assert loaded.keys() == saved.keys() and all(torch.equal(loaded[k], saved[k]) for k in saved)

    dropped = dict(saved)
    dropped.pop(sorted(k for k in saved if k.startswith("head_o."))[0])
    write_tensors_and_manifest(tmp_path / "seed4", "model.safetensors", dropped, "model.json", {"kind": "arcticnet_sf"})
    with pytest.raises(AssetError, match="seed4"):
        ds.start_weights(ds.build_model(cfg, layers), "real", 4, init, {"data": tiny_world}, layers)
    with pytest.raises(AssetError, match="seed4"):  # found before any export or training
        ds.check_inits(ds.replace(init, seeds=(3, 4)), {"data": tiny_world})

    # a Lightning checkpoint as ARCTIC releases it: weights under "model.", plain hyper-parameters beside
    lightning = {"state_dict": {f"model.{k}": v for k, v in saved.items()}, "hyper_parameters": {"lr": 1e-5}}
    torch.save(lightning, tmp_path / "arctic.ckpt")
    arctic = ds.replace(cfg, model=ds.replace(cfg.model, init=str(tmp_path / "arctic.ckpt")))
    model = ds.build_model(cfg, layers)
    ds.start_weights(model, "real", 0, arctic, {"data": tiny_world}, layers)
    assert all(torch.equal(model.network_state_dict()[k], saved[k]) for k in saved)


def test_export_drops_survive_a_resumed_export(tmp_path, monkeypatch):
    """export_variant reports the whole export, also when a second pass (a fresh dataset,
    counters at zero) finishes what an interrupted one began: samples from ``index.json``,
    drops in all and by reason from every shard's record."""
    from conftest import make_frame

    ds = _downstream()
    reasons = {1: "labels_out_of_crop", 300: "labels_out_of_crop", 520: "empty_render"}

    class _Counting:  # HOGSADataset's frames(g) / batch_size / total_stats
        batch_size = 128

        def __init__(self, bundle=None, data=None, config=None):
            self.dropped = {"labels_out_of_crop": 0, "empty_render": 0}

        def frames(self, g):
            span = range(128 * g, 128 * g + 128)
            for i in span:
                if i in reasons:
                    self.dropped[reasons[i]] += 1
            return [None if i in reasons else make_frame(i) for i in span]

        def total_stats(self):
            return ds.argparse.Namespace(dropped=dict(self.dropped))

    out = tmp_path / "ds"
    cfg = ds.DownstreamConfig()
    cfg = ds.replace(cfg, synthetic=ds.replace(cfg.synthetic, frames=600, render_batch=128))  # shards of 256
    setup = {"bundle": Path("/b"), "data": Path("/d"), "fingerprints": _prints("w0", "b0", "a0"), "backgrounds": out}
    monkeypatch.setattr(ds, "HOGSADataset", _Counting)
    real_frames = ds.dataset_frames_for_shard

    def interrupted(data, num, size):  # the first pass stops at the third shard
        frames = real_frames(data, num, size)

        def shard(k):
            if k == 2:
                raise KeyboardInterrupt
            return frames(k)

        return shard

    monkeypatch.setattr(ds, "dataset_frames_for_shard", interrupted)
    with pytest.raises(KeyboardInterrupt):
        ds.export_variant("full", cfg, setup, out)
    monkeypatch.setattr(ds, "dataset_frames_for_shard", real_frames)
    b = ds.export_variant("full", cfg, setup, out)
    assert (b["requested"], b["samples"], b["written"], b["skipped"]) == (600, 597, 1, 2)
    assert b["dropped_total"] == 3 and b["dropped"] == {"labels_out_of_crop": 2, "empty_render": 1}


def test_other_hands_reach_the_export_and_key_its_frames_and_runs(monkeypatch, tmp_path):
    """``--synthetic-other-hands`` is the loader's ``other_hands`` of every exported variant; it
    names the frames' export and the HOGSA runs' folder, and leaves both alone at 0."""
    ds = _downstream()
    cfg = ds.replace(ds.DownstreamConfig(), synthetic=ds.replace(ds.DownstreamConfig().synthetic, mix="add"))
    other = ds.replace(cfg, synthetic=ds.replace(cfg.synthetic, other_hands=0.5))
    setup = {"bundle": Path("/b"), "data": Path("/d"), "fingerprints": _prints("w0", "b0", "a0")}
    seen = {}

    class Captured(Exception):
        pass

    def fake_write(frames, folder, num, shard, info, progress):
        seen["info"] = info
        raise Captured

    monkeypatch.setattr(ds, "HOGSADataset", lambda bundle, data, config: seen.update(config=config))
    monkeypatch.setattr(ds, "dataset_frames_for_shard", lambda *a: iter(()))
    monkeypatch.setattr(ds, "write_shards", fake_write)
    for c, share in ((cfg, 0.0), (other, 0.5)):
        with pytest.raises(Captured):
            ds.export_variant("full", c, {**setup, "backgrounds": tmp_path}, tmp_path)
        assert seen["config"].sample.other_hands == share
        assert seen["info"]["other_hands"] == share  # the export describes itself
    assert ds.synthetic_key(cfg, frames_only=True)["other_hands"] == 0.0
    assert ds.synthetic_key(other, frames_only=True)["other_hands"] == 0.5
    assert ds.export_dir("full", cfg, setup, tmp_path) != ds.export_dir("full", other, setup, tmp_path)
    assert ds.run_dir("hogsa", 0, other, Path("/o")) == Path("/o/runs/hogsa+add+hands0.5/seed0")
    assert ds.run_dir("hogsa", 0, cfg, Path("/o")) == Path("/o/runs/hogsa+add/seed0")
    assert ds.run_dir("real", 0, other, Path("/o")) == Path("/o/runs/real/seed0")
    with pytest.raises(SystemExit, match="other-hands"):
        ds.validate(ds.replace(cfg, synthetic=ds.replace(cfg.synthetic, other_hands=1.5)))
    ds.validate(other)  # the default world trains two subjects
    one_subject = ds.replace(other, setup=ds.replace(other.setup, preset="tiny"))
    assert {sid for sid, _ in ds.setup_pairs(one_subject.setup)} == {"s01"}
    with pytest.raises(SystemExit, match=r"two training subjects; the world has \['s01'\]"):
        ds.validate(one_subject)  # before any setup is built
    ds.validate(ds.replace(one_subject, synthetic=cfg.synthetic))  # no other hands: one subject is enough


def test_a_setup_data_root_that_is_not_one_is_refused_by_name(tiny_world, tmp_path):
    ds = _downstream()
    cfg = ds.DownstreamConfig()
    for data in (tmp_path / "missing", tmp_path):
        with pytest.raises(SystemExit, match=rf"--setup-data {data}: not an ARCTIC data root"):
            ds.validate(ds.replace(cfg, setup=ds.replace(cfg.setup, data=str(data))))
    (tmp_path / "root" / "arctic_data" / "data").mkdir(parents=True)  # a root without the p1 protocol
    with pytest.raises(SystemExit, match=r"--setup-data .*protocol_p1.json: file is missing"):
        ds.validate(ds.replace(cfg, setup=ds.replace(cfg.setup, data=str(tmp_path / "root"))))
    ds.validate(ds.replace(cfg, setup=ds.replace(cfg.setup, data=str(tiny_world))))  # a world: accepted


def test_interfield_runs_train_evaluate_and_start_from_a_saved_field_model(tiny_world, tmp_path, monkeypatch):
    """--model-kind interfield_sf: InterField-SF trained with its own loss and evaluated with the
    field's average distance and acceleration errors (clip sums of the two average errors), in
    folders and keys of its own; its saved model starts a fine-tune (no camera prior), and a
    saved model of the other kind is refused naming the file; the tables name its metrics."""
    ds = _downstream()
    base = _tiny_cfg(ds, steps=2, evals=1, checkpoint_every=0)
    cfg = ds.replace(base, model=ds.replace(base.model, kind="interfield_sf"))
    setup = {"data": tiny_world, "bundle": Path("/unused"), "fingerprints": _prints("w0", "b0", "a0")}
    val_dataset = ds.val_dataset
    monkeypatch.setattr(ds, "val_dataset", lambda *a: (lambda v: (v[0], v[1][:12]))(val_dataset(*a)))
    monkeypatch.setattr(ds, "camera_prior", lambda *a: pytest.fail("InterField-SF has no camera"))
    monkeypatch.setattr(ds, "training_step", lambda *a, **k: pytest.fail("ArcticNet-SF's step"))
    res = ds.run_arm("real", 0, cfg, setup, tmp_path)
    folder = ds.run_dir("real", 0, cfg, tmp_path)
    assert folder == tmp_path / "runs" / "real+interfield_sf" / "seed0"
    assert set(res["summary"]) == {"avg/ho", "avg/oh", "acc/ho", "acc/oh"} and res["val_frames"] == 12
    assert all(res["summary"][m] is not None and res["summary"][m] > 0 for m in res["summary"])
    assert set(res["loss_terms_last"]) == {"loss/dist/ro", "loss/dist/lo", "loss/dist/or", "loss/dist/ol"}
    for m in ("avg/ho", "avg/oh"):  # the per-clip sums form the split's value again
        sums = np.array([c[m] for c in res["clips"].values()])
        assert sums[:, 0].sum() / sums[:, 1].sum() == pytest.approx(res["summary"][m], abs=1e-6)
    assert json.loads((folder / "model.json").read_text())["kind"] == "interfield_sf"
    model_key = ds.run_settings("real", 0, cfg, setup)["model"]
    assert model_key["kind"] == "interfield_sf" and "camera_prior" not in model_key

    from safetensors.torch import load_file

    from hogsa_loader.assets.arctic import ArcticRoot
    from hogsa_loader.baselines.engine import BodyLayers
    from hogsa_loader.errors import AssetError

    layers = BodyLayers.from_root(ArcticRoot(tiny_world))
    init = ds.replace(cfg, model=ds.replace(cfg.model, init=str(folder / "model.safetensors")))
    model = ds.build_model(cfg, layers, tiny_world)
    ds.start_weights(model, "real", 0, init, setup, layers)
    saved = load_file(folder / "model.safetensors")
    assert all(torch.equal(model.network_state_dict()[k], saved[k]) for k in saved)
    arctic = ds.build_model(base, layers)
    torch.save(arctic.network_state_dict(), tmp_path / "arcticnet.pt")
    other = ds.replace(cfg, model=ds.replace(cfg.model, init=str(tmp_path / "arcticnet.pt")))
    with pytest.raises(AssetError, match=r"arcticnet.pt.*InterField-SF"):
        ds.check_inits(other, setup)
    from hogsa_loader.baselines import load_saved_model

    with pytest.raises(AssetError, match=r"model.json.*'interfield_sf' model, not an ArcticNet-SF"):
        load_saved_model(folder / "model.safetensors", layers.mano_r, layers.mano_l, layers.objects)

    summ = {"avg/ho": 9.0, "avg/oh": 10.0, "acc/ho": 1.0, "acc/oh": 2.0}
    lower = {**summ, "avg/ho": 8.5, "avg/oh": 9.0}
    results = {"real": {0: {"summary": summ}}, "hogsa": {0: {"summary": lower}}}
    agg = ds.aggregate(results, "interfield_sf")
    assert agg["paired"]["hogsa - real"]["avg/oh"]["per_seed"] == {0: -1.0}
    md = ds.markdown(agg, cfg, "2 CPU cores", {})
    assert "| InterField-SF (real) | 9.00 | 10.00 | 1.00 | 2.00 |" in md and "Δavg. h→o (mm) per seed" in md
