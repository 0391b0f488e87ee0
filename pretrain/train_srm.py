#!/usr/bin/env python
"""Train the SRM (StyleUNet refinement of HOGS renders) on every finished HOGS run of a folder.

Example::

    python pretrain/train_srm.py --data-root ./hogsa_world --data-hogs runs/hogs --run-out runs/srm \
        --optim-iters 4000

Pairs the frozen HOGS renders of each run's *training* views/frames (same split as its HOGS
training; held-out views and frames are never used) with the masked ground-truth crops and
trains one StyleUNet for all of them with ``5·L1 + 0.03·VGG19 + GAN`` (without
``--loss-vgg-weights`` a Laplacian-pyramid L1 substitutes for VGG, weight 1.0, with a warning).
Writes the final EMA generator (``manifest.json`` + ``srm.safetensors``, read by
``hogsa_loader.srm.load_srm(RUN)``), ``metrics.json`` (held-out PSNR/SSIM without vs with
SRM, per view), ``samples.png`` (coarse | refined | GT) and ``curves.png`` into ``--run-out``;
``--resume`` continues exactly from the latest checkpoint. ``--data-cross-hogs FOLDS`` adds
inputs rendered by view-fold runs that never saw the sample's view; ``--data-val-views V``
keeps those training views out and saves the checkpoint that scores best on them (early
stopping without looking at the held-out views). A folder holding checkpoints is refused
unless ``--resume`` or ``--overwrite`` (start again from step 0) is given; every argument is
checked before the runs are read. The flags are those of
:class:`hogsa_loader.train.srm_trainer.SRMTrainConfig` (``--help``); same as ``hogsa train srm``.
"""

import sys

from hogsa_loader.cli.train import parse_srm_args as parse_args
from hogsa_loader.cli.train import train_srm_main as main

__all__ = ["main", "parse_args"]

if __name__ == "__main__":
    sys.exit(main())
