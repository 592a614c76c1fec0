"""A compact XVFI-style interpolator (Sim et al. 2021, as used in seed 002 section 4.3).

What it keeps from XVFI: a flow module shared across scales (applied coarse to fine, each scale refining the upsampled
flows of the coarser one), bidirectional flows F01/F10, complementary flow reversal to the intermediate time t,
backward warping, and a synthesis step that blends the two warped frames with a learned occlusion map plus a
residual refinement. Sizes are small so it trains on one subject's frames on a CPU.
"""
from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn


def backward_warp(image: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """Sample image (B,C,H,W) at x + flow(x); flow (B,2,H,W) in pixels (dx, dy)."""
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


def _block(cin, cout):
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), nn.LeakyReLU(0.1, inplace=True))


class FlowModule(nn.Module):
    """Refines bidirectional flows at one scale; the same weights serve every scale (XVFI's recursion)."""

    def __init__(self, width: int):
        super().__init__()
        self.net = nn.Sequential(_block(3 * 4 + 4, width), _block(width, width), nn.Conv2d(width, width, 3, padding=2,
                                                                                          dilation=2),
                                 nn.LeakyReLU(0.1, inplace=True), _block(width, width), nn.Conv2d(width, 4, 3, padding=1))

    def forward(self, i0, i1, f01, f10):
        x = torch.cat([i0, i1, backward_warp(i1, f01), backward_warp(i0, f10), f01 / 8, f10 / 8], 1)
        d = self.net(x) * 8
        return f01 + d[:, :2], f10 + d[:, 2:]


class SynthesisModule(nn.Module):
    def __init__(self, width: int):
        super().__init__()
        self.net = nn.Sequential(_block(3 * 4 + 4, width), _block(width, width), _block(width, width),
                                 nn.Conv2d(width, 4, 3, padding=1))

    def forward(self, i0, i1, w0, w1, ft0, ft1, t):
        out = self.net(torch.cat([i0, i1, w0, w1, ft0 / 8, ft1 / 8], 1))
        vis = torch.sigmoid(out[:, :1])
        blend = ((1 - t) * vis * w0 + t * (1 - vis) * w1) / ((1 - t) * vis + t * (1 - vis) + 1e-6)
        return (blend + 0.1 * torch.tanh(out[:, 1:])).clamp(0, 1)


MODEL_FORMAT = "avatarlab-interpolator-1"


class XVFILite(nn.Module):
    def __init__(self, width: int = 32, scales: int = 3):
        super().__init__()
        self.scales, self.width = scales, width
        self.flow = FlowModule(width)
        self.synthesis = SynthesisModule(width)
        # start as a cross-fade with zero motion: flow residuals, occlusion logits and refinement at zero
        for last in (self.flow.net[-1], self.synthesis.net[-1]):
            nn.init.zeros_(last.weight)
            nn.init.zeros_(last.bias)

    def flows(self, i0, i1):
        f01 = f10 = None
        for s in reversed(range(self.scales)):
            a = F.interpolate(i0, scale_factor=0.5**s, mode="bilinear", align_corners=False) if s else i0
            b = F.interpolate(i1, scale_factor=0.5**s, mode="bilinear", align_corners=False) if s else i1
            if f01 is None:
                f01 = torch.zeros(a.shape[0], 2, *a.shape[2:], device=a.device)
                f10 = torch.zeros_like(f01)
            else:
                f01 = F.interpolate(f01, size=a.shape[2:], mode="bilinear", align_corners=False) * 2
                f10 = F.interpolate(f10, size=a.shape[2:], mode="bilinear", align_corners=False) * 2
            f01, f10 = self.flow(a, b, f01, f10)
        return f01, f10

    def forward(self, i0: torch.Tensor, i1: torch.Tensor, t: float = 0.5) -> torch.Tensor:
        """i0, i1 (B,3,H,W) in [0,1] -> the frame at time t."""
        f01, f10 = self.flows(i0, i1)
        ft0, ft1 = flow_reversal(f01, f10, t)
        return self.synthesis(i0, i1, backward_warp(i0, ft0), backward_warp(i1, ft1), ft0, ft1, t)


def save_interpolator(path: Path, model: XVFILite, iterations: int) -> None:
    """Weights only (tensors and plain values), written atomically."""
    from avatarlab.io import atomic_path

    with atomic_path(Path(path)) as tmp:
        torch.save({"format": MODEL_FORMAT, "width": model.width, "scales": model.scales, "iterations": iterations,
                    "state": {k: v.cpu() for k, v in model.state_dict().items()}}, tmp)


def load_interpolator(path: str | Path, device: torch.device | str = "cpu") -> XVFILite:
    """A model.pt written by save_interpolator -> the network in eval mode; anything else stops with one line."""
    from avatarlab.safe_load import load_tensors

    content = load_tensors(Path(path), "a frame interpolator (model.pt)")
    if not isinstance(content, dict) or content.get("format") != MODEL_FORMAT:
        raise ValueError(f"{path}: not an avatarlab frame interpolator (expected format {MODEL_FORMAT})")
    model = XVFILite(int(content["width"]), int(content["scales"]))
    model.load_state_dict(content["state"])
    return model.eval().to(device)
