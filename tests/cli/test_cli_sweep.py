"""Every ``hogsa`` subcommand and pretrain script refuses bad values before any work: a
non-zero exit, one ``error:`` line on stderr, no traceback, no new files."""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import pytest
from conftest import job

from hogsa_loader.cli.main import main as hogsa

ROOT = Path(__file__).resolve().parents[2]
HOGSA_COMMANDS = ("assets", "world", "world-noise", "export", "demo", "view", "h2o-export", "plates")

#: (command, base arguments with {W} = tiny world, {B} = bundle, flag, bad values)
TABLE: list[tuple[str, list[str], str, tuple[str, ...]]] = [
    ("assets", ["--out", "o"], "--seed", ("nan", "abc", "-1")),
    ("world", ["--out", "o", "--preset", "tiny"], "--seed", ("nan", "-1")),
    ("world", ["--out", "o"], "--preset", ("huge",)),
    ("world-noise", ["--src", "{W}", "--out", "o"], "--trans-mm", ("nan", "inf", "-1")),
    ("world-noise", ["--src", "{W}", "--out", "o"], "--rot-deg", ("nan", "inf")),
    ("world-noise", ["--src", "{W}", "--out", "o"], "--pose-rad", ("nan", "inf")),
    ("world-noise", ["--src", "{W}", "--out", "o"], "--smooth", ("0", "nan")),
    (
        "export",
        ["--bundle", "{B}", "--data", "{W}", "--out", "o", "--num", "8", "--shard-size", "8"],
        "--num",
        ("0", "-1", "nan"),
    ),
    ("export", ["--bundle", "{B}", "--data", "{W}", "--out", "o", "--num", "8"], "--shard-size", ("0", "12")),
    ("export", ["--bundle", "{B}", "--data", "{W}", "--out", "o", "--num", "8"], "--render-size", ("0", "nan")),
    ("export", ["--bundle", "{B}", "--data", "{W}", "--out", "o", "--num", "8"], "--device", ("potato",)),
    ("export", ["--bundle", "{B}", "--data", "{W}", "--out", "o", "--num", "8"], "--world-size", ("0",)),
    ("demo", ["--out", "o"], "--samples", ("0", "nan")),
    ("demo", ["--out", "o"], "--workers", ("-1",)),
    (
        "view",
        ["--bundle", "{B}", "--data", "{W}", "--subject", "s01", "--object", "box", "--out", "o"],
        "--orbit",
        ("-2", "nan"),
    ),
    (
        "view",
        ["--bundle", "{B}", "--data", "{W}", "--subject", "s01", "--object", "box", "--out", "o"],
        "--distance",
        ("0", "nan"),
    ),
    (
        "view",
        ["--bundle", "{B}", "--data", "{W}", "--subject", "s01", "--object", "box", "--out", "o"],
        "--size",
        ("0",),
    ),
    (
        "h2o-export",
        ["--world", "{W}", "--out", "o", "--subject", "s01", "--sequence", "box_grab_01"],
        "--image-size",
        ("0", "nan"),
    ),
    ("plates", ["--data", "{W}", "--out", "o"], "--width", ("0", "nan")),
    ("plates", ["--data", "{W}", "--out", "o"], "--min-coverage", ("nan", "2")),
    ("plates", ["--data", "{W}", "--out", "o"], "--views", ("0", "9")),
    ("train_all_hogs", ["--data", "{W}", "--out", "o", "--dry-run"], "--array-index", ("-1", "nan", "3")),
    ("train_all_hogs", ["--data", "{W}", "--out", "o", "--dry-run"], "--array-size", ("0",)),
    ("train_all_hogs", ["--data", "{W}", "--out", "o", "--dry-run"], "--gpus", ("-1", "nan", "0,0", "²")),
    ("train_contactnet", ["--data", "{W}", "--out", "o"], "--optim-iters", ("-1", "nan")),
    ("train_contactnet", ["--data", "{W}", "--out", "o"], "--optim-lr", ("nan", "0")),
    ("build_pose_bank", ["--data", "{W}", "--contactnet", "{B}/contactnet", "--out", "o"], "--per-sequence", ("0",)),
    ("build_pose_bank", ["--data", "{W}", "--contactnet", "{B}/contactnet", "--out", "o"], "--device", ("potato",)),
    (
        "train_hogs",
        ["--data", "{W}", "--subject", "s01", "--object", "box", "--out", "o"],
        "--optim-lr-scale",
        ("nan", "0"),
    ),
    (
        "train_hogs",
        ["--data", "{W}", "--subject", "s01", "--object", "box", "--out", "o"],
        "--loss-lambda-ssim",
        ("nan", "inf"),
    ),
    ("train_hogs", ["--data", "{W}", "--subject", "s01", "--object", "box", "--out", "o"], "--views", ("0", "9")),
    ("train_srm", ["--data", "{W}", "--hogs", "{B}/hogs", "--out", "o"], "--optim-ema-decay", ("nan", "2")),
    ("train_srm", ["--data", "{W}", "--hogs", "{B}/hogs", "--out", "o"], "--batch-size", ("0",)),
]
CASES = [(cmd, base, flag, v) for cmd, base, flag, vals in TABLE for v in vals]


_JOBS = {"train_hogs": "hogs", "train_srm": "srm", "train_contactnet": "contactnet", "build_pose_bank": "bank"}


def _script_main(name: str):
    return job(_JOBS.get(name, name)).main


@pytest.mark.parametrize("cmd,base,flag,value", CASES, ids=[f"{c}{f}={v}" for c, _, f, v in CASES])
def test_bad_value_is_refused_before_work(
    cmd, base, flag, value, tiny_world, untrained_bundle, tmp_path, monkeypatch
) -> None:
    monkeypatch.chdir(tmp_path)
    argv = [a.replace("{W}", str(tiny_world)).replace("{B}", str(untrained_bundle)) for a in base] + [flag, value]
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            rc = hogsa([cmd, *argv]) if cmd in HOGSA_COMMANDS else _script_main(cmd)(argv)
        except SystemExit as exc:
            rc = exc.code
    lines = [line for line in err.getvalue().splitlines() if line.strip()]
    assert isinstance(rc, int) and rc != 0, (rc, err.getvalue())
    assert len(lines) == 1 and "error:" in lines[0] and "Traceback" not in err.getvalue(), err.getvalue()
    assert flag in lines[0] or flag.lstrip("-") in lines[0], lines[0]  # refused for this value, not another
    assert not any(tmp_path.iterdir()), sorted(p.name for p in tmp_path.iterdir())


@pytest.mark.parametrize("lo_hi", [("0.5", "0.1"), ("-0.1", "0.2"), ("nan", "0.2"), ("0", "inf")])
def test_pose_bank_articulation_range_is_checked(lo_hi, tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    err = io.StringIO()
    with contextlib.redirect_stderr(err), pytest.raises(SystemExit) as exc:
        _script_main("build_pose_bank")(["--data", "w", "--contactnet", "c", "--out", "o", "--pom-arti-range", *lo_hi])
    assert exc.value.code != 0 and "--pom-arti-range" in err.getvalue() and "Traceback" not in err.getvalue()
    assert not any(tmp_path.iterdir())


def test_gpu_list_accepts_what_cuda_visible_devices_accepts() -> None:
    mod = job("train_all_hogs")
    assert mod._gpu_ids("0, 1,3") == "0,1,3"
    assert mod._gpu_ids("GPU-8f6e2c1a-1b2c,MIG-4d3c/1/0") == "GPU-8f6e2c1a-1b2c,MIG-4d3c/1/0"
