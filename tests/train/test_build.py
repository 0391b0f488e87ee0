"""``hogsa build``: the stage graph, its keys, protocol-safe subjects, the TOML config and the
command line (torchrun and srun: ``tests/docs/test_walkthrough.py``)."""

from __future__ import annotations

import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import pytest
from conftest import tiny_build_config as tiny_config

from hogsa_loader.errors import UsageError
from hogsa_loader.system import process_slot, rank_device
from hogsa_loader.train.build import build, build_status, config_toml, plan_build, read_config
from hogsa_loader.train.stages import StageNode, StageRecords, run_stage_graph


# ---------------------------------------------------------------------------- the stage graph
def _timed_stage(folder, log, name: str, seconds: float):
    """A stage build that logs its start and end times and creates its output folder."""

    def build_it() -> str:
        with open(log, "a") as f:
            f.write(f"start {name} {time.time()}\n")
        time.sleep(seconds)
        (folder / name).mkdir()
        with open(log, "a") as f:
            f.write(f"end {name} {time.time()}\n")
        return name

    return build_it


def test_stage_graph_runs_each_stage_after_what_it_needs(tmp_path):
    """Stages start only once the stages they need have ended (side by side on forked
    processes where there are two cores, else in order); a second run reuses all of them."""
    log = tmp_path / "log.txt"
    nodes = [
        StageNode("a", "ka", [tmp_path / "a"], _timed_stage(tmp_path, log, "a", 0.4)),
        StageNode("b", "kb", [tmp_path / "b"], _timed_stage(tmp_path, log, "b", 0.1)),
        StageNode("c", "kc", [tmp_path / "c"], _timed_stage(tmp_path, log, "c", 0.0), needs=("a", "b")),
        StageNode("d", "kd", [tmp_path / "d"], _timed_stage(tmp_path, log, "d", 0.0), needs=("b",)),
    ]
    stages = StageRecords(tmp_path / "out", lambda s: None)
    run_stage_graph(stages, nodes, lambda s: None)
    t = {tuple(line.split()[:2]): float(line.split()[2]) for line in log.read_text().splitlines()}
    assert len(t) == 8
    assert t["start", "c"] >= max(t["end", "a"], t["end", "b"])
    assert t["start", "d"] >= t["end", "b"]
    if sys.platform.startswith("linux") and len(os.sched_getaffinity(0)) > 1:  # side by side
        assert t["start", "b"] < t["end", "a"] and t["start", "a"] < t["end", "b"]
    assert set(stages.seconds) == {"a", "b", "c", "d"} and stages.reused == []
    again = StageRecords(tmp_path / "out", lambda s: None)
    run_stage_graph(again, nodes, lambda s: None)
    assert sorted(again.reused) == ["a", "b", "c", "d"]
    assert len(log.read_text().splitlines()) == 8  # nothing was built again

    def broken() -> None:
        raise RuntimeError("stage failed on purpose")

    bad = [
        StageNode("e", "ke", [tmp_path / "e"], broken),
        StageNode("f", "kf", [tmp_path / "f"], _timed_stage(tmp_path, log, "f", 0.0)),
    ]
    with pytest.raises(RuntimeError, match="on purpose"):
        run_stage_graph(StageRecords(tmp_path / "out", lambda s: None), bad, lambda s: None)
    with pytest.raises(ValueError, match="not listed before it"):
        run_stage_graph(
            StageRecords(tmp_path / "out", lambda s: None),
            [StageNode("g", "kg", [tmp_path / "g"], broken, needs=("h",))],
            lambda s: None,
        )


