"""Does dlib see the head model as a face? Detection rate and NME of dlib's 68 points vs the model's landmarks.

Frontal renders of random heads (shape, expression, texture ~ N(0, std) clipped to [-2, 2]) go through the same
landmark detector as real video frames; the NME (mean point error over the outer-eye-corner distance) compares
dlib's points with the model's projected landmark embedding.
`python -m avatarlab.pretrain.dlib_check [overrides]`; writes a JSON report and an overlay PNG.
"""
from __future__ import annotations

import logging
import time

import numpy as np
import torch
from omegaconf import DictConfig

from avatarlab.headmodel import load_head_model
from avatarlab.headmodel.flame import clip_coefficients
from avatarlab.preprocess.landmarks import detect_landmarks, normalised_mean_error
from avatarlab.render.camera import orbit_camera
from avatarlab.render.head_renderer import HeadRenderer
from avatarlab.runtime.entry import entry_point
from avatarlab.runtime.io import write_json, write_png

log = logging.getLogger(__name__)
READS = ('seed', 'head_model', 'render', 'dlib_check')  # the config sections this step reads (runtime/entry.py)
LANDMARK_GROUPS = {"jaw": range(0, 17), "brows": range(17, 27), "nose": range(27, 36), "eyes": range(36, 48),
                   "mouth": range(48, 68)}


@torch.no_grad()
def render_random_heads(cfg: DictConfig, count: int, generator: torch.Generator):
    model = load_head_model(cfg.head_model)
    std = float(cfg.dlib_check.coefficient_std)
    params = model.zeros(count)
    for name in ("shape", "expression", "texture"):
        params[name] = clip_coefficients(torch.randn(params[name].shape, generator=generator) * std)
    size = int(cfg.dlib_check.image_size)
    camera = orbit_camera(float(cfg.dlib_check.camera_distance), 0.0, 0.0, image_size=(size, size), batch=count)
    out = HeadRenderer(model, background=tuple(cfg.render.background),
                       backface_shade=float(cfg.render.backface_shade))(params, camera)
    images = (out.rgb.permute(0, 2, 3, 1).clamp(0, 1).numpy() * 255).round().astype(np.uint8)
    return images, out.landmarks2d.numpy(), model.source


def evaluate(images: np.ndarray, truth: np.ndarray) -> dict:
    found, nmes, per_point, detections = 0, [], [], []
    for image, gt in zip(images, truth):
        det = detect_landmarks(image)
        detections.append(det)
        if det is None:
            continue
        found += 1
        nmes.append(normalised_mean_error(det.landmarks, gt))
        iod = np.linalg.norm(gt[36] - gt[45])
        per_point.append(np.linalg.norm(det.landmarks - gt, axis=1) / iod)
    per_point = np.array(per_point) if per_point else np.full((1, 68), np.nan)
    return {
        "renders": len(images), "detected": found, "detection_rate": found / max(len(images), 1),
        "nme_mean": float(np.mean(nmes)) if nmes else None, "nme_median": float(np.median(nmes)) if nmes else None,
        "nme_by_group": {g: float(np.nanmean(per_point[:, list(idx)])) for g, idx in LANDMARK_GROUPS.items()},
    }, detections


def overlay(images, truth, detections, count: int = 8) -> np.ndarray:
    """Model landmarks in green, dlib's in red, for the first `count` renders side by side."""
    tiles = []
    for image, gt, det in list(zip(images, truth, detections))[:count]:
        tile = image.copy()
        for pts, colour in ((gt, (0, 220, 0)), (None if det is None else det.landmarks, (230, 0, 0))):
            if pts is None:
                continue
            for x, y in np.round(pts).astype(int):
                tile[max(0, y - 1):y + 2, max(0, x - 1):x + 2] = colour
        tiles.append(tile)
    return np.concatenate(tiles, axis=1)


@entry_point(READS)
def main(cfg, device) -> None:
    generator = torch.Generator().manual_seed(int(cfg.seed))
    start = time.perf_counter()
    images, truth, source = render_random_heads(cfg, int(cfg.dlib_check.renders), generator)
    report, detections = evaluate(images, truth)
    report.update({
        "head_model": source, "image_size": int(cfg.dlib_check.image_size), "seed": int(cfg.seed),
        "coefficient_std": float(cfg.dlib_check.coefficient_std), "seconds": time.perf_counter() - start,
        "targets": {"min_detection_rate": cfg.dlib_check.min_detection_rate, "max_nme": cfg.dlib_check.max_nme},
    })
    report["meets_targets"] = bool(report["detection_rate"] >= cfg.dlib_check.min_detection_rate and
                                   report["nme_mean"] is not None and report["nme_mean"] <= cfg.dlib_check.max_nme)
    write_png(cfg.dlib_check.overlay, overlay(images, truth, detections))
    write_json(cfg.dlib_check.out, report)
    log.info("dlib on %d renders of %s: detected %.1f%%, NME %.4f (targets >= %.0f%%, <= %.2f): %s",
             report["renders"], source, 100 * report["detection_rate"], report["nme_mean"] or float("nan"),
             100 * cfg.dlib_check.min_detection_rate, cfg.dlib_check.max_nme,
             "met" if report["meets_targets"] else "NOT met")


if __name__ == "__main__":
    main()
