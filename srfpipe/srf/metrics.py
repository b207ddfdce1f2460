"""Image and segmentation metrics: PSNR, SSIM (Gaussian window), per-class IoU.

Plain numpy/torch so the evaluation has no extra dependency. Images are float in [0, 1].
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F


# The one floor of every PSNR in the project: the mean squared error is taken as at least 1e-12, so
# a perfect match reads 120 dB rather than infinity (which JSON cannot hold and no mean survives).
# Only a (near-)perfect match meets it: one 8-bit level off in one of 15 million values is 1e-12.
MSE_FLOOR = 1e-12


def psnr_from_mse(mse: float) -> float:
    """PSNR in dB of images in [0, 1] from their mean squared error per channel value, the error
    floored at MSE_FLOOR (at most 120 dB). A host float: pass a tensor only where it is read anyway."""
    return -10.0 * math.log10(max(float(mse), MSE_FLOOR))


def psnr(pred: np.ndarray, target: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR in dB over all pixels, or over the pixels where `mask` (H, W) is True (NaN when no pixel
    is); see `psnr_from_mse` for the floor."""
    err = (np.asarray(pred, np.float64) - np.asarray(target, np.float64)) ** 2
    if mask is not None:
        if not mask.any():
            return float("nan")
        err = err[mask]
    return psnr_from_mse(err.mean())


def _gaussian_window(size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def ssim(pred: np.ndarray, target: np.ndarray, window: int = 11, sigma: float = 1.5) -> float:
    """Mean SSIM (Wang et al. 2004) of two (H, W, 3) images in [0, 1], Gaussian 11x11, sigma 1.5,
    K1 = 0.01, K2 = 0.03, computed per channel over the valid (unpadded) region."""
    a = torch.as_tensor(np.asarray(pred), dtype=torch.float64).permute(2, 0, 1).unsqueeze(1)
    b = torch.as_tensor(np.asarray(target), dtype=torch.float64).permute(2, 0, 1).unsqueeze(1)
    window = min(window, *a.shape[-2:])
    window -= 1 - window % 2  # odd, and no larger than a tiny image
    g = _gaussian_window(window, sigma)
    kx, ky = g.view(1, 1, 1, -1), g.view(1, 1, -1, 1)

    def blur(x):
        return F.conv2d(F.conv2d(x, kx), ky)

    c1, c2 = 0.01**2, 0.03**2
    mu_a, mu_b = blur(a), blur(b)
    var_a = blur(a * a) - mu_a**2
    var_b = blur(b * b) - mu_b**2
    cov = blur(a * b) - mu_a * mu_b
    num = (2 * mu_a * mu_b + c1) * (2 * cov + c2)
    den = (mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2)
    return float((num / den).mean())


def label_from_probabilities(probabilities: np.ndarray, threshold: float = 0.5) -> np.ndarray:
    """Label image (…,) from per-class probabilities (…, C): 1 + argmax, 0 where no class passes."""
    probabilities = np.asarray(probabilities)
    if probabilities.shape[-1] == 0:  # no classes: every pixel is background
        return np.zeros(probabilities.shape[:-1], dtype=np.uint8)
    best = probabilities.argmax(axis=-1)
    return np.where(probabilities.max(axis=-1) >= threshold, best + 1, 0).astype(np.uint8)


def confusion(pred: np.ndarray, target: np.ndarray, num_labels: int) -> np.ndarray:
    """Confusion counts (num_labels, num_labels) [target, pred] over label images."""
    pred = np.asarray(pred, np.int64).ravel()
    target = np.asarray(target, np.int64).ravel()
    valid = (target >= 0) & (target < num_labels)
    return np.bincount(target[valid] * num_labels + pred[valid], minlength=num_labels**2).reshape(
        num_labels, num_labels
    )


def iou_from_confusion(matrix: np.ndarray) -> np.ndarray:
    """Per-label IoU = TP / (TP + FP + FN); NaN for a label absent from both prediction and target."""
    tp = np.diag(matrix).astype(np.float64)
    union = matrix.sum(0) + matrix.sum(1) - tp
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(union > 0, tp / np.maximum(union, 1), np.nan)