# ---------------------------------------------------------------------------- keys and plans
def test_every_stage_setting_is_in_its_key_and_paths_are_not(tiny_world, tmp_path):
    cfg = tiny_config(tiny_world, tmp_path / "a")
    keys = {n.name: n.key for n in plan_build(cfg).nodes}
    assert list(keys) == ["hogs/s01_box", "contactnet", "bank", "srm", "bundle"]
    # another output folder: the same keys (a moved build stays valid)
    assert {
        n.name: n.key for n in plan_build(replace(cfg, run=replace(cfg.run, out=str(tmp_path / "b")))).nodes
    } == keys
    changes = {
        "bank finger noise": replace(cfg, bank=replace(cfg.bank, pom=replace(cfg.bank.pom, finger_scale=0.5))),
        "bank variants": replace(cfg, bank=replace(cfg.bank, data=replace(cfg.bank.data, variants=3))),
        "bank frames": replace(cfg, bank=replace(cfg.bank, data=replace(cfg.bank.data, frames="all"))),
        "srm adversarial weight": replace(cfg, srm=replace(cfg.srm, loss=replace(cfg.srm.loss, lambda_gan=0.0))),
        "hogs steps": replace(cfg, hogs=replace(cfg.hogs, optim=replace(cfg.hogs.optim, iters=5))),
        "seed": replace(cfg, run=replace(cfg.run, seed=1)),
    }
    changed = {what: {n.name: n.key for n in plan_build(c).nodes} for what, c in changes.items()}
    for what, k in changed.items():
        assert k["bundle"] != keys["bundle"], what
    assert changed["bank finger noise"]["hogs/s01_box"] == keys["hogs/s01_box"]  # only what depends on it
    assert changed["bank finger noise"]["srm"] == keys["srm"]
    assert changed["srm adversarial weight"]["bank"] == keys["bank"]
    assert changed["hogs steps"]["srm"] != keys["srm"] and changed["hogs steps"]["bank"] == keys["bank"]
    assert len({k["bundle"] for k in changed.values()}) == len(changes)
    # every process of a multi-GPU build (cuda:LOCAL_RANK) keys its stages as a plain cuda build does
    on = {
        d: {n.name: n.key for n in plan_build(replace(cfg, run=replace(cfg.run, device=d))).nodes}
        for d in ("cuda", "cuda:0", "cuda:1")
    }
    assert on["cuda"] == on["cuda:0"] == on["cuda:1"] != keys
    # ContactNet is keyed by what it reads: allowing a held-out subject is another ContactNet
    with pytest.warns(UserWarning, match="s05"):
        allowed = {
            n.name: n.key for n in plan_build(tiny_config(tiny_world, tmp_path / "a", allow_held_out=("s05",))).nodes
        }
    assert allowed["contactnet"] != keys["contactnet"] and allowed["hogs/s01_box"] == keys["hogs/s01_box"]


def test_stages_build_with_the_settings_of_their_job(tiny_world, tmp_path, monkeypatch):
    """Each stage hands its job exactly the configured settings, with the build's root, folders,
    seed and device filled in."""
    import hogsa_loader.train.build as b

    cfg = tiny_config(tiny_world, tmp_path / "out")
    cfg = replace(
        cfg, run=replace(cfg.run, seed=7), bank=replace(cfg.bank, pom=replace(cfg.bank.pom, finger_scale=0.5))
    )
    seen = {}

    class Stop(Exception):
        pass

    def grab(name):
        def f(job, **kw):
            seen[name] = job
            raise Stop

        return f

    monkeypatch.setattr(b, "build_pose_bank", grab("bank"))
    monkeypatch.setattr(b, "fit_contactnet", grab("contactnet"))
    monkeypatch.setattr(b, "HogsTrainer", grab("hogs"))
    monkeypatch.setattr(b, "SRMTrainer", grab("srm"))
    for node in plan_build(cfg).nodes[:4]:
        with pytest.raises(Stop):
            node.build()
    out = tmp_path / "out"
    assert seen["hogs"].data.root == str(tiny_world) and seen["hogs"].run.out == str(out / "runs/hogs/s01_box")
    assert seen["hogs"].run.seed == 7 and seen["hogs"].optim.iters == 4 and seen["hogs"].data.sequences is not None
    assert all(s.split("_", 1)[1] in ("grab_01", "use_01") for s in seen["hogs"].data.sequences)  # the paper's choice
    assert seen["contactnet"].optim.seed == 7 and seen["contactnet"].run.out == str(out / "runs/contactnet")
    assert seen["bank"].pom.finger_scale == 0.5 and seen["bank"].data.contactnet == str(out / "runs/contactnet")
    assert seen["bank"].run.seed == 7 and all(s.startswith("s01/box_") for s in seen["bank"].data.sequences)
    assert seen["srm"].data.hogs == str(out / "runs/hogs") and seen["srm"].run.seed == 7
    assert seen["srm"].data.runs == ("s01_box",)  # this build's runs, not every run left in the folder


