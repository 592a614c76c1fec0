"""Image metrics: PSNR, SSIM (kornia), ST-LPIPS and LPIPS (learned perceptual distances), and face metrics (dlib).

- ST-LPIPS (Ghildyal & Liu, ECCV 2022, "Shift-tolerant perceptual similarity"; AlexNet backbone + linear layers,
  BSD-2) ships its trained weights inside the stlpips-pytorch wheel, so it works out of the box. Reported as
  `st_lpips`, never as LPIPS.
- LPIPS (Zhang et al. 2018, VGG) needs the ImageNet VGG16 backbone given by path (a torchvision state dict); without
  it LPIPS is reported missing (None), never made up.
- Face metrics: dlib's HOG detector finds the face (detection rate), its 68 landmarks give the NME against the ground
  truth's landmarks (normalised by the outer-eye distance, points 36 and 45), and dlib's face-recognition network
  the identity similarity (cosine of the 128-d descriptors). All run here without downloads.
"""
from __future__ import annotations

import importlib.util
import logging
from functools import lru_cache
from pathlib import Path

import kornia
import numpy as np
import torch

from avatarlab.model.losses import crop_at, head_patches
from avatarlab.runtime.config import CPU
from avatarlab.runtime.safe_load import load_tensors

log = logging.getLogger(__name__)


def psnr_per_image(pred: torch.Tensor, target: torch.Tensor, max_value: float | None = None) -> torch.Tensor:
    """Eq. (10) for each image: 10 log10(MAX(I_GT)^2 / MSE), MAX the ground truth's largest value (`max_value` fixes
    it instead). pred, target (B, C, H, W) in [0, 1] -> (B,)."""
    pred, target = pred.clamp(0, 1), target.reshape(-1, *target.shape[-3:])
    pred = pred.reshape(target.shape)
    mse = ((pred - target) ** 2).flatten(1).mean(1).clamp(min=1e-12)
    peak = target.flatten(1).amax(1) if max_value is None else torch.full_like(mse, max_value)
    return 10 * torch.log10(peak**2 / mse)


def psnr(pred: torch.Tensor, target: torch.Tensor, max_value: float | None = None) -> float:
    """Eq. (10) per image, averaged over the images (`psnr_per_image`)."""
    return float(psnr_per_image(pred, target, max_value).mean())


def ssim(pred: torch.Tensor, target: torch.Tensor, window: int = 11) -> float:
    """Mean SSIM over the image (the window mean, as in the INSTA protocol)."""
    return float(kornia.metrics.ssim(pred.clamp(0, 1), target, window).mean())


