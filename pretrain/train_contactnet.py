#!/usr/bin/env python
"""Train POM's ContactNet on the annotated frames of an ARCTIC-format dataset.

Example::

    python pretrain/train_contactnet.py --data-root ./hogsa_world --run-out runs/contactnet \
        --optim-iters 1500 --data-val-subjects s02

ContactNet trains on the subjects the dataset's protocol does not hold out (s03 and s05 on
ARCTIC are never read unless named in ``--data-allow-held-out``); ``--data-val-subjects``
keeps named training subjects out of its training to validate on (default: none). Writes
``contactnet.safetensors`` + ``manifest.json`` (loaded by
:func:`hogsa_loader.pom.contactnet.load_contactnet`), ``metrics.json`` (validation MAE,
IoU@0.5, BCE, also on unperturbed hands) and ``curve.png`` into ``--run-out``. The flags are
those of :class:`hogsa_loader.pom.job_config.ContactNetJobConfig` (``--help``); same as
``hogsa train contactnet``.
"""

import sys

from hogsa_loader.cli.train import parse_contactnet_args as parse_args
from hogsa_loader.cli.train import train_contactnet_main as main

__all__ = ["main", "parse_args"]

if __name__ == "__main__":
    sys.exit(main())
