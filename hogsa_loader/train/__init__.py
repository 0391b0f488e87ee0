"""Training of the HOGS models (``pretrain/train_hogs.py``)."""

from hogsa_loader.train.hogs_data import HogsData, ViewSample, dilate_mask, load_hogs_data, select_sequences
from hogsa_loader.train.hogs_trainer import BASE_LRS, PART_NAMES, HogsConfig, HogsTrainer
from hogsa_loader.train.losses import alpha_outside, box_of, hogs_loss, masked_l1, masked_ssim, psnr, ssim_map

__all__ = [
    "BASE_LRS", "PART_NAMES", "HogsConfig", "HogsData", "HogsTrainer", "ViewSample", "alpha_outside", "box_of",
    "dilate_mask", "hogs_loss", "load_hogs_data", "masked_l1", "masked_ssim", "psnr", "select_sequences", "ssim_map",
]
