"""The embedded stand-in for FFHQ: a folder of varied portraits of the head model.

Each portrait has its own identity, expression, a small head pose, a hair cap coloured from a palette, a background
(flat or gradient), lighting and colour variety and sensor noise - appearance the synthetic training generator does not
have. The folder then goes through the same preprocessing and per-image RGB fit as real photographs would (a
subject with `source: portraits`). Replace it by real images with `source: images`.
"""
from __future__ import annotations

import itertools
import logging
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig
from PIL import Image

from avatarlab.headmodel import load_head_model
from avatarlab.headmodel.flame import clip_coefficients, vertices_to_landmarks
from avatarlab.headmodel.mouth import uv_coverage
from avatarlab.render.camera import orbit_camera
from avatarlab.render.head_renderer import HeadRenderer
from avatarlab.render.lighting import default_lighting
from avatarlab.runtime.config import CPU
from avatarlab.runtime.entry import entry_point
from avatarlab.runtime.io import atomic_path

log = logging.getLogger(__name__)
READS = ('seed', 'head_model', 'subject')  # the config sections this step reads (runtime/entry.py)
HAIR_COLOURS = np.array([[0.08, 0.06, 0.05], [0.25, 0.15, 0.08], [0.45, 0.3, 0.15], [0.75, 0.6, 0.35],
                         [0.5, 0.5, 0.5], [0.55, 0.2, 0.08]])


def hair_mask(model) -> torch.Tensor:
    """Scalp vertices (V,) bool: above the brows at the front of the head, above the nape at the back. The levels
    are placed from the template's own landmarks in units of its eye-to-chin height (so they fit FLAME 2020 as well
    as the procedural head, where they are the brows + 0.17, the eyes - 0.52 and the nose tip - 0.68 units)."""
    b = model.buffers_
    v = b.v_template
    landmarks = vertices_to_landmarks(v[None], b.faces, b.lmk_faces_idx, b.lmk_bary)[0]
    eye_y, brow_y = landmarks[36:48, 1].mean(), landmarks[17:27, 1].mean()
    unit = eye_y - landmarks[8, 1]
    front = v[:, 2] > landmarks[30, 2] - 0.68 * unit
    return model.regions["head"] & ((front & (v[:, 1] > brow_y + 0.17 * unit)) | (~front & (v[:, 1] > eye_y - 0.52 * unit)))


def hair_texels(model, hair: torch.Tensor) -> torch.Tensor:
    """For a UV texture: the texels (H, W) bool of the faces whose three vertices are all scalp vertices."""
    albedo = model.albedo_model
    faces = model.buffers_.faces.cpu()
    scalp = hair.cpu()[faces].all(1)
    return torch.from_numpy(uv_coverage(albedo.uv.cpu().numpy(), albedo.uv_faces.cpu().numpy()[scalp.numpy()],
                                        tuple(albedo.mean.shape[:2])))


@torch.no_grad()
def render_portraits(cfg: DictConfig, device: torch.device = CPU, chunk: int = 16):
    """The portraits' parameters, and a generator of their images (uint8 (n, H, W, 3), `chunk` at a time, so
    70000 portraits at 512² never sit in memory at once). The head renders on `device`; every random draw comes
    from one CPU generator, so the images do not depend on the device."""
    model = load_head_model(cfg.head_model)
    count, size = int(cfg.subject.portraits), int(cfg.subject.video_size)
    g = torch.Generator().manual_seed(int(cfg.seed) + 7)
    params = model.zeros(count)
    for name, std in (("shape", 1.0), ("expression", 0.7), ("texture", 1.0)):
        params[name] = clip_coefficients(torch.randn(params[name].shape, generator=g) * std)
    params["pose"][:, 3:6] = (torch.rand(count, 3, generator=g) - 0.5) * torch.tensor([0.4, 0.7, 0.3])
    params["pose"][:, 6] = torch.rand(count, generator=g) * 0.25
    lighting = default_lighting(count) * (0.8 + 0.4 * torch.rand(count, 1, 1, generator=g))
    lighting[:, 1:4] += (torch.rand(count, 3, 3, generator=g) - 0.5) * 0.6
    hair = hair_mask(model)
    if model.albedo_model.is_uv:  # the hair painted into the texture: its texels instead of its vertices
        hair = hair_texels(model, hair)
    colours = torch.from_numpy(HAIR_COLOURS).float()[torch.randint(0, len(HAIR_COLOURS), (count,), generator=g)]
    hair_shade = colours[:, None] * (0.85 + 0.3 * torch.rand(count, int(hair.sum()), 1, generator=g))
    camera = orbit_camera(1.0 + 0.1 * torch.randn(count, generator=g), 0.0, 0.0, target=(0.0, 0.0, 0.0),
                          image_size=(size, size), batch=count, fov_height=0.36)
    model.to(device)
    renderer = HeadRenderer(model, background=(0, 0, 0))

    def images():
        for start in range(0, count, chunk):
            s = slice(start, start + chunk)
            on = {k: v[s].to(device) for k, v in params.items()}
            albedo = model.albedo(on["texture"])
            if model.albedo_model.is_uv:  # (n, 3, H, W)
                albedo = albedo.permute(0, 2, 3, 1).clone()
                albedo[:, hair.to(device)] = hair_shade[s].to(device)
                albedo = albedo.permute(0, 3, 1, 2)
            else:  # (n, V, 3)
                albedo[:, hair.to(device)] = hair_shade[s].to(device)
            geo = model(on["shape"], on["expression"], on["pose"])
            cam = type(camera)(K=camera.K[s], R=camera.R[s], t=camera.t[s], image_size=camera.image_size).to(device)
            out = renderer.mesh_renderer(geo.vertices, albedo, cam, lighting[s].to(device))
            rgb, mask = out.rgb.cpu(), out.mask.cpu()
            n = rgb.shape[0]
            top, bottom = torch.rand(n, 3, 1, 1, generator=g), torch.rand(n, 3, 1, 1, generator=g)
            ramp = torch.linspace(0, 1, size)[None, None, :, None]
            background = top + (bottom - top) * ramp * (torch.rand(n, 1, 1, 1, generator=g) > 0.5)
            rgb = rgb * mask + background * (1 - mask)
            rgb = rgb + 0.015 * torch.randn(rgb.shape, generator=g)
            yield (rgb.clamp(0, 1).permute(0, 2, 3, 1).numpy() * 255).round().astype(np.uint8)

    return params, images(), model.source


@entry_point(READS)
def main(cfg, device) -> None:
    params, chunks, source = render_portraits(cfg, device)
    out_dir = Path(cfg.subject.images_out)
    out_dir.mkdir(parents=True, exist_ok=True)
    for i, image in enumerate(itertools.chain.from_iterable(chunks)):
        with atomic_path(out_dir / f"{i:05d}.png") as tmp:
            Image.fromarray(image).save(tmp, format="PNG")
    with atomic_path(cfg.subject.truth_out) as tmp:
        np.savez_compressed(tmp, **{k: v.numpy() for k, v in params.items()}, head_model=source)
    log.info("%d portraits (stand-in for FFHQ) at %dx%d in %s", i + 1, image.shape[1], image.shape[0], out_dir)


if __name__ == "__main__":
    main()
