"""Protocol safety: no training stage reads a subject the dataset holds out unless the user
names it; the stages are run on the tiny world (s01 train, s05 val) with the dataset reader
instrumented."""

from __future__ import annotations

import subprocess
import sys
import warnings
from pathlib import Path

import pytest

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.assets.protocol import ARCTIC_HELD_OUT, HeldOutWarning, held_out_subjects, training_subjects
from hogsa_loader.errors import UsageError

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def reads(monkeypatch):
    """Every (subject, sequence) the dataset reader is asked for while the test runs."""
    seen: list[tuple[str, str]] = []
    original = ArcticRoot.sequence

    def sequence(self, sid, seq):
        seen.append((sid, seq))
        return original(self, sid, seq)

    monkeypatch.setattr(ArcticRoot, "sequence", sequence)
    return seen


def test_held_out_subjects_come_from_the_protocol_files(tiny_world, tmp_path):
    root = ArcticRoot(tiny_world)
    assert held_out_subjects(root) == {"s05": "val"}
    bare = tmp_path / "data"
    (bare / "arctic_data" / "data").mkdir(parents=True)
    assert held_out_subjects(ArcticRoot(bare)) == ARCTIC_HELD_OUT  # no protocol file: ARCTIC's


def test_training_subjects_refuse_held_out_ones_unless_named(tiny_world):
    root = ArcticRoot(tiny_world)
    assert training_subjects(root) == ["s01"]
    with pytest.raises(UsageError, match=r"s05 \(val\) held out by the dataset's protocol.*--allow-held-out"):
        training_subjects(root, ["s01", "s05"], stage="ContactNet")
    with pytest.warns(HeldOutWarning, match=r"reads held-out subject\(s\) \['s05'\]"):
        assert training_subjects(root, ["s05"], ["s05"]) == ["s05"]
    with pytest.warns(HeldOutWarning):
        assert training_subjects(root, None, ["s05"]) == ["s01", "s05"]
    with pytest.raises(UsageError, match="does not hold out"):
        training_subjects(root, None, ["s01"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert training_subjects(root, ["s01"]) == ["s01"]  # no warning without held-out subjects


def test_default_contactnet_reads_no_held_out_subject(tiny_world, tmp_path, reads):
    from hogsa_loader.train.pom_config import (
        ContactNetDataConfig,
        ContactNetJobConfig,
        ContactNetOptimConfig,
        ContactNetRunConfig,
    )
    from hogsa_loader.train.pom_jobs import fit_contactnet

    job = ContactNetJobConfig(
        data=ContactNetDataConfig(root=str(tiny_world)),
        optim=ContactNetOptimConfig(iters=2, batch=4, points=64),
        run=ContactNetRunConfig(out=str(tmp_path / "cn"), val_every=2),
    )
    m = fit_contactnet(job, progress=False)
    assert reads and {sid for sid, _ in reads} == {"s01"}
    assert m["train_subjects"] == ["s01"] and m["val_subjects"] == [] and m["held_out_read"] == []
    bad = ContactNetJobConfig(
        data=ContactNetDataConfig(root=str(tiny_world), val_subjects=("s05",)),
        optim=job.optim,
        run=ContactNetRunConfig(out=str(tmp_path / "cn2")),
    )
    with pytest.raises(UsageError, match="s05"):
        fit_contactnet(bad, progress=False)


def test_default_pose_bank_selects_no_held_out_subject(tiny_world):
    from hogsa_loader.train.pom_config import BankDataConfig, PoseBankConfig
    from hogsa_loader.train.pom_jobs import _bank_sequences

    root = ArcticRoot(tiny_world)

    def bank(**data):
        return PoseBankConfig(data=BankDataConfig(root=str(tiny_world), contactnet="cn", **data))

    assert {s.split("/")[0] for s in _bank_sequences(root, bank())} == {"s01"}
    s05 = [s for s in root.sequences() if s.startswith("s05/")]
    for asked in (dict(subjects=("s05",)), dict(sequences=tuple(s05))):
        with pytest.raises(UsageError, match=r"the pose bank: s05 \(val\)"):
            _bank_sequences(root, bank(**asked))
    with pytest.warns(HeldOutWarning):
        assert _bank_sequences(root, bank(subjects=("s05",), allow_held_out=("s05",))) == s05


def _train_all(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "hogsa_loader.cli.train_all_hogs", *args, "--dry-run"],
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_train_all_hogs_trains_the_training_split_by_default(tiny_world, tmp_path):
    out = _train_all("--data", str(tiny_world), "--out", str(tmp_path / "runs"))
    assert out.returncode == 0, out.stderr[-2000:]
    assert "s01" in out.stdout and "s05" not in out.stdout
    refused = _train_all("--data", str(tiny_world), "--out", str(tmp_path / "runs"), "--split", "all")
    assert refused.returncode == 2 and "s05 (val) held out" in refused.stderr and "--allow-held-out" in refused.stderr
    named = _train_all(
        "--data", str(tiny_world), "--out", str(tmp_path / "runs"), "--split", "val", "--allow-held-out", "s05"
    )
    assert named.returncode == 0 and "s05" in named.stdout and "held-out subject(s) ['s05']" in named.stderr


def test_train_all_hogs_takes_its_share_under_srun_and_torchrun(tiny_world, tmp_path):
    """Real environments of the launchers: srun's SLURM_PROCID / SLURM_STEP_NUM_TASKS and torchrun's
    RANK / WORLD_SIZE pick the process's share; LOCAL_RANK / SLURM_LOCALID its GPU."""
    import os

    from conftest import job

    base = [sys.executable, "-m", "hogsa_loader.cli.train_all_hogs", "--data", str(tiny_world)]
    base += ["--out", str(tmp_path / "runs"), "--split", "all", "--allow-held-out", "s05", "--dry-run"]
    clean = {k: v for k, v in os.environ.items() if not k.startswith(("SLURM_", "RANK", "WORLD_SIZE", "LOCAL_RANK"))}
    for env, slot in (
        ({"SLURM_PROCID": "1", "SLURM_STEP_NUM_TASKS": "2", "SLURM_NTASKS": "2"}, "process 1/2"),
        ({"SLURM_PROCID": "0", "SLURM_NTASKS": "4"}, "process 0/1"),  # an sbatch script itself: every pair
        ({"RANK": "0", "WORLD_SIZE": "3"}, "process 0/3"),
    ):
        out = subprocess.run(base, env={**clean, **env}, capture_output=True, text=True, timeout=300)
        assert out.returncode == 0 and slot in out.stdout, (out.stdout, out.stderr[-2000:])
    tah = job("train_all_hogs")
    rest = ["--optim-iters", "5", "--device", "cuda"]
    assert tah.rank_device(rest, {"LOCAL_RANK": "3"})[-1] == "cuda:3"
    assert tah.rank_device(rest, {"SLURM_LOCALID": "1"})[-1] == "cuda:1"
    assert tah.rank_device(rest, {}) == rest
    assert tah.rank_device(["--device", "cuda:0"], {"LOCAL_RANK": "2"}) == ["--device", "cuda:0"]


def test_h2o_holds_out_subject4_under_each_of_its_folder_names(tmp_path):
    from hogsa_loader.assets.h2o import H2ORoot

    for names in (("subject1", "subject4"), ("subject1_ego", "subject4_ego"), ("subject2_pose", "subject4_pose")):
        root_dir = tmp_path / "_".join(names)
        for n in names:
            (root_dir / n).mkdir(parents=True)
        root = H2ORoot(root_dir)
        assert sorted(root.subjects()) == sorted(names)
        assert held_out_subjects(root) == {names[1]: "test"}
        assert training_subjects(root) == [names[0]]
        with pytest.raises(UsageError, match=f"{names[1]} \\(test\\)"):
            training_subjects(root, [names[1]])
