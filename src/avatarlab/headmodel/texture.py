"""Albedo PCA (seed 002, section 2.2); the SH lighting lives in avatarlab.render.lighting."""
from __future__ import annotations

import torch
from torch import nn

from avatarlab.headmodel.sources import UVAlbedo, VertexAlbedo


class AlbedoModel(nn.Module):
    """Albedo from texture coefficients tau: per-vertex colours (B,V,3) or a UV map (B,3,H,W)."""

    def __init__(self, albedo: VertexAlbedo | UVAlbedo, n_components: int | None = None):
        super().__init__()
        total = albedo.basis.shape[-1]
        self.n_components = min(n_components or total, total)
        self.is_uv = isinstance(albedo, UVAlbedo)
        self.register_buffer("mean", torch.as_tensor(albedo.mean, dtype=torch.float32))
        self.register_buffer("basis", torch.as_tensor(albedo.basis[..., : self.n_components], dtype=torch.float32))
        if self.is_uv:
            self.register_buffer("uv", torch.as_tensor(albedo.uv, dtype=torch.float32))
            self.register_buffer("uv_faces", torch.as_tensor(albedo.uv_faces, dtype=torch.long))

    def forward(self, texture: torch.Tensor) -> torch.Tensor:
        tau = texture[:, : self.n_components]
        colour = self.mean.unsqueeze(0) + torch.einsum("bk,...k->b...", tau, self.basis)
        colour = colour.clamp(0.0, 1.0)
        return colour.permute(0, 3, 1, 2) if self.is_uv else colour
