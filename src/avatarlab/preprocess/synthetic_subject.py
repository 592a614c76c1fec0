"""Synthetic "videos" of the head model with known ground truth (the embedded default subjects).

A subject has one identity (shape, texture, lighting, camera) and per-frame expression and pose following a preset:
`talking` (jaw and lips move, blinks, small head motion) or `head_turns` (a yaw sweep while talking). The frames are
encoded to an MP4 with OpenCV, exactly as a real recording would arrive, and the truth (parameters, camera,
landmarks, masks, depth) goes beside it so every later step can be checked against it.
`python -m avatarlab.preprocess.synthetic_subject subject.name=synth_talk subject.preset=talking`
"""
from __future__ import annotations

import logging

import numpy as np
import torch
from omegaconf import DictConfig

from avatarlab.headmodel import load_head_model
from avatarlab.render.camera import orbit_camera
from avatarlab.render.head_renderer import HeadRenderer
from avatarlab.render.lighting import default_lighting
from avatarlab.runtime.config import CPU
from avatarlab.runtime.entry import entry_point
from avatarlab.runtime.io import atomic_path, write_video

log = logging.getLogger(__name__)
READS = ('seed', 'head_model', 'render', 'subject')  # the config sections this step reads (runtime/entry.py)
PRESETS = ("talking", "head_turns")


def motion(preset: str, frames: int, fps: float, n_expr: int, rng: np.random.Generator):
    """Per-frame expression (F, E) and pose (F, 15) for a preset; smooth, deterministic given rng."""
    t = np.arange(frames) / fps
    expr = np.zeros((frames, n_expr))
    pose = np.zeros((frames, 15))
    # speech-like jaw: syllables at ~4 Hz with a slow envelope, never negative (closed mouth at 0)
    syllables = np.clip(np.sin(2 * np.pi * 4.0 * t + rng.uniform(0, 6)), 0, None)
    envelope = 0.5 + 0.5 * np.sin(2 * np.pi * 0.35 * t + rng.uniform(0, 6))
    pose[:, 6] = 0.22 * syllables * envelope
    for k in range(min(n_expr, 8)):  # slow expression drift in the leading components
        phase, freq = rng.uniform(0, 2 * np.pi), rng.uniform(0.2, 0.8)
        expr[:, k] = 0.8 * np.sin(2 * np.pi * freq * t + phase)
    pose[:, 3] = 0.05 * np.sin(2 * np.pi * 0.3 * t + rng.uniform(0, 6))  # nod
    pose[:, 4] = 0.08 * np.sin(2 * np.pi * 0.2 * t + rng.uniform(0, 6))  # small turn
    if preset == "head_turns":
        pose[:, 4] = 0.9 * np.sin(2 * np.pi * t / max(t[-1], 1e-6))  # one full sweep of about +-50 degrees
    elif preset != "talking":
        raise ValueError(f"subject.preset must be one of {PRESETS}, got {preset!r}")
    gaze = 0.15 * np.sin(2 * np.pi * 0.25 * t)
    pose[:, 10] = pose[:, 13] = gaze
    return expr.astype(np.float32), pose.astype(np.float32)


def blink_weights(frames: int, fps: float, rng: np.random.Generator) -> np.ndarray:
    """0..1 eyelid closure: a blink (~150 ms) every 2-4 s."""
    closure = np.zeros(frames)
    time = rng.uniform(0.3, 1.0)
    while time * fps < frames:
        centre = time * fps
        idx = np.arange(frames)
        closure = np.maximum(closure, np.exp(-0.5 * ((idx - centre) / (0.05 * fps)) ** 2))
        time += rng.uniform(2.0, 4.0)
    return closure


def _eyelid_response(model) -> np.ndarray:
    """Per expression component: signed forward motion of the eyelid-opening region (upper-lid landmarks)."""
    lm_faces = model.buffers_.faces[model.buffers_.lmk_faces_idx[[37, 38, 43, 44, 40, 41, 46, 47]]].reshape(-1)
    dirs = model.buffers_.exprdirs[lm_faces, :, : model.n_expression]  # (k, 3, E)
    near_eyes = dirs.norm(dim=1).mean(0)
    overall = model.buffers_.exprdirs[..., : model.n_expression].norm(dim=1).mean(0) + 1e-12
    return (near_eyes / overall * torch.sign(dirs[:, 2].mean(0))).numpy()


