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


def frame_crops(meta: dict) -> list[tuple[int, int, int]]:
    """The crop (cx, cy, side) of every frame of a frames.json: its `crops` (one per clip) or its one `crop`."""
    if "crops" not in meta:
        c = meta["crop"]
        return [(c["cx"], c["cy"], c["side"])] * int(meta["count"])
    per_frame = [None] * int(meta["count"])
    for c in meta["crops"]:
        per_frame[c["first"]:c["first"] + c["count"]] = [(c["cx"], c["cy"], c["side"])] * c["count"]
    if any(c is None for c in per_frame):
        raise ValueError("frames.json: its crops do not cover every frame")
    return per_frame


def crop_points(points: np.ndarray, meta: dict) -> np.ndarray:
    """Original-image pixel coordinates -> coordinates in the cropped, resized frames. With one crop per clip
    (`crops`), the first axis of `points` is the frame."""
    points = np.asarray(points, dtype=np.float64)
    if "crops" in meta:
        crops = np.array(frame_crops(meta)[: len(points)], dtype=np.float64)
        crops = crops.reshape(len(points), *[1] * (points.ndim - 2), 3)
    else:
        c = meta["crop"]
        crops = np.array([c["cx"], c["cy"], c["side"]], dtype=np.float64)
    side = crops[..., 2:]
    corner = np.concatenate([crops[..., :1] - side / 2, crops[..., 1:2] - side / 2], axis=-1)
    return (points - corner) * (meta["size"] / side)
