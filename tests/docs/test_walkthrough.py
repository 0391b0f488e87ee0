"""``docs/real-arctic.md``, executed: every console command and the Python block, in order, on
the generated test world treated as a user's ARCTIC root (``data`` in a fresh folder), with the
settings file shrunk to toy sizes (the one edit step 2 invites). torchrun's two processes and
srun's two tasks build side by side into one folder of their own: the four processes of two
launchers take each stage once between them and write the stages a single process writes; srun
is played by two processes with the variables srun sets; ``--gpus`` starts its two processes on
that build."""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

from conftest import tiny_build_config

from hogsa_loader.train.build import config_toml, read_config

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "real-arctic.md"


def _blocks(kind: str) -> list[str]:
    return re.findall(rf"```{kind}\n(.*?)```", DOC.read_text(), flags=re.S)


def _commands() -> list[str]:
    return [line[2:].strip() for block in _blocks("console") for line in block.splitlines() if line.startswith("$ ")]


def _records(out: Path) -> dict[str, str]:
    return {p.stem: json.loads(p.read_text())["key"] for p in (out / "stages").glob("*.json")}


def _run(argv: list[str], cwd: Path, env: dict[str, str], **kw) -> subprocess.CompletedProcess:
    proc = subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=900, **kw)
    assert proc.returncode == 0, (argv, proc.stdout[-2000:], proc.stderr[-3000:])
    return proc


