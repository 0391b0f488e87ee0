"""ARCTIC's trainer as a client: PyTorch Lightning's DDP strategy on 2 CPU processes (torchrun,
real processes) trains ArcticNet-SF on ``wrap_train_loader``'s batches
(``examples/lightning_arcticnet.py``, run by the command of ``docs/real-arctic.md`` at toy
sizes, on the CPU). The real half gets a distributed sampler, the synthetic
half each rank's share, the ``set_epoch`` Lightning calls reaches both, ``pin_memory`` is kept,
and both ranks end with the same weights. Also :func:`distributed_loader` on its own."""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from torch.utils.data import BatchSampler, DataLoader, RandomSampler, TensorDataset, WeightedRandomSampler

from hogsa_loader.sample.mixing import distributed_loader

ROOT = Path(__file__).resolve().parents[2]
TOY = ["--backbone", "resnet18", "--epochs", "2", "--batches-per-epoch", "2", "--batch-size", "4", "--img-res", "64"]
TOY += ["--lr", "1e-4", "--method", "no_pom"]


def _documented_command() -> list[str]:
    """The Lightning command of ``docs/real-arctic.md``, on the CPU."""
    doc = (ROOT / "docs" / "real-arctic.md").read_text()
    (line,) = re.findall(r"^\$ (torchrun .*lightning_arcticnet\.py.*)$", doc, re.M)
    return [a if a != "gpu" else "cpu" for a in shlex.split(line)]


@pytest.fixture(scope="module")
def lightning_run(tiny_world, untrained_bundle, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("lightning")
    (tmp / "data").symlink_to(tiny_world, target_is_directory=True)
    (tmp / "build").mkdir()
    (tmp / "build" / "bundle").symlink_to(untrained_bundle, target_is_directory=True)
    (tmp / "examples").symlink_to(ROOT / "examples", target_is_directory=True)
    env = {k: v for k, v in os.environ.items() if k not in ("RANK", "WORLD_SIZE", "LOCAL_RANK")}
    argv = [sys.executable, "-m", "torch.distributed.run", *_documented_command()[1:], *TOY]
    proc = subprocess.run([*argv, "--ckpt-every", "1"], capture_output=True, text=True, env=env, cwd=tmp, timeout=900)
    assert proc.returncode == 0, proc.stderr[-4000:]
    out = tmp / "lightning"
    # the same run resumed by Lightning from its checkpoint after step 1 (mid-epoch 0)
    resumed = [*argv, "--resume", str(out / "checkpoints" / "step=1.ckpt")]
    resumed[resumed.index("--out") + 1] = "resumed"
    proc = subprocess.run(resumed, capture_output=True, text=True, env=env, cwd=tmp, timeout=900)
    assert proc.returncode == 0, proc.stderr[-4000:]

    def rows(folder):
        logs = {r: (folder / f"lightning.rank{r}.jsonl").read_text().splitlines() for r in (0, 1)}
        return {r: [json.loads(x) for x in lines] for r, lines in logs.items()}

    whole, again = rows(out), rows(tmp / "resumed")
    return {r: (rs[:-1], rs[-1], again[r][:-1]) for r, rs in whole.items()}


def test_each_rank_trains_on_its_own_real_and_synthetic_share(lightning_run):
    (steps0, end0, _), (steps1, end1, _) = lightning_run[0], lightning_run[1]
    assert [s["epoch"] for s in steps0] == [s["epoch"] for s in steps1] == [0, 0, 1, 1]
    for epoch in (0, 1):
        real = [{n for s in steps if s["epoch"] == epoch for n in s["real"]} for steps in (steps0, steps1)]
        syn = [{n for s in steps if s["epoch"] == epoch for n in s["synthetic"]} for steps in (steps0, steps1)]
        assert len(real[0]) == len(real[1]) == 4 and not real[0] & real[1]  # DistributedSampler: disjoint
        assert len(syn[0]) == len(syn[1]) == 4 and not syn[0] & syn[1]  # the stream's rank shares
    for s in steps0 + steps1:
        assert s["real_sampler"] == "DistributedSampler"
        assert s["pin_memory"] is True  # the real loader's pin_memory kept on its per-rank copy
    assert end0["world_size"] == end1["world_size"] == 2
    assert end0["weights"] == end1["weights"]  # DDP: one model


def test_lightnings_set_epoch_reaches_both_halves(lightning_run):
    for steps, _, _ in lightning_run.values():
        for s in steps:
            assert s["real_sampler_epoch"] == s["synthetic_epoch"] == s["epoch"]
        first = [n for s in steps if s["epoch"] == 0 for n in s["real"] + s["synthetic"]]
        second = [n for s in steps if s["epoch"] == 1 for n in s["real"] + s["synthetic"]]
        assert first != second  # a new real order and a new synthetic stream in epoch 1
        syn = [{n for s in steps if s["epoch"] == e for n in s["synthetic"]} for e in (0, 1)]
        assert not syn[0] & syn[1]


def test_lightning_resumes_mid_epoch_on_the_batches_of_the_uninterrupted_run(lightning_run):
    """Lightning saves the mixed loader's state (every rank's place in its stream) in its
    checkpoint and loads it before the epoch's ``set_epoch``: the resumed run trains steps 2-4
    on exactly the real and synthetic samples of the uninterrupted run, on each rank."""
    for steps, _, resumed in lightning_run.values():
        assert [(s["epoch"], s["real"], s["synthetic"]) for s in resumed] == [
            (s["epoch"], s["real"], s["synthetic"]) for s in steps[1:]
        ]


def test_distributed_loader_keeps_the_settings_and_splits_the_samples():
    ds = TensorDataset(torch.arange(10))
    gen = torch.Generator().manual_seed(3)
    loader = DataLoader(ds, batch_size=2, shuffle=True, drop_last=True, pin_memory=True, generator=gen)
    parts = [distributed_loader(loader, rank, 3, seed=5) for rank in range(3)]
    seen = [torch.cat([b[0] for b in part]).tolist() for part in parts]
    assert [len(s) for s in seen] == [2, 2, 2]  # 10 // 3 = 3 per rank, one batch of 2 (drop_last kept)
    assert not set(seen[0]) & set(seen[1]) and not set(seen[1]) & set(seen[2]) and not set(seen[0]) & set(seen[2])
    for part in parts:
        assert part.sampler.shuffle and part.sampler.seed == 5 and part.sampler.drop_last
        assert part.batch_size == 2 and part.drop_last and part.pin_memory and part.generator is gen
    kept = distributed_loader(DataLoader(ds, batch_size=5), 1, 2)
    assert not kept.sampler.shuffle and [b[0].tolist() for b in kept] == [[1, 3, 5, 7, 9]]


def test_distributed_loader_refuses_a_sampler_it_cannot_split():
    ds = TensorDataset(torch.arange(4))
    weighted = DataLoader(ds, batch_size=2, sampler=WeightedRandomSampler([1.0] * 4, 4))
    with pytest.raises(ValueError, match="WeightedRandomSampler.*DistributedSampler"):
        distributed_loader(weighted, 0, 2)
    batches = DataLoader(ds, batch_sampler=BatchSampler(RandomSampler(ds), 2, True))  # its own batch sampler
    with pytest.raises(ValueError, match="batch_size="):
        distributed_loader(batches, 0, 2)
    with pytest.raises(ValueError, match="without replacement"):
        distributed_loader(DataLoader(ds, batch_size=2, sampler=RandomSampler(ds, replacement=True)), 0, 2)
