"""Evaluation: image metrics, model size / bitrate / speed accounting, the evaluation driver, Bjøntegaard
deltas and paper-style reports."""

from stgc.eval.metrics import (
    LPIPS,
    gaussian_window,
    lpips_status,
    mse,
    psnr,
    psnr_per_image,
    ssim,
    ssim_map,
    ssim_per_image,
)

__all__ = [
    "LPIPS",
    "gaussian_window",
    "lpips_status",
    "mse",
    "psnr",
    "psnr_per_image",
    "ssim",
    "ssim_map",
    "ssim_per_image",
]
