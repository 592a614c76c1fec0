"""2D neural renderers: feature map -> image in three x2 stages (seed 002, section 3.1.2, figure 14).

Proposed stage: (1) an RGB branch - 1x1 conv of the stage's input to 3 channels, bilinear x2 (with the previous
stage's RGB, so the stages refine one image); (2) the upsampling block, a 1x1 conv and LeakyReLU -> features at twice
the resolution; (3) a 1x1 conv of those to 3 channels; (4) (1) + (3). The upsampling block: the input goes through two
separate Squeeze-and-Excitation blocks, one for each context branch; the global branch is dilated 3x3 convolutions
with LeakyReLU, the local branch 1x1 convolutions with LeakyReLU; their sum is pixel-shuffled (x2) and blurred.
The dissertation gives no channel widths: each branch's first conv keeps the input width and its second makes the
4 x output width that PixelShuffle turns into the output width; widths halve per stage down to `min_channels`.

Baseline (HeadNeRF, Hong et al. 2022): the RGB starts from the input feature map (1x1 conv, bilinear x2 + blur); per
stage conv1x1 C->2C + LeakyReLU, conv1x1 2C->4C + LeakyReLU, + the input repeated x4, PixelShuffle, blur, conv1x1 ->
max(C/2, min) + LeakyReLU, 1x1 conv to RGB added to the RGB, which is upsampled (bilinear + blur) between stages.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from kornia.filters import filter2d
from torch import nn


def _lrelu() -> nn.Module:
    return nn.LeakyReLU(0.2, inplace=True)


class Blur(nn.Module):
    """The [1, 2, 1] x [1, 2, 1] smoothing filter (normalised)."""

    def __init__(self):
        super().__init__()
        k = torch.tensor([1.0, 2.0, 1.0])
        self.register_buffer("kernel", (k[:, None] * k[None, :])[None])

    def forward(self, x):
        return filter2d(x, self.kernel.to(x.dtype), normalized=True)


class SqueezeExcite(nn.Module):
    def __init__(self, channels: int, reduction: int = 4):
        super().__init__()
        hidden = max(channels // reduction, 4)
        self.fc = nn.Sequential(nn.Linear(channels, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, channels),
                                nn.Sigmoid())

    def forward(self, x):
        return x * self.fc(x.mean((2, 3)))[:, :, None, None].to(x.dtype)


class UpsamplingBlock(nn.Module):
    """Proposed block: SE -> global context (dilated 3x3) and SE -> local context (1x1); sum; PixelShuffle(2); blur."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.se_global, self.se_local = SqueezeExcite(cin), SqueezeExcite(cin)
        self.global_branch = nn.Sequential(nn.Conv2d(cin, cin, 3, padding=2, dilation=2), _lrelu(),
                                           nn.Conv2d(cin, cout * 4, 3, padding=4, dilation=4), _lrelu())
        self.local_branch = nn.Sequential(nn.Conv2d(cin, cin, 1), _lrelu(), nn.Conv2d(cin, cout * 4, 1), _lrelu())
        self.shuffle = nn.PixelShuffle(2)
        self.blur = Blur()

    def forward(self, x):
        return self.blur(self.shuffle(self.global_branch(self.se_global(x)) + self.local_branch(self.se_local(x))))


class ProposedStage(nn.Module):
    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.rgb = nn.Conv2d(cin, 3, 1)
        self.up = UpsamplingBlock(cin, cout)
        self.post = nn.Sequential(nn.Conv2d(cout, cout, 1), _lrelu())
        self.to_rgb = nn.Conv2d(cout, 3, 1)

    def forward(self, x, rgb):
        skip = self.rgb(x) + (rgb if rgb is not None else 0)
        skip = F.interpolate(skip, scale_factor=2, mode="bilinear", align_corners=False)
        feat = self.post(self.up(x))
        return feat, skip + self.to_rgb(feat)


class BaselineStage(nn.Module):
    """HeadNeRF's PixelShuffle upsampling stage followed by its channel-reducing conv and the stage's RGB layer."""

    def __init__(self, cin: int, cout: int, last: bool):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, 2 * cin, 1)
        self.conv2 = nn.Conv2d(2 * cin, 4 * cin, 1)
        self.shuffle = nn.PixelShuffle(2)
        self.blur = Blur()
        self.reduce = nn.Conv2d(cin, cout, 1)
        self.to_rgb = nn.Conv2d(cout, 3, 1)
        self.last = last

    def forward(self, x, rgb):
        y = F.leaky_relu(self.conv2(F.leaky_relu(self.conv1(x), 0.2)), 0.2) + x.repeat(1, 4, 1, 1)
        feat = F.leaky_relu(self.reduce(self.blur(self.shuffle(y))), 0.2)
        rgb = rgb + self.to_rgb(feat)
        if not self.last:
            rgb = self.blur(F.interpolate(rgb, scale_factor=2, mode="bilinear", align_corners=False))
        return feat, rgb


class NeuralRenderer2D(nn.Module):
    """kind: 'proposed' | 'baseline'. (B, C, h, w) -> (B, 3, 8h, 8w) in [0, 1] (sigmoid of the summed RGB).
    Stage widths: C, then halving down to `min_channels` (HeadNeRF: 32)."""

    def __init__(self, in_channels: int, kind: str = "proposed", stages: int = 3, min_channels: int = 32):
        super().__init__()
        if kind not in ("proposed", "baseline"):
            raise ValueError(f"renderer kind must be 'proposed' or 'baseline', got {kind!r}")
        self.kind = kind
        chans = [in_channels]
        for _ in range(stages):
            chans.append(max(chans[-1] // 2, min_channels))
        if kind == "proposed":
            self.stages = nn.ModuleList(ProposedStage(chans[i], chans[i + 1]) for i in range(stages))
        else:
            self.input_rgb = nn.Conv2d(in_channels, 3, 1)
            self.blur = Blur()
            self.stages = nn.ModuleList(BaselineStage(chans[i], chans[i + 1], i == stages - 1) for i in range(stages))

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        x, rgb = features, None
        if self.kind == "baseline":
            rgb = self.blur(F.interpolate(self.input_rgb(x), scale_factor=2, mode="bilinear", align_corners=False))
        for stage in self.stages:
            x, rgb = stage(x, rgb)
        return torch.sigmoid(rgb)
