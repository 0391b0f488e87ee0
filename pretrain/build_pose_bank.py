#!/usr/bin/env python
"""Build a POM pose bank: perturb annotated contact frames and optimise them.

Example::

    python pretrain/build_pose_bank.py --data-root ./hogsa_world --data-contactnet runs/contactnet \
        --run-out banks/small --data-per-sequence 16

For every sequence (or those of ``--data-subjects``), ``--data-per-sequence`` contact frames
(evenly spaced) are perturbed ``--data-variants`` times each (different seeds) and optimised;
samples the optimiser drops are left out, and so are those failing GraspTTA's acceptance
unless ``--pom-keep-rejected``. Writes ``poses.safetensors`` + ``manifest.json`` (read with
:func:`hogsa_loader.pom.load_pose_bank`). The flags are those of
:class:`hogsa_loader.pom.job_config.PoseBankConfig` (``--help``); same as ``hogsa train bank``.
"""

import sys

from hogsa_loader.cli.train import build_pose_bank_main as main
from hogsa_loader.cli.train import parse_bank_args as parse_args

__all__ = ["main", "parse_args"]

if __name__ == "__main__":
    sys.exit(main())
