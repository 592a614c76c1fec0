"""The head crop of the frame extraction: cropping frames and moving pixel coordinates into the crop."""
from __future__ import annotations

import cv2
import numpy as np


def crop_and_resize(frame: np.ndarray, crop, size: int) -> np.ndarray:
    cx, cy, side = crop
    half = side / 2
    # affine map of the crop square onto the output; outside the frame, edge pixels are replicated
    scale = size / side
    M = np.array([[scale, 0, -(cx - half) * scale], [0, scale, -(cy - half) * scale]], dtype=np.float64)
    return cv2.warpAffine(frame, M, (size, size), flags=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REPLICATE)


def crop_points(points: np.ndarray, meta: dict) -> np.ndarray:
    """Original-image pixel coordinates -> coordinates in the cropped, resized frames."""
    c = meta["crop"]
    scale = meta["size"] / c["side"]
    return (points - np.array([c["cx"] - c["side"] / 2, c["cy"] - c["side"] / 2])) * scale
