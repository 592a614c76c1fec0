"""Image metrics of the avatars: PSNR, SSIM (kornia), LPIPS (the lpips package) and identity similarity (dlib).

LPIPS needs the ImageNet backbone: its VGG16 weights are given by path (a torchvision state dict); the lpips package
supplies its own linear calibration layers. Without the backbone, LPIPS is reported as missing (None), never made up.
Identity similarity is the cosine of dlib's face-recognition descriptors (face_recognition_models), a learned metric
that runs here without downloads.
"""
from __future__ import annotations

import logging
from functools import lru_cache
from pathlib import Path

import kornia
import numpy as np
import torch

from avatarlab.config import CPU

log = logging.getLogger(__name__)


def psnr(pred: torch.Tensor, target: torch.Tensor) -> float:
    return float(kornia.metrics.psnr(pred.clamp(0, 1), target, 1.0))


def ssim(pred: torch.Tensor, target: torch.Tensor, window: int = 11) -> float:
    """Mean SSIM over the image (the window mean, as in the INSTA protocol)."""
    return float(kornia.metrics.ssim(pred.clamp(0, 1), target, window).mean())


class LPIPS:
    """LPIPS (Zhang et al. 2018, VGG variant) with the backbone loaded from a local torchvision state dict."""

    def __init__(self, backbone_path: str | Path, device: torch.device = CPU):
        import lpips
        from torchvision.models import vgg16

        path = Path(backbone_path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: VGG16 ImageNet weights for LPIPS not found")
        self.model = lpips.LPIPS(net="vgg", pretrained=True, pnet_rand=True, verbose=False).eval()
        vgg = vgg16()
        vgg.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
        load_backbone(self.model, vgg.features)
        self.model.to(device)
        self.device = device
        self.name = f"lpips-vgg:{path.name}"

    @torch.no_grad()
    def __call__(self, pred: torch.Tensor, target: torch.Tensor) -> float:
        pred, target = pred.to(self.device), target.to(self.device)
        return float(self.model(pred.clamp(0, 1) * 2 - 1, target * 2 - 1).mean())


def load_backbone(lpips_model, vgg_features: torch.nn.Sequential) -> None:
    """Copy VGG16 `features` weights into the five slices of lpips' backbone (same layer indices)."""
    net = lpips_model.net
    for slice_ in (net.slice1, net.slice2, net.slice3, net.slice4, net.slice5):
        for name, layer in slice_.named_children():
            src = vgg_features[int(name)]
            if isinstance(layer, torch.nn.Conv2d):
                layer.weight.data.copy_(src.weight.data)
                layer.bias.data.copy_(src.bias.data)


def lpips_metric(backbone_path: str | None, device: torch.device = CPU):
    """An LPIPS callable (computed on `device`), or None (reported missing) when no backbone weights are given."""
    if not backbone_path:
        log.warning("LPIPS: no VGG16 ImageNet weights given (finetune.lpips_backbone): LPIPS is reported missing")
        return None
    return LPIPS(backbone_path, device)


@lru_cache(maxsize=1)
def _face_models():
    import importlib.util

    import dlib

    folder = Path(list(importlib.util.find_spec("face_recognition_models").submodule_search_locations)[0]) / "models"
    return (dlib.get_frontal_face_detector(), dlib.shape_predictor(str(folder / "shape_predictor_68_face_landmarks.dat")),
            dlib.face_recognition_model_v1(str(folder / "dlib_face_recognition_resnet_model_v1.dat")))


def face_descriptor(image_rgb: np.ndarray) -> np.ndarray | None:
    """128-d dlib face descriptor of the largest face, or None."""
    detector, predictor, encoder = _face_models()
    image = np.ascontiguousarray(image_rgb)
    boxes = detector(image, 1)
    if not boxes:
        return None
    box = max(boxes, key=lambda b: b.width() * b.height())
    return np.array(encoder.compute_face_descriptor(image, predictor(image, box)))


def identity_similarity(pred_rgb: np.ndarray, target_rgb: np.ndarray) -> float | None:
    """Cosine similarity of the two faces' descriptors (None when a face is not found)."""
    a, b = face_descriptor(pred_rgb), face_descriptor(target_rgb)
    if a is None or b is None:
        return None
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
