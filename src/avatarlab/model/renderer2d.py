"""2D neural renderers: feature map -> image, three x2 stages (seed 002, section 3.1.2).

Proposed: per stage an RGB branch (1x1 conv -> 3 channels, bilinear x2) plus an upsampling block - two SE blocks on
the input, a global-context branch (dilated 3x3 convs + LeakyReLU) and a local-context branch (1x1 convs + LeakyReLU)
summed, PixelShuffle(2), blur [1,2,1]x[1,2,1] - followed by 1x1 conv + LeakyReLU and 1x1 conv -> 3 channels; the
branches are summed. Baseline (HeadNeRF): conv1x1 C->2C, LeakyReLU(0.2), conv1x1 2C->4C, + the input repeated x4,
PixelShuffle, blur, conv1x1 -> max(C/2, 32), with an RGB skip per stage.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class Blur(nn.Module):
    def __init__(self):
        super().__init__()
        k = torch.tensor([1.0, 2.0, 1.0])
        self.register_buffer("kernel", (k[:, None] * k[None, :] / 16.0)[None, None])

    def forward(self, x):
        c = x.shape[1]
        return F.conv2d(F.pad(x, (1, 1, 1, 1), mode="replicate"), self.kernel.expand(c, 1, 3, 3), groups=c)


class SqueezeExcite(nn.Module):
    def __init__(self, channels: int, reduction: int = 4):
        super().__init__()
        self.fc = nn.Sequential(nn.Linear(channels, max(channels // reduction, 4)), nn.ReLU(inplace=True),
                                nn.Linear(max(channels // reduction, 4), channels), nn.Sigmoid())

    def forward(self, x):
        return x * self.fc(x.mean((2, 3)))[:, :, None, None]


class UpsamplingBlock(nn.Module):
    """Proposed block: SE x2; global (dilated 3x3) + local (1x1) context; PixelShuffle(2); blur."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.se = nn.Sequential(SqueezeExcite(cin), SqueezeExcite(cin))
        act = lambda: nn.LeakyReLU(0.2, inplace=True)  # noqa: E731
        self.global_branch = nn.Sequential(nn.Conv2d(cin, cout * 4, 3, padding=2, dilation=2), act(),
                                           nn.Conv2d(cout * 4, cout * 4, 3, padding=4, dilation=4), act())
        self.local_branch = nn.Sequential(nn.Conv2d(cin, cout * 4, 1), act(), nn.Conv2d(cout * 4, cout * 4, 1), act())
        self.shuffle = nn.PixelShuffle(2)
        self.blur = Blur()

    def forward(self, x):
        x = self.se(x)
        return self.blur(self.shuffle(self.global_branch(x) + self.local_branch(x)))


class ProposedStage(nn.Module):
    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.rgb = nn.Conv2d(cin, 3, 1)
        self.up = UpsamplingBlock(cin, cout)
        self.post = nn.Sequential(nn.Conv2d(cout, cout, 1), nn.LeakyReLU(0.2, inplace=True))
        self.to_rgb = nn.Conv2d(cout, 3, 1)

    def forward(self, x, rgb):
        skip = F.interpolate(self.rgb(x) + (rgb if rgb is not None else 0), scale_factor=2, mode="bilinear",
                             align_corners=False)
        feat = self.post(self.up(x))
        return feat, skip + self.to_rgb(feat)


class BaselineStage(nn.Module):
    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, 2 * cin, 1)
        self.conv2 = nn.Conv2d(2 * cin, 4 * cin, 1)
        self.shuffle = nn.PixelShuffle(2)
        self.blur = Blur()
        self.out = nn.Conv2d(cin, cout, 1)
        self.to_rgb = nn.Conv2d(cout, 3, 1)

    def forward(self, x, rgb):
        y = self.conv2(F.leaky_relu(self.conv1(x), 0.2)) + x.repeat(1, 4, 1, 1)
        feat = self.out(self.blur(self.shuffle(y)))
        skip = F.interpolate(rgb, scale_factor=2, mode="bilinear", align_corners=False) if rgb is not None else 0
        return feat, skip + self.to_rgb(feat)


class NeuralRenderer2D(nn.Module):
    """kind: 'proposed' | 'baseline'. (B, C, h, w) -> (B, 3, 8h, 8w) in [0, 1] (sigmoid of the summed RGB)."""

    def __init__(self, in_channels: int, kind: str = "proposed", stages: int = 3):
        super().__init__()
        if kind not in ("proposed", "baseline"):
            raise ValueError(f"renderer kind must be 'proposed' or 'baseline', got {kind!r}")
        self.kind = kind
        chans = [in_channels]
        for _ in range(stages):
            chans.append(max(chans[-1] // 2, 32))
        stage = ProposedStage if kind == "proposed" else BaselineStage
        self.stages = nn.ModuleList(stage(chans[i], chans[i + 1]) for i in range(stages))

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        x, rgb = features, None
        for stage in self.stages:
            x, rgb = stage(x, rgb)
        return torch.sigmoid(rgb)
