"""Spherical-harmonics lighting (seed 002, section 2.2: 9 SH bands x 3 colours = 27 values)."""
from __future__ import annotations

import math

import torch

SH_BANDS = 9
# Lambertian irradiance factors per band (Ramamoorthi & Hanrahan 2001), basis order:
# 1, x, y, z, xy, xz, yz, x^2 - y^2, 3z^2 - 1 (the order used by DECA/photometric_optimization).
_SH_FACTORS = torch.tensor([
    1 / math.sqrt(4 * math.pi),
    (2 * math.pi / 3) * math.sqrt(3 / (4 * math.pi)),
    (2 * math.pi / 3) * math.sqrt(3 / (4 * math.pi)),
    (2 * math.pi / 3) * math.sqrt(3 / (4 * math.pi)),
    (math.pi / 4) * 3 * math.sqrt(5 / (12 * math.pi)),
    (math.pi / 4) * 3 * math.sqrt(5 / (12 * math.pi)),
    (math.pi / 4) * 3 * math.sqrt(5 / (12 * math.pi)),
    (math.pi / 4) * (3 / 2) * math.sqrt(5 / (12 * math.pi)),
    (math.pi / 4) * (1 / 2) * math.sqrt(5 / (4 * math.pi)),
])


def sh_basis(normals: torch.Tensor) -> torch.Tensor:
    """normals (..., 3), unit, in the view frame (x right, y up, z towards the camera) -> (..., 9)."""
    x, y, z = normals.unbind(-1)
    one = torch.ones_like(x)
    basis = torch.stack([one, x, y, z, x * y, x * z, y * z, x * x - y * y, 3 * z * z - 1], dim=-1)
    return basis * _SH_FACTORS.to(normals)


def sh_shading(normals: torch.Tensor, sh_coefficients: torch.Tensor) -> torch.Tensor:
    """normals (B, ..., 3), sh_coefficients (B, 9, 3) -> RGB shading (B, ..., 3)."""
    basis = sh_basis(normals)
    flat = basis.reshape(basis.shape[0], -1, SH_BANDS)
    return torch.bmm(flat, sh_coefficients).reshape(*normals.shape[:-1], 3)


def default_lighting(batch: int = 1, ambient: float = 0.8, frontal: float = 0.3, top: float = 0.12,
                     device=None) -> torch.Tensor:
    """SH coefficients (B, 9, 3) for soft white light from the front and slightly above."""
    sh = torch.zeros(batch, SH_BANDS, 3, device=device)
    sh[:, 0] = ambient / _SH_FACTORS[0]
    sh[:, 2] = top / _SH_FACTORS[2]
    sh[:, 3] = frontal / _SH_FACTORS[3]
    return sh
