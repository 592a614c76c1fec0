"""Preprocessed subjects written the way the preprocessing steps write them, for tests of later stages."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from avatarlab.render import orbit_camera


def fake_real_set(folder: Path, count: int = 4, size: int = 64, seed: int = 0, clips: list[int] | None = None):
    """An image subject: random frames, full masks and a neutral per-image fit (one row per image)."""
    (folder / "frames").mkdir(parents=True)
    rng = np.random.default_rng(seed)
    names = []
    for i in range(count):
        Image.fromarray((rng.random((size, size, 3)) * 255).astype(np.uint8)).save(folder / "frames" / f"{i:06d}.png")
        names.append(f"{i:06d}.png")
    sources = [f"clip{c}.mp4" for c in clips] if clips is not None else ["images"] * count
    (folder / "frames.json").write_text(json.dumps({"files": names, "count": count, "size": size,
                                                    "sources": sources}))
    np.savez(folder / "masks.npz", masks=np.ones((count, size, size), np.uint8))
    cam = orbit_camera(1.0, 0.0, 0.0, image_size=(size, size), batch=count)
    lighting = np.zeros((count, 9, 3), np.float32)
    lighting[:, 0] = 2.8
    np.savez(folder / "fit_rgb.npz", shape=np.zeros((count, 100), np.float32),
             texture=np.zeros((count, 50), np.float32), lighting=lighting,
             expression=rng.normal(0, 0.5, (count, 50)).astype(np.float32), pose=np.zeros((count, 15), np.float32),
             K=cam.K.numpy(), R=cam.R.numpy(), t=cam.t.numpy(), fitted=np.ones(count, bool), image_size=size)
    points = np.tile(np.stack(np.meshgrid(np.linspace(20, 44, 17), np.linspace(20, 44, 4)), -1).reshape(-1, 2)[:68],
                     (count, 1, 1))
    np.savez(folder / "landmarks.npz", points=points * size / 64, found=np.ones(count, bool))
    return folder


def fake_video_subject(folder: Path, count: int = 12, size: int = 64, clips: list[int] | None = None):
    """A video subject: like an image set, but one shared identity (shape, texture, lighting) as a video fit has."""
    fake_real_set(folder, count, size, clips=clips)
    with np.load(folder / "fit_rgb.npz") as f:
        fit = {k: f[k] for k in f.files}
    for key in ("shape", "texture", "lighting"):
        fit[key] = fit[key][0]
    np.savez(folder / "fit_rgb.npz", **fit)
    return folder


def tiny_model_overrides() -> list[str]:
    """A very small head model network (fast tests)."""
    return ["scale=smoke", "tracking.enabled=false", "model.width=16", "model.depth=2", "model.skip_layer=1",
            "model.feature_channels=8", "model.samples=4", "model.frequencies=2"]


def torch_equal(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    return all(torch.equal(p, q) for p, q in zip(a.state_dict().values(), b.state_dict().values()))


def rendered_video_subject(folder: Path, frames: int = 48, size: int = 32, preset: str = "talking", seed: int = 1):
    """A video subject as preprocessing would leave it, from a synthetic video of the head model with its truth as the
    fit (frames, masks, landmarks and parameters agree exactly): data a model can learn from."""
    from avatarlab.preprocess import synthetic_subject
    from helpers.config import step_cfg

    cfg = step_cfg(synthetic_subject, ["scale=smoke", f"subject.frames={frames}", f"subject.video_size={size}",
                                       f"subject.preset={preset}", f"subject.seed={seed}"])
    truth = synthetic_subject.render_subject(cfg)
    (folder / "frames").mkdir(parents=True)
    names = [f"{i:06d}.png" for i in range(frames)]
    for name, image in zip(names, truth["video"]):
        Image.fromarray(image).save(folder / "frames" / name)
    (folder / "frames.json").write_text(json.dumps({"files": names, "count": frames, "size": size,
                                                    "sources": ["video.mp4"] * frames}))
    np.savez(folder / "masks.npz", masks=truth["masks"])
    np.savez(folder / "fit_rgb.npz", shape=truth["shape"], texture=truth["texture"], lighting=truth["lighting"],
             expression=truth["expression"], pose=truth["pose"], K=truth["K"], R=truth["R"], t=truth["t"],
             fitted=np.ones(frames, bool), image_size=size)
    np.savez(folder / "landmarks.npz", points=truth["landmarks2d"], found=np.ones(frames, bool))
    return folder
