"""Training jobs from the command line: HOGS, SRM, ContactNet and the pose bank.

Each job's flags are derived from its config dataclass (``--group-field``;
:mod:`hogsa_loader.cli.dataclass_args`), every argument is checked before any data is
read, and errors are reported as one ``PROG: error: ...`` line (exit status 2 for a usage
error, 1 otherwise). ``hogsa train hogs|srm|contactnet|bank`` runs the ``*_main`` functions
(:mod:`hogsa_loader.cli.train_commands`).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import torch

from hogsa_loader.assets.arctic import ALLO_VIEWS
from hogsa_loader.assets.h2o_meshes import find_h2o_mesh
from hogsa_loader.cli import checks
from hogsa_loader.cli.dataclass_args import add_dataclass_arguments, apply_field_checks, dataclass_from_args
from hogsa_loader.errors import AssetError, HogsaError, UsageError
from hogsa_loader.train import HogsConfig, HogsTrainer
from hogsa_loader.train.pom_config import ContactNetJobConfig, PoseBankConfig
from hogsa_loader.train.pom_jobs import build_pose_bank, fit_contactnet
from hogsa_loader.train.run_folder import check_run_folder, latest_checkpoint, read_trainer_state
from hogsa_loader.train.srm_trainer import SRMTrainConfig, SRMTrainer

__all__ = [
    "JOBS",
    "build_pose_bank_main",
    "hogs_parser",
    "parse_bank_args",
    "parse_contactnet_args",
    "parse_hogs_args",
    "parse_srm_args",
    "run_hogs",
    "run_srm",
    "srm_parser",
    "train_contactnet_main",
    "train_hogs_main",
    "train_srm_main",
]

_RUN_FLAGS = (
    ("--resume", "continue from the run folder's latest checkpoint"),
    ("--overwrite", "start again from step 0 in a run folder that holds checkpoints (they are deleted)"),
    ("--quiet", "no progress bar or summary"),
)


def _config_parser(p: argparse.ArgumentParser, cls: type) -> argparse.ArgumentParser:
    """``p`` with the flags of config ``cls`` and the run flags ``--resume/--overwrite/--quiet``."""
    add_dataclass_arguments(p, cls)
    apply_field_checks(p, cls)
    for flag, text in _RUN_FLAGS:
        p.add_argument(flag, action="store_true", help=text)
    checks.one_line_errors(p)
    return p


# --------------------------------------------------------------------------------------
# HOGS
# --------------------------------------------------------------------------------------


def hogs_parser(p: Optional[argparse.ArgumentParser] = None) -> argparse.ArgumentParser:
    """The flags of one HOGS run (:class:`~hogsa_loader.train.HogsConfig` + run flags)."""
    return _config_parser(
        p or argparse.ArgumentParser(prog="hogsa train hogs", description=HOGS_DESCRIPTION), HogsConfig
    )


HOGS_DESCRIPTION = "Train one HOGS model (right hand, left hand, object Gaussians) per subject + object."


def check_hogs_args(cfg: HogsConfig, resume: bool, overwrite: bool) -> None:
    """Every check that needs no data read: paths, views, the run folder and, with ``resume``,
    the run's saved settings and its latest trainer state.

    Raises:
        UsageError / RunExistsError: a bad path, view or run folder.
        AssetError: a malformed or corrupt checkpoint.
        ValueError: settings that differ from the run's saved ones.
    """
    d = cfg.data
    checks.input_dir(d.root, "--data")
    for flag, path in (("--mano-dir", d.mano_dir), ("--object-mesh-dir", d.object_mesh_dir)):
        if path is not None:
            checks.input_dir(path, flag)
    if d.dataset == "h2o" and d.object_mesh_dir is not None:
        try:
            find_h2o_mesh(d.object_mesh_dir, d.object)
        except AssetError as exc:
            raise UsageError(f"--object-mesh-dir {exc}") from exc
    for flag, views in (("--views", d.views), ("--eval-views", d.eval_views)):
        bad = [v for v in views or () if v not in ALLO_VIEWS]
        if d.dataset == "arctic" and bad:
            raise UsageError(f"{flag} must be allocentric ARCTIC views {tuple(ALLO_VIEWS)}, got {bad}")
    checks.output_dir(cfg.run.out, "--out")
    check_run_folder(cfg.run.out, resume=resume, overwrite=overwrite)
    if resume:
        # views and eval views left to the data (None) are compared when the trainer resumes
        given = {k: v for k, v in cfg.to_json().items() if not (k in ("views", "eval_views") and v is None)}
        folder = latest_checkpoint(Path(cfg.run.out), given, HogsConfig.RESUMABLE, HogsConfig.defaults())
        if folder is not None:
            read_trainer_state(folder)


def _guarded(prog: str, build: Callable[[], object]) -> tuple[object, Optional[int]]:
    """``(build(), None)``, or ``(None, exit status)`` with the error reported: files and data
    give status 1, a usage error or a setting the job refused (ValueError) status 2."""
    try:
        return build(), None
    except (HogsaError, OSError) as exc:
        return None, checks.report(prog, exc)
    except ValueError as exc:
        return None, checks.report(prog, UsageError(str(exc)))


def _build_and_train(prog: str, build: Callable[[], Any], overwrite: bool) -> tuple[Optional[dict], int]:
    """``(trainer.train() metrics, 0)`` for the trainer ``build()`` returns, or ``(None, exit
    status)`` with the error reported: building fails as :func:`_guarded`; during training
    files and data give status 1 (they are not usage errors)."""
    trainer, rc = _guarded(prog, build)
    if rc is not None:
        return None, rc
    try:
        return trainer.train(overwrite=overwrite), 0  # type: ignore[attr-defined]
    except (HogsaError, OSError) as exc:
        return None, checks.report(prog, exc)


def run_hogs(cfg: HogsConfig, *, resume: bool = False, overwrite: bool = False, quiet: bool = False) -> int:
    """Check, build (and resume) the trainer, train; the exit status."""

    def build() -> HogsTrainer:
        check_hogs_args(cfg, resume, overwrite)
        trainer = HogsTrainer(cfg, progress=not quiet)
        if resume and trainer.resume() and not quiet:
            print(f"resumed {cfg.run.out} at step {trainer.step}")
        return trainer

    m, rc = _build_and_train("hogsa train hogs", build, overwrite)
    if m is None:
        return rc
    if not quiet:
        print(json.dumps({k: m[k] for k in ("psnr", "ssim", "iters")} | {"s_per_iter": m["timings"]["s_per_iter"]}))
    return 0


def train_hogs_main(argv: Optional[Sequence[str]] = None) -> int:
    """``train_hogs`` / ``hogsa train hogs``: parse, then :func:`run_hogs`."""
    a = hogs_parser().parse_args(argv)
    return run_hogs(dataclass_from_args(HogsConfig, a), resume=a.resume, overwrite=a.overwrite, quiet=a.quiet)


def parse_hogs_args(argv: Optional[Sequence[str]] = None) -> HogsConfig:
    """The :class:`~hogsa_loader.train.HogsConfig` of a ``train_hogs`` command line."""
    return dataclass_from_args(HogsConfig, hogs_parser().parse_args(argv))


# --------------------------------------------------------------------------------------
# SRM
# --------------------------------------------------------------------------------------

SRM_DESCRIPTION = "Train the SRM (StyleUNet refinement of HOGS renders) on every finished HOGS run of a folder."


def srm_parser(p: Optional[argparse.ArgumentParser] = None) -> argparse.ArgumentParser:
    """The flags of one SRM run (:class:`~hogsa_loader.train.srm_trainer.SRMTrainConfig`, run flags, ``--threads``)."""
    p = p or argparse.ArgumentParser(prog="hogsa train srm", description=SRM_DESCRIPTION)
    p.add_argument("--threads", type=checks.positive_int, default=None, help="torch CPU threads (default: torch's)")
    return _config_parser(p, SRMTrainConfig)


def check_srm_args(cfg: SRMTrainConfig, resume: bool, overwrite: bool) -> None:
    """Every check that needs no run read: input and output folders and the run folder.

    Raises:
        UsageError / RunExistsError: a bad path or run folder.
    """
    checks.input_dir(cfg.data.root, "--data")
    checks.input_dir(cfg.data.hogs, "--hogs")
    if cfg.data.cross_hogs:
        checks.input_dir(cfg.data.cross_hogs, "--cross-hogs")
    if cfg.data.cache:
        checks.output_dir(cfg.data.cache, "--cache")
    checks.output_dir(cfg.run.out, "--out")
    check_run_folder(cfg.run.out, resume=resume, overwrite=overwrite)


def _print_srm_summary(m: dict) -> None:
    """The selected checkpoint (stderr), the held-out scores and one line per run and view (stdout)."""
    if m["selection"]:
        b = m["selection"]["best"]
        print(
            f"hogsa train srm: selected step {b['step']} (validation views {m['selection']['val_views']}: "
            f"{b['psnr_without_srm']:.2f} -> {b['psnr']:.2f} dB on {b['n']} pairs)",
            file=sys.stderr,
        )
    print(json.dumps({k: m[k] for k in ("without_srm", "with_srm", "delta_psnr", "delta_ssim")}, indent=1))
    for row in m["per_view"]:
        before, after = row["without_srm"], row["with_srm"]
        print(
            f"{row['run']:>24s} view {row['view']}: n={row['n']} "
            f"PSNR {before['psnr']:.2f} -> {after['psnr']:.2f} dB, SSIM {before['ssim']:.4f} -> {after['ssim']:.4f}"
        )


def run_srm(cfg: SRMTrainConfig, *, resume: bool = False, overwrite: bool = False, quiet: bool = False) -> int:
    """Check, build (and resume) the SRM trainer, train, print the summary; the exit status."""

    def build() -> SRMTrainer:
        check_srm_args(cfg, resume, overwrite)
        trainer = SRMTrainer(cfg, progress=not quiet)
        if resume:
            if trainer.resume():
                print(f"hogsa train srm: resumed {cfg.run.out} at step {trainer.step}", file=sys.stderr)
            else:
                print(f"hogsa train srm: nothing to resume in {cfg.run.out}; starting fresh", file=sys.stderr)
        return trainer

    m, rc = _build_and_train("hogsa train srm", build, overwrite)
    if m is None:
        return rc
    _print_srm_summary(m)
    return 0


def parse_srm_args(argv: Optional[Sequence[str]] = None) -> tuple[SRMTrainConfig, argparse.Namespace]:
    """The :class:`~hogsa_loader.train.srm_trainer.SRMTrainConfig` of a ``train_srm`` command line and
    the parsed namespace (``resume``, ``overwrite``, ``quiet``, ``threads``)."""
    a = srm_parser().parse_args(argv)
    return dataclass_from_args(SRMTrainConfig, a), a


def train_srm_main(argv: Optional[Sequence[str]] = None) -> int:
    """``train_srm`` / ``hogsa train srm``: parse, set the thread count, then :func:`run_srm`."""
    cfg, a = parse_srm_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)
    return run_srm(cfg, resume=a.resume, overwrite=a.overwrite, quiet=a.quiet)


# --------------------------------------------------------------------------------------
# ContactNet and pose bank
# --------------------------------------------------------------------------------------

CONTACTNET_DESCRIPTION = "Train POM's ContactNet on the annotated frames of an ARCTIC-format or H2O dataset."
BANK_DESCRIPTION = "Build a POM pose bank: optimise perturbed contact frames of every sequence and keep the grasps."


def _job_parser(prog: str, description: str, cls: type) -> argparse.ArgumentParser:
    """The flags of config ``cls`` plus ``--threads`` and ``--quiet``."""
    p = argparse.ArgumentParser(prog=prog, description=description)
    add_dataclass_arguments(p, cls)
    apply_field_checks(p, cls)
    p.add_argument("--threads", type=checks.positive_int, default=None, help="torch CPU threads (default: torch's)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    checks.one_line_errors(p)
    return p


def _run_job(prog: str, a: argparse.Namespace, job: Callable[[], dict]) -> int:
    """Run ``job`` (its checks first), print its JSON summary unless quiet; the exit status."""
    if a.threads:
        torch.set_num_threads(a.threads)
    result, rc = _guarded(prog, job)
    if rc is not None:
        return rc
    if not a.quiet:
        print(json.dumps(result, indent=2))
    return 0


def parse_contactnet_args(argv: Optional[Sequence[str]] = None) -> tuple[ContactNetJobConfig, argparse.Namespace]:
    """The :class:`~hogsa_loader.train.pom_config.ContactNetJobConfig` of a command line and the namespace."""
    a = _job_parser("hogsa train contactnet", CONTACTNET_DESCRIPTION, ContactNetJobConfig).parse_args(argv)
    return dataclass_from_args(ContactNetJobConfig, a), a


def train_contactnet_main(argv: Optional[Sequence[str]] = None) -> int:
    """``train_contactnet`` / ``hogsa train contactnet``: parse, check the folders, fit."""
    cfg, a = parse_contactnet_args(argv)

    def job() -> dict:
        checks.input_dir(cfg.data.root, "--data")
        checks.output_dir(cfg.run.out, "--out")
        return fit_contactnet(cfg, progress=not a.quiet)

    return _run_job("hogsa train contactnet", a, job)


def parse_bank_args(argv: Optional[Sequence[str]] = None) -> tuple[PoseBankConfig, argparse.Namespace]:
    """The :class:`~hogsa_loader.train.pom_config.PoseBankConfig` of a command line and the namespace
    (exit status 2 for an articulation range that is not finite ``0 <= LO <= HI``)."""
    p = _job_parser("hogsa train bank", BANK_DESCRIPTION, PoseBankConfig)
    a = p.parse_args(argv)
    cfg = dataclass_from_args(PoseBankConfig, a)
    lo_hi = cfg.pom.arti_range
    if lo_hi is not None and not 0.0 <= lo_hi[0] <= lo_hi[1] < math.inf:
        p.error(f"argument --pom-arti-range: need finite 0 <= LO <= HI, got {lo_hi[0]} {lo_hi[1]}")
    return cfg, a


def build_pose_bank_main(argv: Optional[Sequence[str]] = None) -> int:
    """``build_pose_bank`` / ``hogsa train bank``: parse, check the folders, build."""
    cfg, a = parse_bank_args(argv)

    def job() -> dict:
        checks.input_dir(cfg.data.root, "--data")
        checks.input_dir(cfg.data.contactnet, "--contactnet")
        checks.output_dir(cfg.run.out, "--out")
        return build_pose_bank(cfg, progress=not a.quiet)

    return _run_job("hogsa train bank", a, job)


#: entry point of each ``hogsa train`` job
JOBS: dict[str, Callable[[Optional[Sequence[str]]], int]] = {
    "hogs": train_hogs_main,
    "srm": train_srm_main,
    "contactnet": train_contactnet_main,
    "bank": build_pose_bank_main,
}
