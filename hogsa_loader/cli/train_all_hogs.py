"""Train a HOGS model for every (subject, object) of a split, skipping finished ones.

``python -m hogsa_loader.cli.train_all_hogs --data ROOT --out RUNS_DIR [--gpus 0,1] -- [hogsa
train hogs flags]``. Each pair is trained as ``hogsa train hogs`` into ``RUNS_DIR/<subject>_<object>``;
a finished pair (three part checkpoints and ``metrics.json``) is skipped, one with only
intermediate checkpoints resumed. Pairs are spread over processes: ``--array-index I
--array-size N`` (or SLURM arrays, srun's ``SLURM_PROCID``, torchrun's ``RANK``/``WORLD_SIZE``)
takes pairs ``I, I+N, ...``, ``--device cuda`` becoming ``cuda:LOCAL_RANK``; ``--gpus``
starts one child per listed GPU. Arguments after ``--`` go to ``hogsa train hogs`` unchanged
(``--data``, ``--dataset``, ``--subject``, ``--object``, ``--out``,
``--sequences`` and ``--resume`` are set here). ``RUNS_DIR/summary.json`` lists every
finished run's held-out PSNR/SSIM.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any, Optional, Sequence

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.assets.h2o import H2O_EGO_CAMERA, H2O_OBJECT_NAMES, H2ORoot
from hogsa_loader.assets.protocol import held_out_subjects, training_subjects
from hogsa_loader.cli import checks
from hogsa_loader.errors import UsageError
from hogsa_loader.io.atomic import atomic_write
from hogsa_loader.models.gaussians.hogs_model import HogsModel
from hogsa_loader.system import process_slot
from hogsa_loader.system import rank_device as device_of_rank


def build_parser() -> argparse.ArgumentParser:
    """The flags of this command (those after ``--`` go to ``hogsa train hogs``)."""
    p = argparse.ArgumentParser(prog="python -m hogsa_loader.cli.train_all_hogs", description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True, help="ARCTIC(-format) data root, or an H2O root with --dataset h2o")
    p.add_argument(
        "--dataset",
        default="arctic",
        choices=["arctic", "h2o"],
        help="h2o: pairs are (subject, object class) of every sequence; pass --mano-dir and "
        "--object-mesh-dir to hogsa train hogs after --",
    )
    p.add_argument("--out", required=True, help="folder of the runs (one sub-folder per subject_object)")
    p.add_argument("--protocol", default="p1")
    p.add_argument(
        "--split",
        default="train",
        choices=["train", "val", "test", "all"],
        help="subjects/sequences of this split of the protocol (default: train; H2O: train = every subject but "
        "the held-out subject4). A split with held-out subjects needs --allow-held-out naming them",
    )
    p.add_argument(
        "--allow-held-out",
        default="",
        help="comma-separated subjects the protocol holds out (ARCTIC: s03, s05; H2O: subject4) to train on anyway",
    )
    p.add_argument("--subjects", default=None, help="comma-separated subject filter")
    p.add_argument("--objects", default=None, help="comma-separated object filter")
    p.add_argument(
        "--sequences-like",
        default=None,
        help="comma-separated sequence suffixes to train on, e.g. grab_01,use_01 (the paper's choice)",
    )
    p.add_argument(
        "--array-index",
        type=checks.non_negative_int,
        default=None,
        help="this process's slot (default: $SLURM_ARRAY_TASK_ID or $RANK or 0)",
    )
    p.add_argument("--array-size", type=checks.positive_int, default=None, help="processes in the job array")
    p.add_argument("--gpus", default=None, type=_gpu_ids, help="comma-separated GPU ids: one child process per GPU")
    p.add_argument("--dry-run", action="store_true", help="list this process's pairs and exit")
    checks.one_line_errors(p)
    return p


def parse_args(argv: Optional[Sequence[str]] = None) -> tuple[argparse.Namespace, list[str]]:
    """This command's arguments and those after ``--`` (for ``hogsa train hogs``)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    rest: list[str] = []
    if "--" in argv:
        i = argv.index("--")
        argv, rest = argv[:i], argv[i + 1 :]
    p = build_parser()
    a = p.parse_args(argv)
    if a.array_index is not None and a.array_index >= (a.array_size or 1):
        size = a.array_size or 1
        p.error(f"--array-index {a.array_index} is outside 0..{size - 1} (--array-size {size})")
    return a, rest


def _usage(message: str) -> None:
    """Report a usage error as one line and exit with status 2."""
    raise SystemExit(checks.report("train_all_hogs", UsageError(message)))