# ---------------------------------------------------------------------------- protocol safety
def test_default_pairs_are_the_training_split_only(tiny_world, tmp_path):
    plan = plan_build(tiny_config(tiny_world, tmp_path, pairs=None))
    subjects = {s for s, _, _ in plan.pairs}
    assert subjects and not subjects & {"s03", "s05"}
    with pytest.raises(UsageError, match=r"s05 \(val\) held out"):
        plan_build(tiny_config(tiny_world, tmp_path, pairs=("s05/box",)))
    with pytest.warns(UserWarning, match="s05"):
        allowed = plan_build(tiny_config(tiny_world, tmp_path, pairs=("s05/box",), allow_held_out=("s05",)))
    assert [(s, o) for s, o, _ in allowed.pairs] == [("s05", "box")]
    with pytest.raises(UsageError, match="SUBJECT/OBJECT"):
        plan_build(tiny_config(tiny_world, tmp_path, pairs=("s01",)))


def test_a_default_build_reads_no_held_out_frame(tiny_world, tmp_path, monkeypatch):
    """Every stage of a default build, instrumented at the dataset reader: no sequence of a
    held-out subject (s05 in the tiny world) is read."""
    from hogsa_loader.assets.arctic import ArcticRoot

    log = tmp_path / "read.txt"  # the stages may run on forked processes: they append here
    original = ArcticRoot.sequence

    def spy(self, sid, seq):
        with open(log, "a") as fh:
            fh.write(f"{sid}\n")
        return original(self, sid, seq)

    monkeypatch.setattr(ArcticRoot, "sequence", spy)
    bundle, seconds = build(tiny_config(tiny_world, tmp_path / "out", pairs=None), log=None)
    assert (bundle / "manifest.json").is_file() and set(seconds) >= {"hogs/s01_box", "contactnet", "bank", "srm"}
    read = log.read_text().split()
    assert read and set(read) == {"s01"}


# ---------------------------------------------------------------------------- processes
def test_process_slot_and_device_from_the_launchers():
    assert process_slot({}) == (0, 1)
    assert process_slot({"RANK": "1", "WORLD_SIZE": "2", "LOCAL_RANK": "1"}) == (1, 2)
    assert process_slot({"SLURM_PROCID": "3", "SLURM_STEP_NUM_TASKS": "4", "SLURM_NTASKS": "4"}) == (3, 4)
    assert process_slot({"SLURM_NTASKS": "4", "SLURM_PROCID": "0"}) == (0, 1)  # an sbatch script itself
    assert rank_device("cuda", {"LOCAL_RANK": "1"}) == "cuda:1"
    assert rank_device("cuda", {"SLURM_LOCALID": "2"}) == "cuda:2"
    assert rank_device("cuda:0", {"LOCAL_RANK": "1"}) == "cuda:0" and rank_device("cpu", {"LOCAL_RANK": "1"}) == "cpu"


def test_gpus_refuses_repeated_ids_and_a_launcher(tmp_path, monkeypatch, capsys):
    from hogsa_loader.cli.build import _without_gpus, main

    assert _without_gpus(["--out", "b", "--gpus", "0,1", "--seed", "2", "--gpus=3"]) == ["--out", "b", "--seed", "2"]
    args = ["--data", str(tmp_path), "--out", str(tmp_path / "b")]
    assert main([*args, "--gpus", "0,0"]) == 2 and "distinct GPU ids" in capsys.readouterr().err
    monkeypatch.setenv("WORLD_SIZE", "2")
    assert main([*args, "--gpus", "0,1"]) == 2 and "not under torchrun or srun" in capsys.readouterr().err


