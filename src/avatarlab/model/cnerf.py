"""CNeRF: a NeRF conditioned on FLAME's shape, pose and expression (density), and texture and lighting (features).

Per sample point: PE(xyz) + beta + theta + psi -> MLP (skip connection of the input) -> density sigma and a hidden
vector; hidden -> 1 FC -> + tau + lambda -> 2 FC -> feature v. No view direction (seed 002, 3.1.1).
Feature maps come from volume rendering (eq. 7) along rays through the pixels of a low-resolution feature map whose
intrinsics are the image's scaled by (h_feature / h_image, w_feature / w_image).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from avatarlab.render.camera import Camera


def positional_encoding(x: torch.Tensor, frequencies: int) -> torch.Tensor:
    """x (..., 3) -> (..., 3 + 6 * frequencies): x, sin(2^k pi x), cos(2^k pi x)."""
    scales = (2.0 ** torch.arange(frequencies, device=x.device, dtype=x.dtype)) * torch.pi
    angles = x[..., None] * scales  # (..., 3, F)
    return torch.cat([x, angles.sin().flatten(-2), angles.cos().flatten(-2)], -1)


@dataclass
class CNeRFConfig:
    frequencies: int = 10
    depth: int = 8
    width: int = 384
    skip_layer: int = 4
    feature_channels: int = 256
    samples: int = 64
    near: float = 0.75  # metres from the camera; the head sits at ~1 m
    far: float = 1.25
    coordinate_scale: float = 5.0  # world metres -> network units (the head spans about +-1)
    n_shape: int = 100
    n_expression: int = 50
    n_pose: int = 12  # neck, jaw, eyes (the root is the camera's business)
    n_texture: int = 50
    n_lighting: int = 27


class CNeRF(nn.Module):
    def __init__(self, cfg: CNeRFConfig):
        super().__init__()
        self.cfg = cfg
        pe_dim = 3 + 6 * cfg.frequencies
        cond = cfg.n_shape + cfg.n_pose + cfg.n_expression
        in_dim = pe_dim + cond
        layers = []
        for i in range(cfg.depth):
            d_in = in_dim if i == 0 else cfg.width + (in_dim if i == cfg.skip_layer else 0)
            layers.append(nn.Linear(d_in, cfg.width))
        self.layers = nn.ModuleList(layers)
        self.density = nn.Linear(cfg.width, 1)
        self.hidden = nn.Linear(cfg.width, cfg.width)
        self.appearance = nn.Sequential(nn.Linear(cfg.width + cfg.n_texture + cfg.n_lighting, cfg.width // 2),
                                        nn.ReLU(inplace=True), nn.Linear(cfg.width // 2, cfg.feature_channels))

    def forward(self, points: torch.Tensor, geometry_code: torch.Tensor, appearance_code: torch.Tensor):
        """points (B, P, 3) world; geometry_code (B, S+12+E); appearance_code (B, T+27) -> sigma (B,P), v (B,P,C)."""
        x_in = torch.cat([positional_encoding(points * self.cfg.coordinate_scale, self.cfg.frequencies),
                          geometry_code[:, None].expand(-1, points.shape[1], -1)], -1)
        h = x_in
        for i, layer in enumerate(self.layers):
            if i == self.cfg.skip_layer:
                h = torch.cat([h, x_in], -1)
            h = F.relu(layer(h))
        sigma = F.softplus(self.density(h).squeeze(-1) - 1.0)
        h = self.hidden(h)
        feature = self.appearance(torch.cat([h, appearance_code[:, None].expand(-1, points.shape[1], -1)], -1))
        return sigma, feature

    def frozen_prefix(self, count: int):
        """Parameters of the first `count` MLP layers (frozen during per-subject fine-tuning)."""
        return [p for layer in self.layers[:count] for p in layer.parameters()]


def camera_rays(camera: Camera, size: tuple[int, int]):
    """Rays through the pixel centres of a (h, w) map of `camera` (intrinsics scaled). -> origins, dirs (B,h*w,3)."""
    cam = camera.scaled(size)
    h, w = size
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    pix = torch.stack([xs + 0.5, ys + 0.5, torch.ones_like(xs)], -1).reshape(-1, 3).to(cam.K)
    dirs_cam = torch.einsum("bij,pj->bpi", torch.linalg.inv(cam.K), pix)  # z = 1 in camera coordinates
    R_t = cam.R.transpose(1, 2)
    dirs = torch.einsum("bij,bpj->bpi", R_t, dirs_cam)
    origins = (-torch.einsum("bij,bj->bi", R_t, cam.t))[:, None].expand_as(dirs)
    return origins, dirs


def volume_render_features(sigma: torch.Tensor, features: torch.Tensor, depths: torch.Tensor):
    """Eq. (7): FeatureMap(r) = sum_i T_i (1 - exp(-sigma_i delta_i)) v_i, T_i = exp(-sum_{j<i} sigma_j delta_j).

    sigma (B, R, N), features (B, R, N, C), depths (B, R, N) along the ray (camera z, since dirs have z = 1).
    Returns the feature map values (B, R, C) and the accumulated opacity (B, R).
    """
    delta = torch.cat([depths[..., 1:] - depths[..., :-1], torch.full_like(depths[..., :1], 1e3)], -1)
    alpha = 1.0 - torch.exp(-sigma * delta)
    transmittance = torch.cumprod(torch.cat([torch.ones_like(alpha[..., :1]), 1.0 - alpha + 1e-10], -1), -1)[..., :-1]
    weights = alpha * transmittance
    return (weights[..., None] * features).sum(-2), weights.sum(-1)


def render_feature_map(nerf: CNeRF, camera: Camera, size: tuple[int, int], geometry_code, appearance_code,
                       stratified: bool = True):
    """-> feature map (B, C, h, w) and opacity (B, 1, h, w)."""
    cfg = nerf.cfg
    origins, dirs = camera_rays(camera, size)
    b, r = dirs.shape[:2]
    t = torch.linspace(cfg.near, cfg.far, cfg.samples, device=dirs.device)
    t = t.expand(b, r, -1).clone()
    if stratified:
        t = t + (torch.rand_like(t) - 0.5) * (cfg.far - cfg.near) / cfg.samples
    points = origins[:, :, None] + dirs[:, :, None] * t[..., None]  # (B, R, N, 3)
    sigma, feat = nerf(points.reshape(b, -1, 3), geometry_code, appearance_code)
    fmap, opacity = volume_render_features(sigma.reshape(b, r, -1), feat.reshape(b, r, cfg.samples, -1), t)
    h, w = size
    return fmap.transpose(1, 2).reshape(b, -1, h, w), opacity.reshape(b, 1, h, w)
