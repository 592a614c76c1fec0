"""Trivial predictors: what a model must beat before any of its numbers mean something.

Each predicts the test images from training data alone and is composited into the test frame's true mask exactly
as the model's render is, then scored by the same metrics on the same frames:
- `mean_colour`: one colour inside the mask, the mean colour of the training samples' head regions;
- `mean_frame`: the pixelwise mean of the training images;
- `last_frame`: the last training frame before the test frame (a video subject: the frame just before the test clip;
  a same-recording test frame: its clip's last training frame);
- `nearest`: the training sample whose conditioning is nearest (each block - e.g. shape, expression, jaw, neck,
  camera - standardised over the training set and weighted equally).
"""
from __future__ import annotations

import numpy as np
import torch

from avatarlab.model.losses import composite


def mean_colour(train_images: torch.Tensor, train_masks: torch.Tensor, test_masks: torch.Tensor) -> torch.Tensor:
    """(N,3,H,W), (N,1,H,W) training; (T,1,H,W) test masks -> (T,3,H,W)."""
    colour = (train_images * train_masks).sum((0, 2, 3)) / train_masks.sum().clamp(min=1)
    return composite(colour[None, :, None, None].expand(len(test_masks), -1, *test_masks.shape[2:]), test_masks)


def mean_frame(train_images: torch.Tensor, train_masks: torch.Tensor, test_masks: torch.Tensor) -> torch.Tensor:
    mean = composite(train_images, train_masks).mean(0, keepdim=True)
    return composite(mean.expand(len(test_masks), -1, -1, -1), test_masks)


def frames_at(train_images: torch.Tensor, train_masks: torch.Tensor, idx, test_masks: torch.Tensor) -> torch.Tensor:
    """The training images `idx` (one per test frame), as predictions in the test masks."""
    idx = torch.as_tensor(idx, dtype=torch.long)
    return composite(composite(train_images[idx], train_masks[idx]), test_masks)


def conditioning_blocks(params: dict, R: torch.Tensor, t: torch.Tensor, keys: tuple[str, ...]) -> dict:
    """Named blocks of a sample's conditioning: shape, texture, expression, neck, jaw, camera (R and t)."""
    pose = params["pose"]
    available = {"shape": params.get("shape"), "texture": params.get("texture"),
                 "expression": params["expression"], "neck": pose[:, 3:6], "jaw": pose[:, 6:9],
                 "camera": torch.cat([R.reshape(len(R), 9), t], 1)}
    return {k: available[k].float() for k in keys}


def nearest_indices(pool: dict, query: dict) -> np.ndarray:
    """For each query, the pool entry nearest in block-standardised conditioning: each dimension divided by its
    standard deviation over the pool, each block's squared distance divided by its size, blocks summed."""
    total = None
    for key, values in pool.items():
        std = values.std(0).clamp(min=1e-6)
        diff = (query[key][:, None] - values[None]) / std
        d = (diff**2).mean(-1)
        total = d if total is None else total + d
    return total.argmin(1).numpy()
