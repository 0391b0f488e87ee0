"""ArcticNet-SF trained by PyTorch Lightning on real ARCTIC batches mixed with HOGSA samples.

A minimal ``LightningModule`` around the baseline (ARCTIC trains ArcticNet-SF with PyTorch
Lightning): the model, ARCTIC's target preparation and loss, Adam. ``train_dataloader``
returns :func:`~hogsa_loader.integrations.arctic.wrap_train_loader` around an ordinary
shuffled DataLoader of the real split. Under Lightning's DDP strategy each process trains on
its own share of both halves: the real loader is given a ``DistributedSampler`` by the mixed
loader (Lightning does this only for the DataLoaders it can see), the synthetic stream splits
itself by rank, and the ``set_epoch`` Lightning calls on the loader's ``sampler`` before each
epoch reaches the real sampler, the real dataset and the synthetic stream.

Every training step appends one JSON line to ``OUT/lightning.rank<R>.jsonl`` (its epoch, the
image names of its real and synthetic samples, the epochs the real sampler and the synthetic
stream are at, whether the real loader pins memory); after training each rank appends the
digest of its weights. With ``--ckpt-every N`` Lightning keeps a checkpoint every N steps
(the mixed loader's place in its epoch included: it has ``state_dict``); ``--resume CKPT``
continues from one, mid-epoch, on the batches an uninterrupted run trains on.

Usage (one process, or N under torchrun; ``pip install pytorch-lightning``)::

    python examples/lightning_arcticnet.py --data DATA --bundle BUNDLE --out OUT
    torchrun --nproc-per-node 2 examples/lightning_arcticnet.py --data DATA --bundle BUNDLE \\
        --out OUT --devices 2 [--accelerator cpu|gpu] [--epochs 1] [--batches-per-epoch 0]
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import Any

import pytorch_lightning as pl
import torch
from pytorch_lightning.callbacks import ModelCheckpoint
from torch.utils.data import DataLoader

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.baselines.arcticnet_sf import ArcticNetSF
from hogsa_loader.baselines.engine import BodyLayers, prepare_batch
from hogsa_loader.baselines.loss import arcticnet_sf_loss
from hogsa_loader.integrations.arctic import METHODS, wrap_train_loader
from hogsa_loader.sample import ArcticDataset, is_synthetic
from hogsa_loader.sample.augment import ArcticConfig
from hogsa_loader.train.finetune import weights_digest


class ArcticNetSFModule(pl.LightningModule):
    """ArcticNet-SF (``backbone``, ``img_res`` px patches) trained on ``wrap_train_loader``'s batches."""

    def __init__(self, args: argparse.Namespace) -> None:
        super().__init__()
        self.args = args
        layers = BodyLayers.from_root(ArcticRoot(args.data))
        self.mano_r, self.mano_l, self.objects = layers.mano_r, layers.mano_l, layers.objects
        self.model = ArcticNetSF(args.backbone, layers.mano_r, layers.mano_l, layers.objects, img_res=args.img_res)
        self.mixed: Any = None

    def train_dataloader(self) -> Any:
        real_ds = ArcticDataset(
            self.args.data, split="p1_train", seed=self.args.seed, config=ArcticConfig(img_res=self.args.img_res)
        )
        real = DataLoader(real_ds, batch_size=self.args.batch_size, shuffle=True, drop_last=True, pin_memory=True)
        self.mixed = wrap_train_loader(
            real,
            self.args.bundle,
            self.args.ratio,
            method=self.args.method,
            seed=self.args.seed,
            device=str(self.device),
        )
        return self.mixed

    def training_step(self, batch: Any, batch_idx: int) -> torch.Tensor:
        layers = BodyLayers(self.mano_r, self.mano_l, self.objects)
        inputs, targets, meta_info = prepare_batch(batch, layers, self.args.img_res, self.device)
        losses = arcticnet_sf_loss(self.model(inputs, meta_info), targets)
        self.log("loss", losses["loss"], prog_bar=True, batch_size=len(meta_info["imgname"]))
        self._record(batch)
        return losses["loss"]

    def _record(self, batch: Any) -> None:
        names = list(batch[2]["imgname"])
        real = self.mixed.real_loader
        row = {
            "epoch": self.current_epoch,
            "real": [n for n in names if not is_synthetic(n)],
            "synthetic": [n for n in names if is_synthetic(n)],
            "real_sampler": type(real.sampler).__name__,
            "real_sampler_epoch": getattr(real.sampler, "epoch", None),
            "synthetic_epoch": getattr(self.mixed.synthetic, "epoch", None),
            "pin_memory": bool(real.pin_memory),
        }
        self._write(row)

    def _write(self, row: dict[str, Any]) -> None:
        path = Path(self.args.out) / f"lightning.rank{self.global_rank}.jsonl"
        with open(path, "a") as fh:
            fh.write(json.dumps(row) + "\n")

    def on_train_end(self) -> None:
        self._write({"weights": weights_digest(self.model), "world_size": self.trainer.world_size})

    def configure_optimizers(self) -> torch.optim.Optimizer:
        return torch.optim.Adam(self.model.parameters(), lr=self.args.lr)


def parse_args(argv: Any = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True, help="ARCTIC data root")
    p.add_argument("--bundle", required=True, help="HOGSA bundle")
    p.add_argument("--out", required=True, help="folder of the step logs")
    p.add_argument("--method", default="no_pom", choices=list(METHODS), help="synthetic samples")
    p.add_argument("--ratio", type=float, default=0.5, help="synthetic share of each batch")
    p.add_argument("--backbone", default="resnet50", choices=["resnet18", "resnet50"])
    p.add_argument("--img-res", type=int, default=224, help="patch side (px)")
    p.add_argument("--batch-size", type=int, default=64, help="samples per batch per process")
    p.add_argument("--lr", type=float, default=1e-5)
    p.add_argument("--epochs", type=int, default=1)
    p.add_argument("--batches-per-epoch", type=int, default=0, help="batches of each epoch (0: all)")
    p.add_argument("--devices", type=int, default=1, help="processes (DDP when more than one)")
    p.add_argument("--accelerator", default="cpu", choices=["cpu", "gpu"])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--ckpt-every", type=int, default=0, help="a checkpoint every N steps in OUT/checkpoints (0: none)")
    p.add_argument("--resume", default=None, help="checkpoint to resume from (mid-epoch: the mixed loader's state too)")
    return p.parse_args(argv)


def main(argv: Any = None) -> None:
    args = parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    pl.seed_everything(args.seed, verbose=False)
    torch.set_num_threads(1)
    trainer = pl.Trainer(
        accelerator=args.accelerator,
        devices=args.devices,
        strategy="ddp" if args.devices > 1 else "auto",
        max_epochs=args.epochs,
        limit_train_batches=args.batches_per_epoch or 1.0,
        logger=False,
        enable_checkpointing=bool(args.ckpt_every),
        callbacks=[every_n(args)] if args.ckpt_every else None,
        enable_progress_bar=False,
        enable_model_summary=False,
        num_sanity_val_steps=0,
    )
    trainer.fit(ArcticNetSFModule(args), ckpt_path=args.resume)


def every_n(args: argparse.Namespace) -> pl.Callback:
    """Keep a checkpoint every ``--ckpt-every`` steps (``step=N.ckpt``)."""
    return ModelCheckpoint(
        dirpath=os.path.join(args.out, "checkpoints"),
        filename="{step}",
        every_n_train_steps=args.ckpt_every,
        save_top_k=-1,
    )


if __name__ == "__main__":
    main()
