"""A compact XVFI-style interpolator (Sim et al. 2021, as used in seed 002 section 4.3).

What it keeps from XVFI: a flow module shared across scales (applied coarse to fine, each scale refining the upsampled
flows of the coarser one), bidirectional flows F01/F10, complementary flow reversal to the intermediate time t,
backward warping, and a synthesis step that blends the two warped frames with a learned occlusion map plus a
residual refinement. Sizes are small so it trains on a CPU.

`keep_unwarped` (an option, off by default; not XVFI's): the synthesis may also keep a learned per-pixel share of the
unwarped cross-fade. Where the flows are nearly zero the cross-fade is almost exact, while a warp by small, noisy flows
resamples (blurs) the frame: on synth_talk's stillest held-out frames Farneback lost 1.0 dB to the cross-fade.
The share is `10 * keep * sigmoid(logit)`, `keep` a scalar that starts at
zero, so the untrained network is still exactly the warp of its starting flows. Over three seeds it moved the
held-out PSNR within the seeds' spread, so it stays off.

`still_flow_px` (not XVFI's): at inference, a pixel whose flow to the intermediate frame is shorter than this many
pixels is not warped (its flow set to zero, so the synthesis sees that frame's own pixel). A warp by a flow of a
fraction of a pixel resamples the frame bilinearly, which blurs it, while on a nearly still head such flows are
mostly the estimate's noise: on synth_talk's stillest held-out frames Farneback lost 1.0 dB to the cross-fade. The
pretraining step chooses it among `interp.still_flow_candidates` on its validation triplets, and it is saved with the
network. The default candidates are [0] (every pixel warped, as XVFI): one length for every video lifts the
synthetic subjects and costs real footage, where small flows are partly real motion. So the interpolation step
(`interp/run.py`) chooses the length again for each subject, on that subject's own kept frames
(`interp.subject_still_flow_candidates`, [0, 0.25, 0.5, 1] by default).

Where the flows start (`flow_init`): XVFI learns them from nothing, over days on a 4K video set; `zero` does the same
here. `farneback` (the default; a declared substitution) starts every scale from OpenCV's Farneback flows of the two
frames, and the shared flow module refines a residual on top of them coarse to fine: with the last layers at zero the
untrained network is exactly the Farneback baseline, and training on the platform's videos moves it from there - what
a few hundred CPU iterations can teach is the correction (occlusions, the flow's errors), not motion itself.
"""
from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from avatarlab.preprocess.interp.optical_flow import farneback_flows
from avatarlab.preprocess.interp.warp import backward_warp, flow_reversal

FLOW_INITS = ("zero", "farneback")


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
    """Occlusion-weighted blend of the two warped frames plus a residual; with `keep_unwarped`, a learned share of the
    unwarped cross-fade (see the module's docstring)."""

    def __init__(self, width: int, keep_unwarped: bool = False):
        super().__init__()
        self.keep_unwarped = keep_unwarped
        self.net = nn.Sequential(_block(3 * 4 + 4, width), _block(width, width), _block(width, width),
                                 nn.Conv2d(width, 5 if keep_unwarped else 4, 3, padding=1))
        if keep_unwarped:
            self.keep = nn.Parameter(torch.zeros(()))  # x10 below: Adam's steps of ~lr move the share fast enough

    def forward(self, i0, i1, w0, w1, ft0, ft1, t):
        out = self.net(torch.cat([i0, i1, w0, w1, ft0 / 8, ft1 / 8], 1))
        vis = torch.sigmoid(out[:, :1])
        blend = ((1 - t) * vis * w0 + t * (1 - vis) * w1) / ((1 - t) * vis + t * (1 - vis) + 1e-6)
        if self.keep_unwarped:
            share = 10 * self.keep * torch.sigmoid(out[:, 4:5])
            blend = (1 - share) * blend + share * ((1 - t) * i0 + t * i1)
        return (blend + 0.1 * torch.tanh(out[:, 1:4])).clamp(0, 1)


MODEL_FORMAT = "avatarlab-interpolator-1"


