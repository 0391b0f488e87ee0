"""Training: HOGS (``hogsa train hogs``), the SRM (``hogsa train srm``), ContactNet and the pose
bank (``hogsa train contactnet|bank``). The runtime library never imports this package."""

from hogsa_loader.train.hogs_config import (
    HogsConfig,
    HogsDataConfig,
    HogsLossConfig,
    HogsModelConfig,
    HogsOptimConfig,
    HogsRunConfig,
)
from hogsa_loader.train.hogs_data import (
    MASK_MODES,
    FrameSelection,
    HogsData,
    ViewSample,
    dilate_mask,
    load_hogs_data,
    select_sequences,
)
from hogsa_loader.train.hogs_data_h2o import load_h2o_hogs_data
from hogsa_loader.train.hogs_source import HogsSource, load_run_data, open_hogs_source
from hogsa_loader.train.hogs_trainer import BASE_LRS, PART_NAMES, HogsTrainer
from hogsa_loader.train.losses import alpha_outside, box_of, hogs_loss, masked_l1, masked_ssim, psnr, ssim_map

__all__ = [
    "BASE_LRS",
    "FrameSelection",
    "MASK_MODES",
    "PART_NAMES",
    "HogsConfig",
    "HogsData",
    "HogsDataConfig",
    "HogsLossConfig",
    "HogsModelConfig",
    "HogsOptimConfig",
    "HogsRunConfig",
    "HogsSource",
    "HogsTrainer",
    "ViewSample",
    "alpha_outside",
    "box_of",
    "dilate_mask",
    "hogs_loss",
    "load_h2o_hogs_data",
    "load_hogs_data",
    "load_run_data",
    "masked_l1",
    "masked_ssim",
    "open_hogs_source",
    "psnr",
    "select_sequences",
    "ssim_map",
]