def psnr_in_mask(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> float:
    """PSNR over the head region only (mask > 0), MAX = 1."""
    mse = (((pred - target) ** 2) * mask).sum() / (pred.shape[1] * mask.sum()).clamp(min=1)
    return float(-10 * torch.log10(mse.clamp(min=1e-12)))


def colour_matched(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """`pred` with each image's mean colour inside the mask moved to the target's (per channel, outside unchanged):
    what is left of the error once a recording's overall colour (white balance, exposure) is given."""
    weight = mask.float()
    count = weight.sum((2, 3), keepdim=True).clamp(min=1)
    shift = ((target - pred) * weight).sum((2, 3), keepdim=True) / count
    return (pred + shift * weight).clamp(0, 1)


def psnr_colour_matched(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> float:
    """Head-region PSNR after `colour_matched`: the structure of a prediction, whatever its overall colour."""
    return psnr_in_mask(colour_matched(pred, target, mask), target, mask)


ST_LPIPS_NETS = {"alex": "AlexNet", "vgg": "VGG16"}


class STLPIPS:
    """Shift-tolerant LPIPS with the weights of the stlpips-pytorch wheel (read with weights_only=True and checked to
    cover every layer). Lower is more similar; inputs in [0, 1]. `net`: alex (the metric every table reports) or
    vgg (its VGG16 variant, whose backbone and calibration the wheel also ships; a training term only)."""

    def __init__(self, device: torch.device = CPU, net: str = "alex"):
        from stlpips_pytorch import stlpips

        if net not in ST_LPIPS_NETS:
            raise ValueError(f"ST-LPIPS network must be one of {sorted(ST_LPIPS_NETS)}, got {net!r}")
        root = Path(list(importlib.util.find_spec("stlpips_pytorch").submodule_search_locations)[0])
        weights = root / "weights" / "vST0.0" / f"{net}_shift_tolerant.pth"
        self.name = f"ST-LPIPS ({ST_LPIPS_NETS[net]}, shift-tolerant; Ghildyal & Liu 2022)"
        self.model = stlpips.LPIPS(net=net, variant="shift_tolerant", pretrained=False, verbose=False)
        result = self.model.load_state_dict(load_tensors(weights, "ST-LPIPS weights"), strict=False)
        # `lins.k` are the same modules as `link` (two names in the state dict, one in the file)
        missing = [k for k in result.missing_keys if not k.startswith("lins.")]
        if missing or result.unexpected_keys:
            raise RuntimeError(f"{weights}: does not fit the ST-LPIPS network ({missing or result.unexpected_keys})")
        self.model.eval().to(device)
        for p in self.model.parameters():
            p.requires_grad_(False)
        self.device = device

    @torch.no_grad()
    def per_image(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        pred, target = pred.to(self.device).clamp(0, 1), target.to(self.device)
        return self.model(pred, target, normalize=True).reshape(-1).cpu()

    def __call__(self, pred: torch.Tensor, target: torch.Tensor) -> float:
        return float(self.per_image(pred, target).mean())


class STLPIPSDistance(torch.nn.Module):
    """The perceptual term as the ST-LPIPS distance (shift-tolerant; `net` alex or vgg, the weights of the
    stlpips-pytorch wheel, frozen): the batch's mean distance between the render and the target, inputs in [0, 1].
    `crop` > 0: on one `crop`-pixel window per sample, centred on a random head pixel (LPIPS was trained on 64-pixel
    patches; a 64-pixel window of a 128-pixel image costs about a quarter)."""

    def __init__(self, crop: int = 0, net: str = "alex"):
        super().__init__()
        with torch.random.fork_rng(devices=[]):  # building the network draws random weights: leave the run's stream
            self.model = STLPIPS(net=net).model
        self.crop = int(crop)
        self.net = net
        self.name = (f"ST-LPIPS {ST_LPIPS_NETS[net]} (stlpips-pytorch wheel)"
                     + (f", {self.crop}-pixel head windows" if crop else ""))

    def distance(self, pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        if 0 < self.crop < min(pred.shape[-2:]):
            corners = head_patches(torch.ones_like(pred[:, :1]) if mask is None else mask, self.crop)
            pred, target = crop_at(pred, corners, self.crop), crop_at(target, corners, self.crop)
        return self.model(pred, target, normalize=True).mean()


class LPIPS:
    """LPIPS (Zhang et al. 2018, VGG variant) with the backbone loaded from a local torchvision state dict."""

    name = "LPIPS (VGG; Zhang et al. 2018)"

    def __init__(self, backbone_path: str | Path, device: torch.device = CPU):
        import lpips
        from torchvision.models import vgg16

        path = Path(backbone_path)
        self.model = lpips.LPIPS(net="vgg", pretrained=True, pnet_rand=True, verbose=False).eval()
        vgg = vgg16()
        vgg.load_state_dict(load_tensors(path, "VGG16 ImageNet weights for LPIPS"))
        load_backbone(self.model, vgg.features)
        self.model.to(device)
        self.device = device

    @torch.no_grad()
    def per_image(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        pred, target = pred.to(self.device), target.to(self.device)
        return self.model(pred.clamp(0, 1) * 2 - 1, target * 2 - 1).reshape(-1).cpu()

    def __call__(self, pred: torch.Tensor, target: torch.Tensor) -> float:
        return float(self.per_image(pred, target).mean())


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
        log.warning("LPIPS (VGG): no VGG16 ImageNet weights given (evaluate.lpips_backbone): reported missing; "
                    "ST-LPIPS (AlexNet, weights shipped with stlpips-pytorch) is measured instead")
        return None
    return LPIPS(backbone_path, device)


@lru_cache(maxsize=1)
def _face_models():
    import dlib

    folder = Path(list(importlib.util.find_spec("face_recognition_models").submodule_search_locations)[0]) / "models"
    return (dlib.get_frontal_face_detector(), dlib.shape_predictor(str(folder / "shape_predictor_68_face_landmarks.dat")),
            dlib.face_recognition_model_v1(str(folder / "dlib_face_recognition_resnet_model_v1.dat")))


def find_face(image_rgb: np.ndarray, upsample: int = 1):
    """dlib's largest face in an RGB uint8 image: (box, 68 landmarks (68, 2)) or None."""
    detector, predictor, _ = _face_models()
    image = np.ascontiguousarray(image_rgb)
    boxes = detector(image, upsample)
    if not boxes:
        return None
    box = max(boxes, key=lambda b: b.width() * b.height())
    shape = predictor(image, box)
    return box, np.array([[p.x, p.y] for p in shape.parts()], dtype=np.float64)


def face_descriptor(image_rgb: np.ndarray, face=None) -> np.ndarray | None:
    """128-d dlib face descriptor of the largest face, or None."""
    face = face if face is not None else find_face(image_rgb)
    if face is None:
        return None

    _, predictor, encoder = _face_models()
    image = np.ascontiguousarray(image_rgb)
    return np.array(encoder.compute_face_descriptor(image, predictor(image, face[0])))


def identity_similarity(pred_rgb: np.ndarray, target_rgb: np.ndarray) -> float | None:
    """Cosine similarity of the two faces' descriptors (None when a face is not found)."""
    a, b = face_descriptor(pred_rgb), face_descriptor(target_rgb)
    if a is None or b is None:
        return None
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))


def face_metrics(preds: np.ndarray, targets: np.ndarray, target_landmarks: np.ndarray | None = None,
                 target_cache: dict | None = None, identity: bool = True) -> dict:
    """Over a set of renders (N, H, W, 3) uint8 and their ground-truth frames: dlib's detection rate on the
    renders, the 68-point NME of the render's landmarks against the truth's (target_landmarks (N, 68, 2), NaN where
    unknown; default dlib on the target frames) normalised by the truth's outer-eye distance, and the identity
    similarity (unless identity=False). NME and identity average over the frames where both faces are found; None
    where there are none. `target_cache`: a dict shared by calls on the same targets (several predictors scored on
    the same frames), which keeps each target's face and descriptor."""
    cache = {} if target_cache is None else target_cache
    found, nmes, ids = 0, [], []
    for i, (pred, target) in enumerate(zip(preds, targets)):
        face = find_face(pred)
        if face is None:
            continue
        found += 1
        truth_face = None
        truth = None if target_landmarks is None else target_landmarks[i]
        if truth is None or not np.isfinite(truth).all():
            if ("face", i) not in cache:
                cache["face", i] = find_face(target)
            truth_face = cache["face", i]
            truth = None if truth_face is None else truth_face[1]
        if truth is not None:
            iod = np.linalg.norm(truth[36] - truth[45])
            nmes.append(float(np.linalg.norm(face[1] - truth, axis=1).mean() / max(iod, 1e-6)))
        if not identity:
            continue
        a = face_descriptor(pred, face)
        if ("descriptor", i) not in cache:
            cache["descriptor", i] = face_descriptor(target, truth_face)
        b = cache["descriptor", i]
        if a is not None and b is not None:
            ids.append(float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b))))
    n = len(preds)
    return {"face_detection_rate": found / n if n else None,
            "landmark_nme": float(np.mean(nmes)) if nmes else None,
            "identity_similarity": float(np.mean(ids)) if ids else None,
            "faces_compared": len(nmes)}