class XVFILite(nn.Module):
    def __init__(self, width: int = 32, scales: int = 3, flow_init: str = "zero", keep_unwarped: bool = False,
                 still_flow_px: float = 0.0):
        super().__init__()
        if flow_init not in FLOW_INITS:
            raise ValueError(f"flow_init must be one of {FLOW_INITS}, got {flow_init!r}")
        self.scales, self.width, self.flow_init, self.keep_unwarped = scales, width, flow_init, keep_unwarped
        self.still_flow_px = float(still_flow_px)
        self.flow = FlowModule(width)
        self.synthesis = SynthesisModule(width, keep_unwarped)
        # start as the initial flows' warp-and-average (a cross-fade for zero flows): flow residuals, occlusion logits
        # and refinement at zero
        for last in (self.flow.net[-1], self.synthesis.net[-1]):
            nn.init.zeros_(last.weight)
            nn.init.zeros_(last.bias)

    def initial_flows(self, i0, i1):
        """The flows the recursion starts from at full resolution: zero, or Farneback's both ways (no gradient)."""
        return (None, None) if self.flow_init == "zero" else farneback_flows(i0, i1)

    def flows(self, i0, i1):
        """Bidirectional flows, coarse to fine: at each scale the shared module refines the initial flows (resized
        to that scale) plus the residual carried up from the coarser scale."""
        init01, init10 = self.initial_flows(i0, i1)
        r01 = r10 = f01 = f10 = None
        for s in reversed(range(self.scales)):
            a = F.interpolate(i0, scale_factor=0.5**s, mode="bilinear", align_corners=False) if s else i0
            b = F.interpolate(i1, scale_factor=0.5**s, mode="bilinear", align_corners=False) if s else i1
            if init01 is None:
                base01 = base10 = torch.zeros(a.shape[0], 2, *a.shape[2:], device=a.device, dtype=a.dtype)
            else:
                base01, base10 = ((F.interpolate(f, size=a.shape[2:], mode="bilinear", align_corners=False) * 0.5**s
                                   if s else f).to(a.dtype) for f in (init01, init10))
            if r01 is None:
                r01, r10 = torch.zeros_like(base01), torch.zeros_like(base10)
            else:
                r01 = F.interpolate(r01, size=a.shape[2:], mode="bilinear", align_corners=False) * 2
                r10 = F.interpolate(r10, size=a.shape[2:], mode="bilinear", align_corners=False) * 2
            f01, f10 = self.flow(a, b, base01 + r01, base10 + r10)
            r01, r10 = f01 - base01, f10 - base10
        return f01, f10

    def unwarp_still(self, flow: torch.Tensor) -> torch.Tensor:
        """`flow` (B,2,H,W) with the vectors shorter than `still_flow_px` set to zero (none when it is 0)."""
        if self.still_flow_px <= 0:
            return flow
        return flow * (flow.norm(dim=1, keepdim=True) >= self.still_flow_px).to(flow.dtype)

    def forward(self, i0: torch.Tensor, i1: torch.Tensor, t: float = 0.5) -> torch.Tensor:
        """i0, i1 (B,3,H,W) in [0,1] -> the frame at time t."""
        f01, f10 = self.flows(i0, i1)
        ft0, ft1 = (self.unwarp_still(f) for f in flow_reversal(f01, f10, t))
        return self.synthesis(i0, i1, backward_warp(i0, ft0), backward_warp(i1, ft1), ft0, ft1, t)


def save_interpolator(path: Path, model: XVFILite, iterations: int) -> None:
    """Weights only (tensors and plain values), written atomically."""
    from avatarlab.runtime.io import atomic_path

    with atomic_path(Path(path)) as tmp:
        torch.save({"format": MODEL_FORMAT, "width": model.width, "scales": model.scales, "flow_init": model.flow_init,
                    "keep_unwarped": model.keep_unwarped, "still_flow_px": model.still_flow_px, "iterations": iterations,
                    "state": {k: v.cpu() for k, v in model.state_dict().items()}}, tmp)


def load_interpolator(path: str | Path, device: torch.device | str = "cpu") -> XVFILite:
    """A model.pt written by save_interpolator -> the network in eval mode; anything else stops with one line."""
    from avatarlab.runtime.safe_load import load_tensors

    content = load_tensors(Path(path), "a frame interpolator (model.pt)")
    if not isinstance(content, dict) or content.get("format") != MODEL_FORMAT:
        raise ValueError(f"{path}: not an avatarlab frame interpolator (expected format {MODEL_FORMAT})")
    model = XVFILite(int(content["width"]), int(content["scales"]), str(content.get("flow_init", "zero")),
                     bool(content.get("keep_unwarped", False)), float(content.get("still_flow_px", 0.0)))
    model.load_state_dict(content["state"])
    return model.eval().to(device)
