"""Samples: HOGS renders (and real frames) turned into ArcticNet-SF ``(inputs, targets, meta_info)``.

* :mod:`~hogsa_loader.sample.dataset` — :class:`HOGSADataset`, the endless stream (IterableDataset);
* :mod:`~hogsa_loader.sample.config` — :class:`LoaderConfig`, every setting of the loader, in groups;
* :mod:`~hogsa_loader.sample.mixing` — :class:`MixedLoader`, real and synthetic in one batch;
* :mod:`~hogsa_loader.sample.plan` / :mod:`~hogsa_loader.sample.synth` — the random streams of a
  render batch (:class:`BatchPlan`) and the batched pipeline (:class:`SynthPipeline`);
* :mod:`~hogsa_loader.sample.poses`, :mod:`~hogsa_loader.sample.bank_poses`,
  :mod:`~hogsa_loader.sample.online_poses`, :mod:`~hogsa_loader.sample.cameras` — poses and cameras;
* :mod:`~hogsa_loader.sample.targets` / :mod:`~hogsa_loader.sample.augment` — posed hands, object,
  camera and image to ArcticNet-SF's sample, with ARCTIC's augmentation;
* :mod:`~hogsa_loader.sample.arctic_dataset` — :class:`ArcticDataset`, the real frames;
* :mod:`~hogsa_loader.sample.export` — samples as WebDataset shards, written and read.
"""

from hogsa_loader.sample.arctic_dataset import ArcticDataset
from hogsa_loader.sample.bank_poses import BankPoses
from hogsa_loader.sample.cameras import CameraConfig, CameraSampler
from hogsa_loader.sample.config import (
    BackgroundConfig,
    LoaderConfig,
    PoseConfig,
    RefinementConfig,
    RunConfig,
    SampleChecks,
    SampleConfig,
    with_options,
)
from hogsa_loader.sample.dataset import HOGSADataset, shard_info
from hogsa_loader.sample.frame import SynthFrame
from hogsa_loader.sample.mixing import MixedLoader, num_synthetic
from hogsa_loader.sample.online_poses import OnlinePoses
from hogsa_loader.sample.plan import BatchPlan
from hogsa_loader.sample.poses import PoseBatch, PoseContext, PoseSource, register_pose_source
from hogsa_loader.sample.synth import SynthPipeline, SynthStats, frame_to_sample, is_synthetic, parse_synthetic_imgname
from hogsa_loader.sample.targets import HandLabels, ObjectLabels, make_arctic_sample

__all__ = [
    "ArcticDataset",
    "HandLabels",
    "ObjectLabels",
    "make_arctic_sample",
    "BackgroundConfig",
    "BankPoses",
    "BatchPlan",
    "CameraConfig",
    "CameraSampler",
    "HOGSADataset",
    "LoaderConfig",
    "MixedLoader",
    "OnlinePoses",
    "PoseBatch",
    "PoseConfig",
    "PoseContext",
    "PoseSource",
    "RefinementConfig",
    "RunConfig",
    "SampleChecks",
    "SampleConfig",
    "SynthFrame",
    "SynthPipeline",
    "SynthStats",
    "frame_to_sample",
    "is_synthetic",
    "num_synthetic",
    "parse_synthetic_imgname",
    "register_pose_source",
    "shard_info",
    "with_options",
]