def test_the_walkthrough_runs_as_written(tiny_world, tmp_path):
    commands = _commands()
    first_words = ["hogsa", "hogsa", "hogsa", "torchrun", "srun", "hogsa", "hogsa", "torchrun", "torchrun", "hogsa"]
    assert [c.split()[0] for c in commands] == first_words
    assert "examples/lightning_arcticnet.py" in commands[8]  # run by tests/sample/test_lightning.py
    (tmp_path / "data").symlink_to(tiny_world, target_is_directory=True)
    env = {k: v for k, v in os.environ.items() if k not in ("RANK", "WORLD_SIZE", "LOCAL_RANK")}
    env = {k: v for k, v in env.items() if not k.startswith("SLURM_")}
    seconds = {}

    def timed(step: str, fn):
        t0 = time.perf_counter()
        out = fn()
        seconds[step] = time.perf_counter() - t0
        return out

    hogsa = [sys.executable, "-m", "hogsa_loader.cli.main"]
    # 2. settings: print them, then shrink them (the user's edit)
    words = shlex.split(commands[0])
    assert words[-2] == ">" and words[-1] == "build.toml"
    printed = timed("print-config", lambda: _run(hogsa + words[1:-2], tmp_path, env))
    (tmp_path / "build.toml").write_text(printed.stdout)
    written = read_config(tmp_path / "build.toml")
    assert (written.data.root, written.run.out) == ("data", "build")
    tiny = tiny_build_config(Path("data"), Path("build"), pairs=None)
    (tmp_path / "build.toml").write_text(config_toml(tiny))
    # 3. status, 4. one process
    status = timed("status", lambda: _run(hogsa + shlex.split(commands[1])[1:], tmp_path, env))
    assert "0 of 5 stages done" in status.stdout
    timed("build", lambda: _run(hogsa + shlex.split(commands[2])[1:], tmp_path, env))
    single = _records(tmp_path / "build")
    assert len(single) == 5 and (tmp_path / "build" / "bundle" / "manifest.json").is_file()
    again = _run(hogsa + shlex.split(commands[1])[1:], tmp_path, env)
    assert "5 of 5 stages done" in again.stdout
    # 5. several processes: torchrun's two and srun's two tasks (with srun's variables), side by
    # side in one folder of their own
    torchrun = shlex.split(commands[3])
    argv = [sys.executable, "-m", "torch.distributed.run", *torchrun[1:], "--out", "build_shared"]
    srun = shlex.split(commands[4])
    assert srun[1:3] == ["--ntasks", "2"] and srun[3] == "python"
    task = [sys.executable, *srun[4:], "--out", "build_shared"]

    def both():  # side by side: torchrun and srun's two tasks
        def start(cmd, extra_env):
            pipe = subprocess.PIPE
            return subprocess.Popen(cmd, cwd=tmp_path, env={**env, **extra_env}, stdout=pipe, stderr=pipe, text=True)

        slurm = [{"SLURM_PROCID": str(i), "SLURM_STEP_NUM_TASKS": "2", "SLURM_NTASKS": "2"} for i in range(2)]
        procs = [start(argv, {})] + [start(task, v) for v in slurm]
        return [(*p.communicate(timeout=900), p.returncode) for p in procs]

    results = timed("torchrun + srun", both)
    assert [r[2] for r in results] == [0, 0, 0], [r[1][-2000:] for r in results]
    assert "process 0 of 2" in results[0][0] and "process 1 of 2" in results[0][0]
    ranks = [re.findall(r"process ([01]) of 2", out) for out, _, _ in results[1:]]
    assert sorted(r for found in ranks for r in set(found)) == ["0", "1"], ranks  # srun's two tasks
    assert _records(tmp_path / "build_shared") == single
    built = [line for r in results for line in r[0].splitlines() if "] done in" in line]
    assert len(built) == 5  # each stage once, across the four processes
    # --gpus: two processes of this machine with torchrun's variables (the sharing above), here
    # on the shared build, which they find complete
    gpus = shlex.split(commands[5])
    assert gpus[-2:] == ["--gpus", "0,1"]
    launched = timed("--gpus", lambda: _run(hogsa + gpus[1:] + ["--out", "build_shared"], tmp_path, env))
    assert "process 0 of 2" in launched.stdout and "process 1 of 2" in launched.stdout
    assert _records(tmp_path / "build_shared") == single
    # 6. the Python block
    (code,) = _blocks("python")
    script = tmp_path / "train.py"
    check = "\nassert len(inputs['img']) == 8\n"
    check += "print('synthetic', sum('hogsa_synth' in n for n in meta_info['imgname']))\n"
    script.write_text(code + check)
    out = timed("python", lambda: _run([sys.executable, str(script)], tmp_path, env))
    assert "synthetic 4" in out.stdout
    # 7. fine-tuning, one process and two (toy sizes, on the CPU)
    toy = ["--backbone", "resnet18", "--img-res", "64", "--batch-size", "4", "--steps", "2", "--max-val", "4"]
    one = [a if a != "cuda" else "cpu" for a in shlex.split(commands[6])]
    timed("finetune", lambda: _run(hogsa + one[1:] + toy, tmp_path, env))
    ddp = [a if a != "cuda" else "cpu" for a in shlex.split(commands[7])]
    timed(
        "finetune torchrun",
        lambda: _run([sys.executable, "-m", "torch.distributed.run", *ddp[1:], *toy], tmp_path, env),
    )
    for run in ("finetune", "finetune_ddp"):
        result = json.loads((tmp_path / run / "result.json").read_text())
        assert (
            result["steps"] == 2
            and result["metrics"]["frames"] == 4
            and (tmp_path / run / "model.safetensors").is_file()
        )
    assert (tmp_path / "finetune_ddp" / "log.rank1.jsonl").is_file()
    # 8. depth maps, part masks and intrinsics of the real frames
    timed("frame-maps", lambda: _run(hogsa + shlex.split(commands[9])[1:], tmp_path, env))
    maps = json.loads((tmp_path / "maps" / "maps.json").read_text())
    assert maps["views"] == ["s01/box_use_01/1", "s01/box_use_01/2"] and (tmp_path / "maps" / "preview.png").is_file()
    total = sum(seconds.values())
    steps = ", ".join(f"{k} {v:.0f} s" for k, v in seconds.items())
    print(f"walkthrough on the tiny world: {total:.0f} s ({steps})")
