"""POM — the pose-optimisation module of HOGSA (GraspTTA-style test-time grasp optimisation).

* :mod:`~hogsa_loader.models.pom.contactnet` — topology-free ContactNet, GraspTTA's contact map,
  safetensors checkpoints;
* :mod:`~hogsa_loader.models.pom.perturb` — the paper's perturbation (seeded), optional finger noise;
* :mod:`~hogsa_loader.models.pom.losses` — L_C, L_H, L_P, pose prior;
* :mod:`~hogsa_loader.models.pom.optimize` — batched bimanual optimisation;
* :mod:`~hogsa_loader.models.pom.metrics` — penetration depth, intersection volume, contact,
  acceptance, diversity;
* :mod:`~hogsa_loader.models.pom.bank` — pose-bank files (``load_pose_bank``);
* helpers: :mod:`geometry` (ray parity, SDF grids), :mod:`objects`, :mod:`hands`,
  :mod:`state`, :mod:`train`, :mod:`pipeline`, :mod:`viz`.
"""

from hogsa_loader.models.pom.bank import PoseBank, load_pose_bank, save_pose_bank
from hogsa_loader.models.pom.contactnet import (
    ContactNet,
    ContactNetConfig,
    contact_map,
    load_contactnet,
    save_contactnet,
)
from hogsa_loader.models.pom.hands import HandInfo, hand_infos
from hogsa_loader.models.pom.metrics import diversity, grasp_metrics, summarize
from hogsa_loader.models.pom.objects import ObjectSet
from hogsa_loader.models.pom.optimize import POMConfig, POMResult, optimise_grasps
from hogsa_loader.models.pom.perturb import KEEP_ARTICULATION, FingerNoise, PerturbConfig, PerturbRecord, perturb
from hogsa_loader.models.pom.state import GraspState, HandParams, load_frames

__all__ = [
    "ContactNet",
    "ContactNetConfig",
    "contact_map",
    "load_contactnet",
    "save_contactnet",
    "GraspState",
    "HandParams",
    "load_frames",
    "HandInfo",
    "hand_infos",
    "ObjectSet",
    "PerturbConfig",
    "KEEP_ARTICULATION",
    "FingerNoise",
    "PerturbRecord",
    "perturb",
    "POMConfig",
    "POMResult",
    "optimise_grasps",
    "grasp_metrics",
    "diversity",
    "summarize",
    "PoseBank",
    "load_pose_bank",
    "save_pose_bank",
]
