"""Scores of a model and of its trivial baselines on the same frames, and the model's gain over the best baseline."""
from __future__ import annotations

import torch

from avatarlab.metrics.quality import psnr, psnr_colour_matched, psnr_in_mask, ssim

#: metrics where lower is better
LOWER_IS_BETTER = {"st_lpips", "lpips", "landmark_nme"}


def image_scores(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, perceptual: dict) -> dict:
    """PSNR (whole image), head-region PSNR, the same with each image's mean colour matched to the target's
    (`psnr_head_colour`: a diagnostic of structure, for recordings whose colour no training frame had), SSIM and each
    perceptual metric (name -> callable or None)."""
    out = {"psnr": psnr(pred, target), "psnr_head": psnr_in_mask(pred, target, mask),
           "psnr_head_colour": psnr_colour_matched(pred, target, mask), "ssim": ssim(pred, target)}
    for name, metric in perceptual.items():
        out[name] = metric(pred, target) if metric is not None else None
    return out


def gains(model: dict, baselines: dict[str, dict]) -> dict:
    """Per metric: the best baseline's name and value, and the model's gain over it (positive: the model is better,
    for every metric whatever its direction)."""
    out = {}
    for metric, value in model.items():
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            continue
        candidates = {name: b.get(metric) for name, b in baselines.items() if isinstance(b.get(metric), (int, float))}
        if not candidates:
            continue
        lower = metric in LOWER_IS_BETTER
        best = (min if lower else max)(candidates, key=candidates.get)
        gain = candidates[best] - value if lower else value - candidates[best]
        out[metric] = {"best_baseline": best, "baseline": candidates[best], "gain": gain, "beats": gain > 0}
    return out