def eyelid_component(model) -> int:
    """The expression component that acts most on the eyelids (the blink), found from the bases themselves."""
    return int(np.argmax(np.abs(_eyelid_response(model))))


@torch.no_grad()
def render_subject(cfg: DictConfig, device: torch.device = CPU) -> dict:
    """The subject's frames and truth; the head renders on `device` (the random draws are on the CPU)."""
    sub = cfg.subject
    model = load_head_model(cfg.head_model)
    rng = np.random.default_rng(int(sub.seed))
    frames, fps, size = int(sub.frames), float(sub.fps), int(sub.video_size)
    expr, pose = motion(sub.preset, frames, fps, model.n_expression, rng)
    blink = eyelid_component(model)
    expr[:, blink] += 2.0 * np.sign(_eyelid_response(model)[blink]) * blink_weights(frames, fps, rng)
    shape = np.clip(rng.normal(0, float(sub.identity_std), model.n_shape), -2, 2).astype(np.float32)
    texture = np.clip(rng.normal(0, float(sub.identity_std), model.n_texture), -2, 2).astype(np.float32)
    lighting = default_lighting(1)[0].numpy()
    lighting[1:4] += rng.normal(0, 0.08, (3, 3))
    params = {"shape": torch.from_numpy(np.tile(shape, (frames, 1))), "expression": torch.from_numpy(expr),
              "pose": torch.from_numpy(pose), "texture": torch.from_numpy(np.tile(texture, (frames, 1)))}
    camera = orbit_camera(float(sub.camera_distance), float(sub.camera_yaw), float(sub.camera_pitch),
                          target=(0.0, -0.01, 0.0), image_size=(size, size), batch=frames,
                          fov_height=float(sub.fov_height))
    model.to(device)
    renderer = HeadRenderer(model, background=tuple(sub.background), backface_shade=float(cfg.render.backface_shade))
    light = torch.from_numpy(lighting)[None].expand(frames, -1, -1)
    rgb, masks, depth, lms = [], [], [], []
    for start in range(0, frames, 16):
        s = slice(start, start + 16)
        cam = type(camera)(K=camera.K[s], R=camera.R[s], t=camera.t[s], image_size=camera.image_size).to(device)
        out = renderer({k: v[s].to(device) for k, v in params.items()}, cam, light[s].to(device))
        rgb.append(out.rgb.cpu())
        masks.append(out.mask.cpu())
        depth.append(out.depth.cpu())
        lms.append(out.landmarks2d.cpu())
    rgb = torch.cat(rgb).permute(0, 2, 3, 1).numpy()
    noise = rng.normal(0, float(sub.image_noise), rgb.shape)
    video = (np.clip(rgb + noise, 0, 1) * 255).round().astype(np.uint8)
    return {
        "video": video, "fps": fps, "shape": shape, "texture": texture, "lighting": lighting,
        "expression": expr, "pose": pose, "K": camera.K.numpy(), "R": camera.R.numpy(), "t": camera.t.numpy(),
        "landmarks2d": torch.cat(lms).numpy(), "masks": torch.cat(masks)[:, 0].numpy().astype(np.uint8),
        "depth": torch.cat(depth)[:, 0].numpy().astype(np.float32), "head_model": model.source,
    }


@entry_point(READS)
def main(cfg, device) -> None:
    result = render_subject(cfg, device)
    write_video(cfg.subject.video_out, result.pop("video"), result["fps"])
    with atomic_path(cfg.subject.truth_out) as tmp:
        np.savez_compressed(tmp, **result)
    log.info("synthetic subject %s (%s): %d frames at %dx%d, %.0f fps -> %s", cfg.subject.name, cfg.subject.preset,
             len(result["pose"]), cfg.subject.video_size, cfg.subject.video_size, result["fps"], cfg.subject.video_out)


if __name__ == "__main__":
    main()