# ---------------------------------------------------------------------------- the command line
def test_config_file_round_trips_and_flags_override_it(tiny_world, tmp_path, capsys):
    from hogsa_loader.cli.build import parse_build_args
    from hogsa_loader.cli.main import main

    cfg = tiny_config(tiny_world, tmp_path / "out")
    toml = tmp_path / "b.toml"
    toml.write_text(config_toml(cfg))
    assert read_config(toml) == cfg
    again, _ = parse_build_args(["--config", str(toml), "--hogs-optim-iters", "9", "--seed", "3"])
    assert again == replace(
        cfg, hogs=replace(cfg.hogs, optim=replace(cfg.hogs.optim, iters=9)), run=replace(cfg.run, seed=3)
    )
    assert main(["build", "--print-config"]) == 0
    printed = capsys.readouterr().out
    assert "[hogs.optim]" in printed and "iters = 2000" in printed and "subject =" not in printed
    bad = tmp_path / "bad.toml"
    for text, needle in (
        ("[hogs.optim]\nitres = 3\n", "itres"),
        ("[hogs.run]\ndevice = 'cuda'\n", "set by the build"),  # the build's own --device decides
        ("[bank.data]\nfrequency = 2\n", "frequency"),
    ):
        bad.write_text(text)
        assert main(["build", "--config", str(bad)]) == 2
        err = capsys.readouterr().err
        assert needle in err and str(bad) in err and err.count("\n") == 1, err
    # an unset list round-trips (TOML has no null): the demo's "every sequence" setting
    from hogsa_world.demo import DemoConfig, build_config

    demo = build_config(DemoConfig(), Path(tiny_world), tmp_path / "demo")
    assert demo.data.sequences_like is None
    (tmp_path / "demo.toml").write_text(config_toml(demo))
    assert read_config(tmp_path / "demo.toml") == demo


def test_status_says_what_is_built_and_left(tiny_world, tmp_path, capsys):
    from hogsa_loader.cli.main import main

    cfg = tiny_config(tiny_world, tmp_path / "out")
    assert [r["state"] for r in build_status(cfg)] == ["todo"] * 5
    toml = tmp_path / "b.toml"
    toml.write_text(config_toml(cfg))
    assert main(["build", "--config", str(toml), "--status"]) == 0
    assert "0 of 5 stages done; left: hogs/s01_box, contactnet, bank, srm, bundle" in capsys.readouterr().out
    assert main(["build", "--data", str(tiny_world), "--out", str(tmp_path / "x"), "--pairs", "s05/box"]) == 2
    assert "s05 (val) held out" in capsys.readouterr().err


def test_every_stage_runs_on_one_thread_wherever_it_runs(tmp_path):
    """A stage built alone (in this process) and one built beside another (a forked process)
    use one torch thread both, so what a stage builds does not depend on the schedule."""
    import torch

    log = tmp_path / "threads.txt"

    def stage(name: str):
        def build_it() -> None:
            with open(log, "a") as fh:
                fh.write(f"{name} {torch.get_num_threads()}\n")
            (tmp_path / name).mkdir()

        return build_it

    nodes = [
        StageNode("a", "ka", [tmp_path / "a"], stage("a")),
        StageNode("b", "kb", [tmp_path / "b"], stage("b")),
        StageNode("c", "kc", [tmp_path / "c"], stage("c"), needs=("a", "b")),  # alone: in this process
    ]
    before = torch.get_num_threads()
    run_stage_graph(StageRecords(tmp_path / "out", lambda s: None), nodes, lambda s: None)
    assert sorted(log.read_text().split("\n")[:-1]) == ["a 1", "b 1", "c 1"]
    assert torch.get_num_threads() == before
    run_stage_graph(
        StageRecords(tmp_path / "one", lambda s: None),
        [StageNode("d", "kd", [tmp_path / "d"], stage("d"))],
        lambda s: None,
    )
    assert log.read_text().split("\n")[-2] == "d 1"  # a build of one stage (no fork) too