def _gpu_ids(text: str) -> str:
    """``--gpus``: comma-separated ``CUDA_VISIBLE_DEVICES`` entries (indices, ``GPU-``/``MIG-``
    UUIDs), no repeats."""
    ids = [g.strip() for g in text.split(",") if g.strip()]
    if not ids or not all(re.fullmatch(r"[0-9]+|(GPU|MIG)-[0-9A-Za-z/-]+", g) for g in ids):
        raise argparse.ArgumentTypeError(f"expected comma-separated GPU ids such as 0,1, got {text!r}")
    if len(set(ids)) != len(ids):
        raise argparse.ArgumentTypeError(f"GPU ids repeat in {text!r}")
    return ",".join(ids)


def list_pairs(root: ArcticRoot, a: argparse.Namespace) -> list[tuple[str, str, list[str]]]:
    """Sorted ``(subject, object, sequences)`` of the selection."""
    if a.split == "all":
        seqs = root.sequences()
    elif root.protocol_path(a.protocol).is_file():
        seqs = root.protocol(a.protocol)[a.split]
    elif a.split == "train":  # no protocol file: every subject the dataset's protocol does not hold out
        held = held_out_subjects(root)
        seqs = [s for s in root.sequences() if s.split("/", 1)[0] not in held]
    else:
        _usage(f"--split {a.split}: {root.protocol_path(a.protocol)} is missing")
    subjects = set(a.subjects.split(",")) if a.subjects else None
    objects = set(a.objects.split(",")) if a.objects else None
    suffixes = [s for s in a.sequences_like.split(",") if s] if a.sequences_like else None
    pairs: dict[tuple[str, str], list[str]] = {}
    for sid_seq in seqs:
        sid, seq = sid_seq.split("/", 1)
        obj, _, suffix = seq.partition("_")
        if (subjects and sid not in subjects) or (objects and obj not in objects):
            continue
        if suffixes and suffix not in suffixes:
            continue
        pairs.setdefault((sid, obj), []).append(seq)
    _check_held_out(root, sorted({sid for sid, _ in pairs}), a)
    return [(sid, obj, sorted(s)) for (sid, obj), s in sorted(pairs.items())]


def _check_held_out(root: Any, subjects: list[str], a: argparse.Namespace) -> None:
    """Refuse (one line, exit 2) a selection with a subject the protocol holds out, unless named
    in ``--allow-held-out`` (then warn)."""

    allow = [s for s in a.allow_held_out.split(",") if s]
    try:
        training_subjects(root, subjects, allow, "train_all_hogs")
    except UsageError as exc:
        _usage(str(exc))


def list_h2o_pairs(root: Any, a: argparse.Namespace) -> list[tuple[str, str, list[str]]]:
    """Sorted ``(subject, object, ["scene/seq", ...])`` of an H2O root: the object classes each
    sequence's ``obj_pose_rt`` labels show (H2O splits by subject: select with ``--subjects``)."""

    if a.split not in ("train", "all"):
        _usage("H2O splits by subject: --split train (every subject but the held-out ones) or all")
    subjects = set(a.subjects.split(",")) if a.subjects else None
    if subjects is None and a.split == "train":
        subjects = set(root.subjects()) - set(held_out_subjects(root))
    objects = set(a.objects.split(",")) if a.objects else None
    pairs: dict[tuple[str, str], list[str]] = {}
    for sid in root.subjects():
        if subjects and sid not in subjects:
            continue
        for _, scene, seq in root.sequences(sid):
            cls, _ = root.read_obj_poses(sid, scene, seq, H2O_EGO_CAMERA, root.frames(sid, scene, seq, H2O_EGO_CAMERA))
            for c in sorted(set(cls.tolist()) - {0}):
                obj = H2O_OBJECT_NAMES[c]
                if not objects or obj in objects:
                    pairs.setdefault((sid, obj), []).append(f"{scene}/{seq}")
    _check_held_out(root, sorted({sid for sid, _ in pairs}), a)
    return [(sid, obj, sorted(v)) for (sid, obj), v in sorted(pairs.items())]


def array_slot(a: argparse.Namespace) -> tuple[int, int]:
    """(index, size) of this process in the job array."""
    env = os.environ
    if a.array_index is not None or a.array_size is not None:
        idx, size = a.array_index or 0, a.array_size or 1
    elif "SLURM_ARRAY_TASK_ID" in env and "SLURM_ARRAY_TASK_COUNT" in env:
        idx, size = int(env["SLURM_ARRAY_TASK_ID"]), int(env["SLURM_ARRAY_TASK_COUNT"])
        idx -= int(env.get("SLURM_ARRAY_TASK_MIN", 0))
    else:  # torchrun's RANK / WORLD_SIZE, a task of srun -n N (not the batch script), else alone
        idx, size = process_slot(dict(env))
    if not 0 <= idx < size:
        _usage(f"array index {idx} is outside 0..{size - 1}")
    return idx, size


