"""Shared geometry: the similarity / rigid alignment of two point sets (Procrustes with Kabsch's rotation, Umeyama's
scale). One home for the alignment the RGB fit's ground-truth comparison, the RGBD fit's initialisation and the
speech models' landmark normalisation (seed 000: "aligned by Procrustes with Kabsch rotation") all use."""
from __future__ import annotations

import numpy as np


def similarity_transform(src: np.ndarray, dst: np.ndarray, with_scale: bool = True):
    """(scale, R, t) minimising sum ||scale * R @ src_i + t - dst_i||^2 over proper rotations (no reflection).

    src, dst: (N, D) corresponding points, D = 2 or 3. with_scale=False gives the rigid (Kabsch) solution.
    """
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, s, vt = np.linalg.svd(b.T @ a)
    d = np.ones(src.shape[1])
    d[-1] = np.sign(np.linalg.det(u @ vt)) or 1.0
    rotation = u @ np.diag(d) @ vt
    scale = float((s * d).sum() / (a**2).sum()) if with_scale else 1.0
    return scale, rotation, mu_d - scale * rotation @ mu_s


def align(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> np.ndarray:
    """`src` moved by the similarity (or rigid) transform that best maps it onto `dst`."""
    scale, rotation, t = similarity_transform(src, dst, with_scale)
    return scale * np.asarray(src, np.float64) @ rotation.T + t


def procrustes_error_mm(a: np.ndarray, b: np.ndarray) -> float:
    """Mean vertex distance (mm; a and b in metres) after the similarity transform that best maps a onto b."""
    return float(1000 * np.linalg.norm(align(a, b) - np.asarray(b, np.float64), axis=1).mean())
