"""A finished avatar: its fine-tuned model from `model.pt`, the subject's fitted frames, and rendering of any
parameters and camera with it. Shared by the applications and speech animation."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from avatarlab.data.subject_dir import SubjectDir
from avatarlab.model.head_nerf import HeadNeRFModel, assemble_codes, load_model_file, render_in_chunks
from avatarlab.render.camera import Camera
from avatarlab.runtime.config import CPU

log = logging.getLogger(__name__)


@dataclass
class Avatar:
    net: HeadNeRFModel
    config: dict
    image_size: int

    @torch.no_grad()
    def render(self, params: dict, camera: Camera, batch: int = 4) -> torch.Tensor:
        """params: shape, expression, pose (B, 15), texture, lighting (B, 9, 3) -> images (B, 3, H, W) in [0, 1],
        rendered `batch` at a time on the net's device, returned on the CPU."""
        geometry, appearance = assemble_codes(params, params["lighting"])
        return render_in_chunks(self.net, geometry, appearance, camera, batch).clamp(0, 1)


def load_avatar(path: str | Path, device: torch.device = CPU) -> Avatar:
    net, content = load_model_file(path, device)
    return Avatar(net, content["config"], int(content["spec"]["feature_size"]) * 8)


def load_fit(subject_dir: str | Path, image_size: int) -> dict:
    """A subject's per-frame fit as tensors (shared vectors repeated per frame), K for `image_size`."""
    fit = SubjectDir(subject_dir).fit()
    K = torch.from_numpy(fit["K"]).float()
    K[:, :2] *= image_size / float(fit["image_size"])
    out = {k: torch.from_numpy(np.ascontiguousarray(fit[k])).float() for k in ("shape", "expression", "pose",
                                                                             "texture", "lighting", "R", "t")}
    out["K"], out["fitted"], out["image_size"] = K, torch.from_numpy(fit["fitted"]).bool(), image_size
    return out


def open_avatar(apps, device: torch.device = CPU) -> tuple[Avatar, dict]:
    """The avatar of an `apps` config section (on `device`) and its subject's fit at the avatar's image size."""
    avatar = load_avatar(apps.avatar, device)
    return avatar, load_fit(apps.subject_dir, avatar.image_size)


def select(fit: dict, idx) -> tuple[dict, Camera]:
    """The parameters and camera of frames `idx` of a fit."""
    idx = torch.as_tensor(idx, dtype=torch.long)
    params = {k: fit[k][idx] for k in ("shape", "expression", "pose", "texture", "lighting")}
    size = fit["image_size"]
    return params, Camera(K=fit["K"][idx], R=fit["R"][idx], t=fit["t"][idx], image_size=(size, size))


def orbit(camera: Camera, yaw_deg: float, pitch_deg: float = 0.0, dz: float = 0.0) -> Camera:
    """A novel view: the same camera moved on a sphere about the model's origin (the head) and `dz` further away."""
    angles = torch.tensor([[np.radians(pitch_deg), np.radians(yaw_deg), 0.0]], dtype=camera.R.dtype)
    rot = axis_angle_to_rotation_matrix(angles[:, :1] * torch.tensor([[1.0, 0, 0]])) @ axis_angle_to_rotation_matrix(
        angles[:, 1:2] * torch.tensor([[0, 1.0, 0]]))
    t = camera.t + torch.tensor([0.0, 0.0, dz], dtype=camera.t.dtype)
    return Camera(K=camera.K, R=camera.R @ rot, t=t, image_size=camera.image_size)


def to_uint8(images: torch.Tensor) -> np.ndarray:
    """(B, 3, H, W) in [0, 1] -> (B, H, W, 3) uint8."""
    return (images.permute(0, 2, 3, 1).clamp(0, 1).numpy() * 255).round().astype(np.uint8)
