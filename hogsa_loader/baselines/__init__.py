"""ArcticNet-SF and InterField-SF (re-implementations of ARCTIC's single-frame baselines),
their losses, ARCTIC's metrics, and the training step / evaluation loop that use them."""

from hogsa_loader.baselines.arcticnet_sf import (
    ArcticNetSF,
    arctic_key_map,
    load_arctic_checkpoint,
    load_saved_model,
    matrix_to_rotation_6d,
    perspective_to_weak_perspective,
    rotation_6d_to_matrix,
    weak_perspective_to_perspective,
)
from hogsa_loader.baselines.clips import clip_sums, clip_uncertainty
from hogsa_loader.baselines.engine import BodyLayers, evaluate, mean_cameras, temporal_order, training_step
from hogsa_loader.baselines.interfield_sf import (
    FIELD_KEYS,
    FIELD_METRICS,
    InterFieldSF,
    evaluate_field,
    field_acceleration,
    field_metrics,
    field_training_step,
    interfield_loss,
    load_field_weights,
    read_mano_decimator,
)
from hogsa_loader.baselines.loss import ARCTIC_SF_LOSS_WEIGHTS, arcticnet_sf_loss
from hogsa_loader.baselines.metrics import per_frame_metrics, sequence_metrics, summarize
from hogsa_loader.baselines.resnet import ResNet, build_backbone, load_backbone_weights, resnet18, resnet50
from hogsa_loader.baselines.targets import estimate_translation_k, prepare_targets, solve_rigid_transform

__all__ = [
    "ARCTIC_SF_LOSS_WEIGHTS",
    "ArcticNetSF",
    "FIELD_KEYS",
    "FIELD_METRICS",
    "InterFieldSF",
    "evaluate_field",
    "field_acceleration",
    "field_metrics",
    "field_training_step",
    "interfield_loss",
    "read_mano_decimator",
    "load_field_weights",
    "BodyLayers",
    "arcticnet_sf_loss",
    "clip_sums",
    "clip_uncertainty",
    "evaluate",
    "mean_cameras",
    "per_frame_metrics",
    "sequence_metrics",
    "summarize",
    "temporal_order",
    "training_step",
    "ResNet",
    "arctic_key_map",
    "build_backbone",
    "estimate_translation_k",
    "load_arctic_checkpoint",
    "load_saved_model",
    "load_backbone_weights",
    "matrix_to_rotation_6d",
    "perspective_to_weak_perspective",
    "prepare_targets",
    "resnet18",
    "resnet50",
    "rotation_6d_to_matrix",
    "solve_rigid_transform",
    "weak_perspective_to_perspective",
]
