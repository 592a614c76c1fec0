"""Landmark normalisation and the lip error of seeds 000/001: frames similarity-aligned to a reference on the stable
points (Procrustes with Kabsch rotation), lip error in percent of the inter-ocular distance."""
from __future__ import annotations

import numpy as np

from avatarlab.geometry import similarity_transform

STABLE = list(range(17, 48))  # brows, nose, eyes
LIPS = list(range(48, 68))


def align_to(points: np.ndarray, reference: np.ndarray, idx=STABLE) -> np.ndarray:
    """Similarity-align each (68, 2) frame of `points` (T, 68, 2) to `reference` on `idx` (Umeyama / Kabsch)."""
    out = np.empty_like(points)
    for t, frame in enumerate(points):
        scale, rotation, shift = similarity_transform(frame[idx], reference[idx])
        out[t] = scale * frame @ rotation.T + shift
    return out


def lip_error_percent(pred: np.ndarray, truth: np.ndarray) -> float:
    iod = np.linalg.norm(truth[:, 36] - truth[:, 45], axis=1)
    err = np.linalg.norm(pred[:, LIPS] - truth[:, LIPS], axis=2).mean(1) / iod
    return float(100 * err.mean())