def rank_device(rest: Sequence[str], env: Optional[dict[str, str]] = None) -> list[str]:
    """``hogsa train hogs`` arguments with ``--device cuda`` made ``cuda:LOCAL_RANK`` when this
    process is one of several on a node (torchrun's ``LOCAL_RANK``, srun's ``SLURM_LOCALID``;
    :func:`hogsa_loader.system.rank_device`), so that each process trains on its own GPU;
    other arguments unchanged."""
    out = list(rest)
    for i, arg in enumerate(out[:-1]):
        if arg == "--device":
            out[i + 1] = device_of_rank(out[i + 1], env)
    return out


def is_finished(run: Path) -> bool:
    return HogsModel.is_run(run) and (run / "metrics.json").is_file()


def write_summary(out: Path) -> dict[str, Any]:
    rows = []
    for run in sorted(p for p in out.iterdir() if p.is_dir()):
        if is_finished(run):
            m = json.loads((run / "metrics.json").read_text())
            rows.append(
                {
                    "run": run.name,
                    "subject": m.get("subject"),
                    "object": m.get("object"),
                    "sequences": m.get("sequences"),
                    "iters": m.get("iters"),
                    "psnr": m.get("psnr"),
                    "ssim": m.get("ssim"),
                    "train_s": m.get("timings", {}).get("train_s"),
                }
            )
    summary = {"runs": rows, "num_finished": len(rows)}
    atomic_write(out / "summary.json", (json.dumps(summary, indent=1) + "\n").encode())
    return summary


def main(argv: Optional[Sequence[str]] = None) -> int:
    a, rest = parse_args(argv)
    out = Path(a.out)
    if a.gpus:
        gpus = [g for g in a.gpus.split(",") if g]
        base = ["--data", a.data, "--out", a.out, "--protocol", a.protocol, "--split", a.split, "--dataset", a.dataset]
        base += ["--allow-held-out", a.allow_held_out] if a.allow_held_out else []
        for flag, val in (("--subjects", a.subjects), ("--objects", a.objects), ("--sequences-like", a.sequences_like)):
            if val:
                base += [flag, val]
        procs = []
        for k, gpu in enumerate(gpus):
            cmd = [
                sys.executable,
                "-m",
                "hogsa_loader.cli.train_all_hogs",
                *base,
                "--array-index",
                str(k),
                "--array-size",
                str(len(gpus)),
                *(["--dry-run"] if a.dry_run else []),
                "--",
                *rest,
            ]
            procs.append(subprocess.Popen(cmd, env={**os.environ, "CUDA_VISIBLE_DEVICES": gpu}))
        codes = [p.wait() for p in procs]
        out.mkdir(parents=True, exist_ok=True)
        write_summary(out)
        return max(codes)
    if a.dataset == "h2o":
        pairs = list_h2o_pairs(H2ORoot(a.data), a)
    else:
        pairs = list_pairs(ArcticRoot(a.data), a)
    if not pairs:
        print("train_all_hogs: no (subject, object) pair matches the selection", file=sys.stderr)
        return 2
    idx, size = array_slot(a)
    mine = pairs[idx::size]
    print(f"train_all_hogs: {len(pairs)} pairs, process {idx}/{size} takes {len(mine)}")
    from hogsa_loader.cli.train import train_hogs_main  # deferred: the trainer's modules, only when pairs are trained

    train_one = train_hogs_main

    failed = []
    for sid, obj, seqs in mine:
        run = out / f"{sid}_{obj}"
        if is_finished(run):
            print(f"  {run.name}: finished, skipped")
            continue
        resume = (run / "checkpoints" / "latest.json").is_file()
        print(f"  {run.name}: {'resuming' if resume else 'training'} on {seqs}")
        if a.dry_run:
            continue
        args = [
            "--data",
            a.data,
            "--dataset",
            a.dataset,
            "--subject",
            sid,
            "--object",
            obj,
            "--out",
            str(run),
            "--sequences",
            ",".join(seqs),
        ]
        code = train_one(args + (["--resume"] if resume else []) + rank_device(rest))
        if code:
            failed.append(run.name)
    out.mkdir(parents=True, exist_ok=True)
    summary = write_summary(out)
    print(
        f"train_all_hogs: {summary['num_finished']} finished runs in {out}" + (f"; failed: {failed}" if failed else "")
    )
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
