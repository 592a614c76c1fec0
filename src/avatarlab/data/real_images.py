"""The real images a head model trains and is tested on: frames, masks and RGB fits of a preprocessed subject.

Used for the pretraining image set (the FFHQ stand-in or real photos), a subject's training frames (fine-tuning) and
its test frames (evaluation). Also the two image-space manipulations of the dissertation: the z-distance augmentation
(seed 002, 3.4, strategies beta2/5/6 and the final fine-tuning) and variant (c) of the interpolation experiment
(section 4.3), whose dropped frames are re-created by the frame interpolator.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from avatarlab.data.subject_dir import SubjectDir
from avatarlab.render.camera import Camera

PARAM_KEYS = ("shape", "expression", "pose", "texture", "lighting")


class RealImageSet:
    """Frames, masks and per-frame fits of a subject at `image_size`, restricted to fitted frames (and `indices`).
    images (N, 3, S, S) in [0, 1], masks (N, 1, S, S), K/R/t (camera of each frame at S), params (per frame),
    frame_index (N,) the subject's frame numbers."""

    def __init__(self, subject_dir: str | Path, image_size: int, indices=None, interpolated: str | Path | None = None):
        subject = SubjectDir(subject_dir)
        fit = subject.fit()
        frames, masks = subject.frames(), subject.masks()
        if interpolated is not None:
            replace_with_interpolated(frames, masks, fit, *subject.interpolated(interpolated))
        keep = fit["fitted"].astype(bool).copy()
        if indices is not None:  # e.g. the training split of a subject's video
            chosen = np.zeros_like(keep)
            chosen[np.asarray(indices, dtype=int)] = True
            keep &= chosen
        if keep.sum() == 0:
            raise ValueError(f"{subject.fit_file}: no fitted frame among the ones asked for")
        self.frame_index = np.nonzero(keep)[0]
        scale = image_size / frames.shape[1]
        self.images = F.interpolate(torch.from_numpy(frames[keep]).permute(0, 3, 1, 2).float() / 255,
                                    size=(image_size, image_size), mode="bilinear", align_corners=False,
                                    antialias=scale < 1)
        self.masks = F.interpolate(torch.from_numpy(masks[keep][:, None]).float(), size=(image_size, image_size),
                                   mode="area" if scale < 1 else "nearest")
        K = torch.from_numpy(fit["K"][keep]).float()
        K[:, :2] *= scale
        self.K, self.R, self.t = K, torch.from_numpy(fit["R"][keep]).float(), torch.from_numpy(fit["t"][keep]).float()
        self.params = {k: torch.from_numpy(np.ascontiguousarray(fit[k][keep])).float() for k in PARAM_KEYS}
        self.size = image_size

    def __len__(self):
        return self.images.shape[0]

    def camera(self, idx=slice(None)) -> Camera:
        return Camera(K=self.K[idx], R=self.R[idx], t=self.t[idx], image_size=(self.size, self.size))

    def select(self, idx) -> dict:
        """The parameters of samples `idx`."""
        return {k: v[idx] for k, v in self.params.items()}


def replace_with_interpolated(frames: np.ndarray, masks: np.ndarray, fit: dict, indices: np.ndarray,
                              images: np.ndarray) -> np.ndarray:
    """Variant (c) of the interpolation experiment: the frames that variant (b) drops are re-created without looking
    at them - the image by the frame interpolator, the mask as the union of the two neighbours' masks, the fitted
    parameters and camera as the mean of the neighbours' (a real pipeline would fit the new frame; the neighbours'
    mean is what is known without it). Modifies the arrays in place; returns the indices replaced (those whose
    neighbours were both fitted)."""
    if images.shape[1:3] != frames.shape[1:3]:
        raise ValueError(f"interpolated frames are {images.shape[1:3]}, the subject's frames {frames.shape[1:3]}")
    done = []
    for i, image in zip(np.asarray(indices).tolist(), images):
        a, b = i - 1, i + 1
        if a < 0 or b >= len(frames) or not (fit["fitted"][a] and fit["fitted"][b]):
            fit["fitted"][i] = False
            continue
        frames[i] = image
        masks[i] = np.maximum(masks[a], masks[b])
        for key in ("shape", "expression", "pose", "texture", "lighting", "K", "t"):
            fit[key][i] = (fit[key][a].astype(np.float64) + fit[key][b]) / 2
        u, _, vt = np.linalg.svd((fit["R"][a].astype(np.float64) + fit["R"][b]) / 2)  # nearest rotation to the mean
        fit["R"][i] = u @ vt
        fit["fitted"][i] = True
        done.append(i)
    return np.asarray(done, dtype=int)


def z_augment(images, masks, camera: Camera, g: torch.Generator, low: float, high: float, p: float):
    """The z-distance augmentation: with probability p, the head is moved along the camera's optical axis so that
    it appears s ~ U[low, high] times its size (s > 1: closer). The head's camera-space z becomes z / s (x, y kept)
    and the image is zoomed by s about the principal point, which is what the camera sees of the moved head up to
    the change of perspective within the head's depth (|dz| << z); K is unchanged, so the rays the model is
    trained with meet the head at its new distance (seed 002, 3.4). -> images, masks, camera."""
    n = images.shape[0]
    s = torch.where(torch.rand(n, generator=g) < p, low + (high - low) * torch.rand(n, generator=g), torch.ones(n))
    size = images.shape[-1]
    centre = camera.K[:, :2, 2] / size * 2 - 1  # principal point in [-1, 1] grid units
    theta = torch.zeros(n, 2, 3)
    theta[:, 0, 0] = theta[:, 1, 1] = 1 / s
    theta[:, :, 2] = centre * (1 - 1 / s)[:, None]  # zoom about the principal point
    grid = F.affine_grid(theta, list(images.shape), align_corners=False)
    images = F.grid_sample(images, grid, align_corners=False, padding_mode="border")
    masks = F.grid_sample(masks, grid, align_corners=False)
    t = camera.t.clone()
    t[:, 2] = t[:, 2] / s
    return images, masks, Camera(K=camera.K, R=camera.R, t=t, image_size=camera.image_size)
