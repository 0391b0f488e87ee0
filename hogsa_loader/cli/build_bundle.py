"""Assemble a hogsa-loader bundle from trained HOGS runs (and optional SRM / ContactNet / pose banks).

Example::

    python -m hogsa_loader.cli.build_bundle --data ./hogsa_world --hogs runs/ --out bundle/ \
        [--srm runs/srm] [--contactnet runs/contactnet] [--pose-bank runs/pose_bank]

``--hogs`` is either one run folder (``hand_right/``, ``hand_left/``, ``object/``) or a
folder whose sub-folders (searched two levels deep) are runs; each run's (subject, object)
is read from its object checkpoint. The result is validated with
:func:`hogsa_loader.models.bundle.load_bundle` before the command returns.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Optional, Sequence

from hogsa_loader.assets.roots import DATASETS, open_dataset_root
from hogsa_loader.cli import checks
from hogsa_loader.errors import HogsaError, UsageError
from hogsa_loader.models.bundle import MANIFEST_NAME, load_bundle, write_bundle
from hogsa_loader.models.gaussians.hogs_model import HogsModel


def find_runs(folder: Path, depth: int = 2) -> list[Path]:
    """Finished HOGS run folders at or below ``folder`` (at most ``depth`` levels down)."""
    if HogsModel.is_run(folder):
        return [folder]
    if depth <= 0 or not folder.is_dir():
        return []
    out: list[Path] = []
    for sub in sorted(p for p in folder.iterdir() if p.is_dir()):
        out.extend(find_runs(sub, depth - 1))
    return out


def build_parser() -> argparse.ArgumentParser:
    """The flags of this command."""
    p = argparse.ArgumentParser(prog="python -m hogsa_loader.cli.build_bundle", description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True, help="dataset root the runs were trained on (ARCTIC ./data, or H2O's)")
    p.add_argument("--hogs", required=True, help="a HOGS run folder, or a folder of run folders")
    p.add_argument("--out", required=True, help="bundle folder to write")
    p.add_argument("--srm", default=None, help="SRM checkpoint folder (a hogsa train srm run)")
    p.add_argument("--contactnet", default=None, help="ContactNet checkpoint folder")
    p.add_argument(
        "--pose-bank",
        type=lambda text: [t for t in text.split(",") if t],
        default=[],
        help="pose-bank folders (hogsa train bank), comma-separated, distinct folder names",
    )
    p.add_argument("--dataset", default="arctic", choices=DATASETS, help="dataset format of --data")
    p.add_argument("--mano-dir", default=None, help="H2O: folder with MANO_RIGHT.pkl / MANO_LEFT.pkl")
    p.add_argument("--object-mesh-dir", default=None, help="H2O: folder of the object meshes (<name>/<name>.obj|.ply)")
    p.add_argument("--overwrite", action="store_true", help="replace the bundle already in --out")
    checks.one_line_errors(p)
    return p


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Build the bundle; the exit status (0, 1 for a problem met, 2 for a usage error)."""
    args = build_parser().parse_args(argv)
    try:
        checks.input_dir(args.data, "--data")
        checks.input_dir(args.hogs, "--hogs")
        checks.output_dir(args.out, "--out")
        if (Path(args.out) / MANIFEST_NAME).is_file() and not args.overwrite:
            raise UsageError(f"--out {args.out}: already holds a bundle (pass --overwrite to replace it)")
        root = open_dataset_root(args.dataset, args.data, args.mano_dir, args.object_mesh_dir)
        runs = find_runs(Path(args.hogs))
        if not runs:
            raise UsageError(f"--hogs {args.hogs}: no finished HOGS run under it")
        out = write_bundle(args.out, root, runs, srm=args.srm, contactnet=args.contactnet, pose_banks=args.pose_bank)
        bundle = load_bundle(out, data_root=root)
    except (HogsaError, OSError) as exc:
        return checks.report("build_bundle", exc)
    print(
        f"bundle {out}: {len(bundle.hogs)} HOGS run(s) {bundle.keys}"
        f"{', SRM' if bundle.srm else ''}{', ContactNet' if bundle.contactnet else ''}"
        f"{f', {len(bundle.pose_banks)} pose bank(s)' if bundle.pose_banks else ''}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
