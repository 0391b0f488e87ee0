"""``hogsa finetune`` with 2 gloo ranks under torchrun and as srun starts them (real processes):
each rank's synthetic samples are its own, the weights are the same on both ranks after every
step, the loss is finite, ARCTIC's metrics are written, and a resumed run continues on the same
batches."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

ARGS = [
    "--log-weights",
    "--method",
    "no_pom",
    "--backbone",
    "resnet18",
    "--img-res",
    "64",
    "--batch-size",
    "4",
    "--lr",
    "1e-4",
    "--max-val",
    "4",
]


def _torchrun(tmp_path: Path, out: Path, bundle: Path, data: Path, steps: int) -> subprocess.Popen:
    """A 2-rank fine-tune, started (``_wait`` for it)."""
    env = {k: v for k, v in os.environ.items() if k not in ("RANK", "WORLD_SIZE", "LOCAL_RANK")}
    argv = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2"]
    argv += ["-m", "hogsa_loader.cli.finetune", "--data", str(data), "--bundle", str(bundle), "--out", str(out)]
    argv += [*ARGS, "--steps", str(steps), "--ckpt-every", "1"]
    return subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path)


def _srun(tmp_path: Path, out: Path, bundle: Path, data: Path, steps: int) -> list[subprocess.Popen]:
    """The same fine-tune as two processes with the variables ``srun --ntasks 2`` sets, meeting
    at ``MASTER_ADDR`` / ``MASTER_PORT`` as the docs ask of a SLURM user."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {k: v for k, v in os.environ.items() if k not in ("RANK", "WORLD_SIZE", "LOCAL_RANK")}
    env.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), SLURM_STEP_NUM_TASKS="2", SLURM_NTASKS="2")
    # torchrun sets OMP_NUM_THREADS=1 for several processes per node; the weights' bits depend
    # on the intra-op thread count, so the srun processes get the same to match them
    env["OMP_NUM_THREADS"] = "1"
    argv = [sys.executable, "-m", "hogsa_loader.cli.finetune", "--data", str(data), "--bundle", str(bundle)]
    argv += ["--out", str(out), *ARGS, "--steps", str(steps), "--ckpt-every", "1"]
    pipe = subprocess.PIPE
    return [
        subprocess.Popen(
            argv, stdout=pipe, stderr=pipe, text=True, cwd=tmp_path, env={**env, "SLURM_PROCID": r, "SLURM_LOCALID": r}
        )
        for r in ("0", "1")
    ]


def _wait(*procs: subprocess.Popen) -> None:
    for proc in procs:
        _, err = proc.communicate(timeout=900)
        assert proc.returncode == 0, err[-4000:]


def _log(out: Path, rank: int) -> list[dict]:
    return [json.loads(line) for line in (out / f"log.rank{rank}.jsonl").read_text().splitlines()]


@pytest.fixture(scope="module")
def two_ranks(tiny_world, untrained_bundle, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("finetune")
    whole, cut = tmp / "whole", tmp / "cut"
    _wait(  # side by side: two runs of their own, one under torchrun, one as srun starts it
        _torchrun(tmp, whole, untrained_bundle, tiny_world, steps=3),
        *_srun(tmp, cut, untrained_bundle, tiny_world, steps=2),
    )
    _wait(_torchrun(tmp, cut, untrained_bundle, tiny_world, steps=3))  # resumed from step 2, under torchrun
    return whole, cut


def test_ranks_train_one_model_on_their_own_synthetic_samples(two_ranks):
    whole, _ = two_ranks
    r0, r1 = _log(whole, 0), _log(whole, 1)
    assert [r["step"] for r in r0] == [r["step"] for r in r1] == [1, 2, 3]
    for a, b in zip(r0, r1):
        assert a["weights"] == b["weights"]  # DDP: one model
        assert len(a["synthetic"]) == len(b["synthetic"]) == 2  # half of each batch of 4
        assert not set(a["synthetic"]) & set(b["synthetic"])
        assert not set(a["real"]) & set(b["real"])  # DistributedSampler
        assert a["loss"] == a["loss"] and abs(a["loss"]) < float("inf")
    every0 = {n for r in r0 for n in r["synthetic"]}
    every1 = {n for r in r1 for n in r["synthetic"]}
    assert not every0 & every1 and len(every0) == 6  # disjoint over the whole run, no repeats
    assert len({r["weights"] for r in r0}) == 3  # every step moved the weights
    result = json.loads((whole / "result.json").read_text())
    assert result["steps"] == 3 and result["weights"] == r0[-1]["weights"]
    assert result["metrics"]["frames"] == 4 and "mpjpe/ra/h" in result["metrics"]["summary"]
    assert (whole / "model.safetensors").is_file() and (whole / "model.json").is_file()


def test_a_resumed_run_continues_on_the_same_batches(two_ranks):
    """The run cut after step 2 was started as srun starts it and resumed under torchrun: the
    launchers give the same ranks, so its batches and weights are the uncut torchrun run's."""
    whole, cut = two_ranks
    for rank in (0, 1):
        a, b = _log(whole, rank), _log(cut, rank)
        assert [r["step"] for r in b] == [1, 2, 3]
        assert [(r["synthetic"], r["real"]) for r in a] == [(r["synthetic"], r["real"]) for r in b]
        assert [r["weights"] for r in a] == [r["weights"] for r in b]
    final = [json.loads((run / "result.json").read_text())["weights"] for run in (whole, cut)]
    assert final[0] == final[1]
    # the checkpoints hold each rank's place in its synthetic stream (the resumed run started
    # from it instead of rendering the samples of steps 1-2 again, and counted on from there)
    state = json.loads((cut / "checkpoints" / "step_0000003" / "trainer.json").read_text())
    stream = state["stream"]
    assert (stream["batches"], stream["synthetic_taken"]) == (3, 6)
    ranks = stream["synthetic"]  # each rank's place in its own share of the stream
    assert len(ranks) == 2 and ranks[0]["num_shards"] == 2 and ranks[0] != ranks[1]


def test_a_torn_log_line_is_dropped_and_later_steps_are_trained_again(tmp_path):
    from hogsa_loader.train.finetune import _truncated_log

    log = tmp_path / "log.rank0.jsonl"
    log.write_text('{"step": 1}\n{"step": 2}\n{"step": 3}\n{"st')
    _truncated_log(log, 2)
    assert log.read_text() == '{"step": 1}\n{"step": 2}\n'


def test_held_out_split_and_a_split_without_a_batch_are_refused(tiny_world, tmp_path):
    from hogsa_loader.errors import UsageError
    from hogsa_loader.train.finetune import FinetuneConfig, finetune

    base = FinetuneConfig(data=str(tiny_world), out=str(tmp_path / "o"), backbone="resnet18", img_res=64)
    with pytest.raises(UsageError, match=r"s05 \(val\) held out"):
        finetune(replace(base, split="p1_val"), log=None)
    assert not (tmp_path / "o").exists()
    with pytest.raises(UsageError, match="--batch-size 100000"):
        finetune(replace(base, batch_size=100000, max_val=0), log=None)
