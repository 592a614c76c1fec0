"""Classical baseline: OpenCV Farneback flows both ways, linear flow reversal to t, warp and average; and the same
flows for a batch of image tensors (the XVFI-style network's starting flows)."""
from __future__ import annotations

import cv2
import numpy as np
import torch

from avatarlab.preprocess.interp.warp import backward_warp, flow_reversal


def farneback(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ga, gb = (cv2.cvtColor(x, cv2.COLOR_RGB2GRAY) for x in (a, b))
    return cv2.calcOpticalFlowFarneback(ga, gb, None, 0.5, 3, 15, 3, 5, 1.2, 0)


def interpolate_farneback(a: np.ndarray, b: np.ndarray, t: float = 0.5) -> np.ndarray:
    """a, b: RGB uint8 frames -> the RGB uint8 frame at time t."""
    f01 = torch.from_numpy(farneback(a, b)).permute(2, 0, 1)[None]
    f10 = torch.from_numpy(farneback(b, a)).permute(2, 0, 1)[None]
    ft0, ft1 = flow_reversal(f01, f10, t)
    ta, tb = (torch.from_numpy(x).permute(2, 0, 1)[None].float() / 255 for x in (a, b))
    out = (1 - t) * backward_warp(ta, ft0) + t * backward_warp(tb, ft1)
    return (out[0].permute(1, 2, 0).clamp(0, 1).numpy() * 255).round().astype(np.uint8)


@torch.no_grad()
def farneback_flows(i0: torch.Tensor, i1: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """i0, i1 (B, 3, H, W) in [0, 1] -> Farneback flows F01, F10 (B, 2, H, W) in pixels, as the baseline computes
    them (on the 8-bit frames), on the images' device."""
    def u8(x):
        return (x.detach().float().clamp(0, 1).permute(0, 2, 3, 1).cpu().numpy() * 255).round().astype(np.uint8)

    a, b = u8(i0), u8(i1)
    f01 = np.stack([farneback(x, y) for x, y in zip(a, b)])
    f10 = np.stack([farneback(y, x) for x, y in zip(a, b)])
    return tuple(torch.from_numpy(f).permute(0, 3, 1, 2).to(i0.device) for f in (f01, f10))
