"""Training loss of the parametric head model (seed 002, eq. 8).

L = w1 |(I_gt - I_pred) * mask|^2 / sum(mask) + w2 sum_j |phi_j(I_gt) - phi_j(I_pred)|^2 + sum_k w_k |v_k^offset|^2,
k in {beta, theta, psi, tau, lambda}: learnable per-sample offsets of the fitted vectors (w_k = 0 for synthetic
samples). phi_j are VGG16 feature maps when ImageNet weights are given by path; otherwise a documented stand-in
(fixed random multi-scale convolutions - a texture/edge-sensitive feature loss, NOT VGG) is used and a warning says so.
Not in the dissertation, and off unless asked for (`finetune.w_st_lpips` > 0): one more term, the ST-LPIPS
distance (AlexNet; its weights ship in the stlpips-pytorch wheel) - a learned perceptual metric that needs no
download, but is also one of the evaluation's metrics, so identity similarity and landmark error stand beside it.
"""
from __future__ import annotations

import logging
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

log = logging.getLogger(__name__)
VGG_LAYERS = (3, 8, 15, 22)  # relu1_2, relu2_2, relu3_3, relu4_3
_MEAN = torch.tensor([0.485, 0.456, 0.406])[None, :, None, None]
_STD = torch.tensor([0.229, 0.224, 0.225])[None, :, None, None]


class FeatureDistance(nn.Module):
    """Eq. (8)'s perceptual term over feature maps phi_j: sum_j mean |phi_j(target) - phi_j(pred)|^2."""

    def distance(self, pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        return sum(((a - b) ** 2).mean() for a, b in zip(self(target), self(pred)))


class VGGFeatures(FeatureDistance):
    def __init__(self, weights_path: str | Path):
        super().__init__()
        from torchvision.models import vgg16

        path = Path(weights_path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: VGG16 ImageNet weights not found")
        net = vgg16()
        net.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
        self.features = net.features[: max(VGG_LAYERS) + 1].eval()
        for p in self.parameters():
            p.requires_grad_(False)
        self.name = f"vgg16:{path.name}"

    def forward(self, x):
        x = (x - _MEAN.to(x)) / _STD.to(x)
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in VGG_LAYERS:
                out.append(x)
        return out


class RandomConvFeatures(FeatureDistance):
    """Stand-in for VGG when no ImageNet weights are given: fixed, seeded random conv pyramid (not a learned metric)."""

    def __init__(self, seed: int = 0):
        super().__init__()
        g = torch.Generator().manual_seed(seed)
        chans = [3, 8, 16, 32]
        self.convs = nn.ModuleList()
        for cin, cout in zip(chans[:-1], chans[1:]):
            conv = nn.Conv2d(cin, cout, 3, padding=1)
            with torch.no_grad():
                conv.weight.copy_(torch.randn(conv.weight.shape, generator=g) / (cin * 9) ** 0.5)
                conv.bias.zero_()
            self.convs.append(conv)
        for p in self.parameters():
            p.requires_grad_(False)
        self.name = "random-conv stand-in (no VGG weights given)"

    def forward(self, x):
        out = []
        for i, conv in enumerate(self.convs):
            x = F.relu(conv(x if i == 0 else F.avg_pool2d(x, 2)))
            out.append(x)
        return out


def head_patches(mask: torch.Tensor, size: int, generator=None) -> torch.Tensor:
    """One square window of `size` pixels per sample of `mask` (B, 1, H, W), centred on a pixel drawn from the mask
    (uniformly where it is empty) and moved inside the image -> (row, column) offsets (B, 2)."""
    b, _, h, w = mask.shape
    weights = mask.reshape(b, -1).float() + 1e-6
    flat = torch.multinomial(weights, 1, generator=generator)[:, 0]
    rows = (flat // w - size // 2).clamp(0, h - size)
    cols = (flat % w - size // 2).clamp(0, w - size)
    return torch.stack([rows, cols], 1)


def crop_at(images: torch.Tensor, corners: torch.Tensor, size: int) -> torch.Tensor:
    return torch.stack([img[:, r:r + size, c:c + size] for img, (r, c) in zip(images, corners.tolist())])


def perceptual_network(vgg_weights: str | None) -> nn.Module:
    """Eq. (8)'s feature maps: VGG16 (the dissertation's) when `vgg_weights` is given, else the random-conv stand-in."""
    if vgg_weights:
        net = VGGFeatures(vgg_weights)
        log.info("perceptual loss: VGG16 from %s", vgg_weights)
        return net
    log.warning("perceptual loss: no VGG16 weights given (model.vgg16_weights); using a fixed random-conv stand-in")
    return RandomConvFeatures()


def composite(images: torch.Tensor, masks: torch.Tensor, background: float = 0.5) -> torch.Tensor:
    """The head (mask) over a flat grey background: what the model is trained on and scored against."""
    return images * masks + background * (1 - masks)


def head_model_loss(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, features: nn.Module,
                    offsets: dict[str, torch.Tensor], offset_weights: dict[str, float], is_real: torch.Tensor,
                    w_mse: float = 1.0, w_perceptual: float = 0.1) -> dict[str, torch.Tensor]:
    """Eq. (8). pred/target (B,3,H,W), mask (B,1,H,W), offsets name -> (B, dim), is_real (B,) bool."""
    terms = {"mse": w_mse * (((target - pred) * mask) ** 2).sum() / (3 * mask.sum()).clamp(min=1)}
    terms["perceptual"] = w_perceptual * features.distance(pred, target, mask)
    real = is_real.float()
    terms["offsets"] = sum(offset_weights.get(k, 0.0) * ((v**2).sum(-1) * real).sum() / real.sum().clamp(min=1)
                           for k, v in offsets.items()) if offsets else torch.zeros((), device=pred.device)
    terms["total"] = terms["mse"] + terms["perceptual"] + terms["offsets"]
    return terms
