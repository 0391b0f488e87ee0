"""Fixtures of the baseline tests: the tiny world's body layers and two 64 px batches."""

from __future__ import annotations

import pytest
import torch
from torch.utils.data import DataLoader

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.baselines import BodyLayers
from hogsa_loader.compose import ProceduralBackgrounds
from hogsa_loader.sample import HOGSADataset, MixedLoader, with_options
from hogsa_loader.sample.arctic_dataset import ArcticDataset
from hogsa_loader.sample.augment import ArcticConfig

#: Patch side (px) of the fixture batches.
BATCH_RES = 64


@pytest.fixture(scope="module")
def layers(tiny_world):
    return BodyLayers.from_root(ArcticRoot(tiny_world))


@pytest.fixture(scope="module")
def batches(tiny_world, untrained_bundle):
    """A real batch of 4 and a mixed batch (2 real + 2 synthetic) of the tiny world, 64 px."""
    cfg = ArcticConfig(img_res=BATCH_RES)
    real = DataLoader(
        ArcticDataset(tiny_world, "p1_train", seed=0, config=cfg),
        batch_size=4,
        shuffle=True,
        generator=torch.Generator().manual_seed(0),
    )
    syn = HOGSADataset(
        untrained_bundle,
        tiny_world,
        with_options(arctic=cfg, batch_size=4, num_samples=8, seed=1),
        backgrounds=ProceduralBackgrounds(),
    )
    return next(iter(real)), next(iter(MixedLoader(real, syn, 0.5)))
