"""Image quality metrics (PSNR, SSIM, YUV-PSNR, LPIPS), one implementation shared by the training loss and the
evaluation: the SSIM that training minimises is the SSIM that `stgc eval` reports."""

from stgc.metrics.image import (
    LPIPS,
    gaussian_window,
    lpips_status,
    mse,
    psnr,
    psnr_of_mse,
    psnr_per_image,
    ssim,
    ssim_map,
    ssim_per_image,
    yuv_psnr,
)

__all__ = [
    "LPIPS",
    "gaussian_window",
    "lpips_status",
    "mse",
    "psnr",
    "psnr_of_mse",
    "psnr_per_image",
    "ssim",
    "ssim_map",
    "ssim_per_image",
    "yuv_psnr",
]
