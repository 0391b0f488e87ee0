"""Offline export of synthetic frames as WebDataset tar shards, and reading them back.

* :func:`write_shards` — resumable, rank-sharded writer (``hogsa export`` uses it), fed from a
  dataset by :func:`dataset_frames_for_shard` (each shard's drops by reason kept in its index);
* :class:`SynthShardSamples` — the same samples as a map-style dataset (shuffled reading);
* :class:`SynthShardDataset` — torch ``IterableDataset`` over the shards yielding
  :class:`~hogsa_loader.sample.frame.SynthFrame` or, with ``arctic_samples=True``,
  ArcticNet-SF ``(inputs, targets, meta_info)`` samples augmented like ARCTIC;
* :func:`encode_frame` / :func:`decode_frame` — one sample's tar members.
"""

from hogsa_loader.sample.export.codec import FORMAT_VERSION, decode_frame, encode_frame, frame_labels
from hogsa_loader.sample.export.reader import (
    SynthShardDataset,
    SynthShardSamples,
    expand_shards,
    frame_to_arctic_sample,
    iter_tar_samples,
)
from hogsa_loader.sample.export.writer import (
    INDEX_NAME,
    ExportMismatchError,
    ShardFrames,
    dataset_frames_for_shard,
    export_settings,
    num_shards,
    rebuild_index,
    sample_key,
    shard_name,
    shard_range,
    shards_of_rank,
    write_shards,
)

__all__ = [
    "FORMAT_VERSION",
    "INDEX_NAME",
    "ExportMismatchError",
    "ShardFrames",
    "SynthShardDataset",
    "SynthShardSamples",
    "dataset_frames_for_shard",
    "decode_frame",
    "encode_frame",
    "expand_shards",
    "export_settings",
    "frame_labels",
    "frame_to_arctic_sample",
    "iter_tar_samples",
    "num_shards",
    "rebuild_index",
    "sample_key",
    "shard_name",
    "shard_range",
    "shards_of_rank",
    "write_shards",
]
