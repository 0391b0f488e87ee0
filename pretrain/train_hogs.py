#!/usr/bin/env python
"""Train one HOGS model (right hand, left hand, object Gaussians) per subject + object.

Example::

    python pretrain/train_hogs.py --data-root ./hogsa_world --data-subject s01 \
        --data-object box --run-out runs/s01_box --optim-iters 2000
    python pretrain/train_hogs.py --data-dataset h2o --data-root H2O_ROOT --data-mano-dir MANO_DIR \
        --data-object-mesh-dir H2O_ROOT/object --data-subject subject1 --data-object book \
        --run-out runs/h2o_s1_book

ARCTIC uses the root's ``masks/`` when present (the generated world) and renders the part
masks from the annotated meshes otherwise (``--data-masks``); H2O always renders them, crops
every full frame around the annotated hands and object, trains on the static cameras 0-3
and holds out camera 3 (``--data-views``, ``--data-eval-views``).

Writes the part checkpoints, ``metrics.json``, ``strip.png`` (GT | render | |error| on
held-out views) and ``curves.png`` into ``--run-out``; ``--resume`` continues the run there,
``--overwrite`` starts it again from step 0 (a folder holding checkpoints is refused without
one of them). Every argument is checked before the data is read. The flags are those of
:class:`hogsa_loader.train.HogsConfig` (``--help``); same as ``hogsa train hogs``.
"""

import sys

from hogsa_loader.cli.train import parse_hogs_args as parse_args
from hogsa_loader.cli.train import train_hogs_main as main

__all__ = ["main", "parse_args"]

if __name__ == "__main__":
    sys.exit(main())
