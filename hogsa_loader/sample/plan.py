"""Random streams and render-batch plans of the synthetic loader.

Every random draw of the loader comes from one of the streams in :data:`STREAMS`, each a
numpy generator seeded by a fixed sequence: a sample's streams by ``(seed, epoch, index,
stream)``, the model order of a block of render batches by ``(seed, epoch, block, 7)``, the
hands of render batch ``g`` by ``(seed, epoch, g, 8)``.
The export readers draw their shard order from :func:`shard_order`.
A :class:`BatchPlan` is everything one render batch depends on; the dataset builds it
and :class:`~hogsa_loader.sample.synth.SynthPipeline` renders it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

__all__ = [
    "STREAMS",
    "STREAM_AUG",
    "BATCH_ORDER_STREAM",
    "HANDS_STREAM",
    "SHARD_ORDER_STREAM",
    "sample_rng",
    "batch_order",
    "hands_rng",
    "shard_order",
    "BatchPlan",
]

#: The random streams of one sample: name → last entry of its seed sequence.
STREAMS: dict[str, int] = {"pose": 0, "camera": 1, "background": 2, "augment": 3}
#: The augmentation stream (also drawn by the export readers).
STREAM_AUG: int = STREAMS["augment"]
#: Last entry of the seed sequence of a block's model order (:func:`batch_order`).
BATCH_ORDER_STREAM: int = 7
#: Last entry of the seed sequence of a render batch's hands draw (:func:`hands_rng`).
HANDS_STREAM: int = 8
#: Last entry of the seed sequence of an export reader's shard order (:func:`shard_order`).
SHARD_ORDER_STREAM: int = 0x5A4D


def sample_rng(seed: int, epoch: int, index: int, stream: int) -> np.random.Generator:
    """The numpy generator of one random stream of sample ``index``.

    Args:
        seed: the loader's seed; epoch: its epoch; index: global sample index;
        stream: a value of :data:`STREAMS` (0 pose, 1 camera, 2 background, 3 augmentation).
    """
    return np.random.default_rng([int(seed), int(epoch), int(index), int(stream)])


def batch_order(seed: int, epoch: int, block: int, num_keys: int) -> np.ndarray:
    """(num_keys,) int: the order in which the render batches of ``block`` use the models."""
    return np.random.default_rng([int(seed), int(epoch), int(block), BATCH_ORDER_STREAM]).permutation(int(num_keys))


def hands_rng(seed: int, epoch: int, batch_index: int) -> np.random.Generator:
    """The numpy generator of render batch ``batch_index``'s hands draw (whose hand Gaussians it shows)."""
    return np.random.default_rng([int(seed), int(epoch), int(batch_index), HANDS_STREAM])


def shard_order(seed: int, epoch: int, num_shards: int) -> np.ndarray:
    """(num_shards,) int: the order in which a shuffling export reader visits the shards at ``epoch``."""
    return np.random.default_rng([int(seed), int(epoch), SHARD_ORDER_STREAM]).permutation(int(num_shards))


@dataclass(frozen=True)
class BatchPlan:
    """What one render batch depends on.

    Attributes:
        seed: the loader's seed; epoch: the epoch of the batch.
        key: ``(subject, object)`` of the HOGS model rendered.
        indices: global sample indices (each fixes its own random streams).
        hands: ``(subject, object)`` of the HOGS run whose hand Gaussians are rendered in
            place of the model's own (poses and labels unchanged); None: the model's own.
    """

    seed: int
    epoch: int
    key: tuple[str, str]
    indices: tuple[int, ...]
    hands: Optional[tuple[str, str]] = None

    def rngs(self, stream: str) -> list[np.random.Generator]:
        """One generator of stream ``stream`` (a name of :data:`STREAMS`) per sample."""
        return [sample_rng(self.seed, self.epoch, i, STREAMS[stream]) for i in self.indices]

    def rng(self, position: int, stream: str) -> np.random.Generator:
        """The generator of stream ``stream`` of the ``position``-th sample."""
        return sample_rng(self.seed, self.epoch, self.indices[position], STREAMS[stream])
