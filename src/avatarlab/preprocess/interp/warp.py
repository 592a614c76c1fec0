"""Warping shared by the XVFI-style network and the classical Farneback baseline: backward warping by a flow field and
the complementary linear flow reversal to an intermediate time (XVFI / Super SloMo)."""
from __future__ import annotations

import torch
import torch.nn.functional as F


def backward_warp(image: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """Sample image (B,C,H,W) at x + flow(x); flow (B,2,H,W) in pixels (dx, dy). The sampling positions and the
    sampling are float32 whatever the inputs are: under bfloat16 autocast, pixel index + flow would round to 1/2 px at
    x ~ 100 (the network then learns from, and renders, a warp off by up to 0.25 px)."""
    image, flow = image.float(), flow.float()
    b, _, h, w = image.shape
    ys, xs = torch.meshgrid(torch.arange(h, device=image.device), torch.arange(w, device=image.device),
                            indexing="ij")
    gx = (xs[None] + flow[:, 0]) * 2 / max(w - 1, 1) - 1
    gy = (ys[None] + flow[:, 1]) * 2 / max(h - 1, 1) - 1
    return F.grid_sample(image, torch.stack([gx, gy], -1), mode="bilinear", padding_mode="border",
                         align_corners=True)


def flow_reversal(f01: torch.Tensor, f10: torch.Tensor, t: float):
    """Complementary linear flow reversal: flows from time t back to frames 0 and 1 (as in XVFI / Super SloMo)."""
    ft0 = -(1 - t) * t * f01 + t * t * f10
    ft1 = (1 - t) * (1 - t) * f01 - t * (1 - t) * f10
    return ft0, ft1
