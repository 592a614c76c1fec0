"""Parameter-sweep grid of the head model, like figures 4-7 of the dissertation.

Rows: shape and expression components, jaw and neck rotations about x/y/z, eye gaze, texture components and camera
distance; columns: values across the meaningful range. `python -m avatarlab.pretrain.head_model_demo [overrides]`.
"""
from __future__ import annotations

import logging

import numpy as np
import torch
from omegaconf import DictConfig
from PIL import Image, ImageDraw

from avatarlab.headmodel import load_head_model
from avatarlab.render.camera import orbit_camera
from avatarlab.render.head_renderer import HeadRenderer
from avatarlab.runtime.config import CPU
from avatarlab.runtime.entry import entry_point
from avatarlab.runtime.io import write_png

log = logging.getLogger(__name__)
READS = ('seed', 'head_model', 'render', 'demo')  # the config sections this step reads (runtime/entry.py)


def sweep_rows(columns: int) -> list[tuple[str, str, int, np.ndarray]]:
    """(label, parameter, index, values): what each row varies."""
    coeff = np.linspace(-2, 2, columns)
    small = np.linspace(-0.25, 0.25, columns)
    return [
        ("shape 1", "shape", 0, coeff), ("shape 2", "shape", 1, coeff),
        ("expression 1", "expression", 0, coeff), ("expression 2", "expression", 1, coeff),
        ("expression 3", "expression", 2, np.linspace(0, 2, columns)),
        ("jaw x (open)", "pose", 6, np.linspace(0, 0.4, columns)), ("jaw y", "pose", 7, small),
        ("jaw z", "pose", 8, small),
        ("neck x", "pose", 3, np.linspace(-0.5, 0.5, columns)), ("neck y", "pose", 4, np.linspace(-0.8, 0.8, columns)),
        ("neck z", "pose", 5, np.linspace(-0.5, 0.5, columns)),
        ("eyes y (gaze)", "eyes", 10, np.linspace(-0.4, 0.4, columns)),
        ("texture 1", "texture", 0, coeff), ("texture 2", "texture", 1, coeff),
        ("distance (m)", "distance", 0, np.linspace(0.7, 1.5, columns)),
    ]


def build_batch(model, rows, columns: int, base_distance: float):
    batch = len(rows) * columns
    params = model.zeros(batch)
    distance = torch.full((batch,), base_distance)
    for r, (_, name, idx, values) in enumerate(rows):
        for c, value in enumerate(values):
            k = r * columns + c
            if name == "distance":
                distance[k] = float(value)
            elif name == "eyes":
                params["pose"][k, 10] = float(value)  # left eye, y axis
                params["pose"][k, 13] = float(value)  # right eye, y axis
            else:
                params[name][k, idx] = float(value)
    return params, distance


def label_grid(images: np.ndarray, rows, columns: int, label_width: int = 110) -> np.ndarray:
    """images (R*C, H, W, 3) uint8 -> one labelled grid image."""
    h, w = images.shape[1:3]
    canvas = Image.new("RGB", (label_width + columns * w, len(rows) * h + 16), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    for r, (label, _, _, values) in enumerate(rows):
        draw.text((4, r * h + h // 2 - 12), label, fill=(0, 0, 0))
        draw.text((4, r * h + h // 2 + 2), f"{values[0]:.2g} .. {values[-1]:.2g}", fill=(90, 90, 90))
        for c in range(columns):
            canvas.paste(Image.fromarray(images[r * columns + c]), (label_width + c * w, r * h))
    draw.text((4, len(rows) * h + 2), "avatarlab head model sweep", fill=(90, 90, 90))
    return np.asarray(canvas)


@torch.no_grad()
def render_sweep(cfg: DictConfig, device: torch.device = CPU) -> np.ndarray:
    model = load_head_model(cfg.head_model).to(device)
    size = int(cfg.demo.image_size)
    rows = sweep_rows(int(cfg.demo.columns))
    params, distance = build_batch(model, rows, int(cfg.demo.columns), float(cfg.demo.camera_distance))
    camera = orbit_camera(distance, 0.0, 0.0, focal=float(cfg.demo.camera_distance) * size / 0.32,
                          image_size=(size, size)).to(device)
    out = HeadRenderer(model, background=tuple(cfg.render.background),
                       backface_shade=float(cfg.render.backface_shade))(params, camera)
    images = (out.rgb.cpu().permute(0, 2, 3, 1).clamp(0, 1).numpy() * 255).round().astype(np.uint8)
    return label_grid(images, rows, int(cfg.demo.columns))


@entry_point(READS)
def main(cfg, device) -> None:
    grid = render_sweep(cfg, device)
    write_png(cfg.demo.out, grid)
    log.info("wrote %s (%dx%d)", cfg.demo.out, grid.shape[1], grid.shape[0])


if __name__ == "__main__":
    main()
