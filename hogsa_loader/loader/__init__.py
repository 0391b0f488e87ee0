"""The synthetic loader: HOGS renders turned into ArcticNet-SF samples.

* :mod:`~hogsa_loader.loader.config` — :class:`LoaderConfig`, every setting of the loader, in groups;
* :mod:`~hogsa_loader.loader.plan` — the random streams and :class:`BatchPlan` (one render batch);
* :mod:`~hogsa_loader.loader.frame` — :class:`SynthFrame`, a composited crop + labels;
* :mod:`~hogsa_loader.loader.cameras` — novel / dataset cameras (:class:`CameraSampler`);
* :mod:`~hogsa_loader.loader.poses` — pluggable pose sources (``"perturb"``, registry);
* :mod:`~hogsa_loader.loader.bank_poses` — ``"bank"``: POM-optimised grasps of pose banks;
* :mod:`~hogsa_loader.loader.online_poses` — ``"online"``: POM run per render batch;
* :mod:`~hogsa_loader.loader.viz` — samples with their 2D labels drawn (grids);
* :mod:`~hogsa_loader.loader.synth` — the batched pipeline (:class:`SynthPipeline`);
* :mod:`~hogsa_loader.loader.dataset` — :class:`HOGSADataset` (torch IterableDataset);
* :mod:`~hogsa_loader.loader.mixing` — :class:`MixedLoader` (exact synthetic share per batch).
"""

from hogsa_loader.loader.bank_poses import BankPoses
from hogsa_loader.loader.cameras import CameraConfig, CameraSampler
from hogsa_loader.loader.config import (
    BackgroundConfig,
    LoaderConfig,
    PoseConfig,
    RefinementConfig,
    RunConfig,
    SampleChecks,
    SampleConfig,
    with_options,
)
from hogsa_loader.loader.dataset import HOGSADataset, shard_info
from hogsa_loader.loader.frame import SynthFrame
from hogsa_loader.loader.mixing import MixedLoader, num_synthetic
from hogsa_loader.loader.online_poses import OnlinePoses
from hogsa_loader.loader.plan import BatchPlan
from hogsa_loader.loader.poses import PoseBatch, PoseContext, PoseSource, register_pose_source
from hogsa_loader.loader.synth import SynthPipeline, SynthStats, frame_to_sample, is_synthetic, parse_synthetic_imgname

__all__ = [
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
