"""Telepresence payload (seed 002, 4.4): per frame only pose θ (neck, jaw, eyes), expression ψ and the camera
extrinsics are sent; the receiver holds the avatar and renders. Compares bytes per frame of those parameters
(float32 and float16) with the JPEG of the same frame, and measures what float16 costs in the rendered image
(PSNR of the render from float16 parameters against the render from float32 ones) and the receiver's render time.
`python -m avatarlab.avatar.telepresence apps.avatar=.../model.pt apps.subject_dir=... apps.out=telepresence.json`
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import cv2
import kornia
import numpy as np
import torch
from kornia.geometry.conversions import rotation_matrix_to_axis_angle

from avatarlab.data.subject_dir import SubjectDir
from avatarlab.model.avatar import open_avatar, select
from avatarlab.runtime.entry import entry_point
from avatarlab.runtime.io import write_json

log = logging.getLogger(__name__)
READS = ('seed', 'apps')  # the config sections this step reads (runtime/entry.py)


def payload(params: dict, R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """The per-frame message: neck, jaw and eye rotations (12), expression (E), camera rotation (3) and shift (3)."""
    return torch.cat([params["pose"][:, 3:], params["expression"], rotation_matrix_to_axis_angle(R), t], 1)


def jpeg_bytes(frames: np.ndarray, quality: int) -> list[int]:
    return [len(cv2.imencode(".jpg", cv2.cvtColor(f, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])[1])
            for f in frames]


@entry_point(READS)
def main(cfg, device) -> None:
    apps = cfg.apps
    avatar, fit = open_avatar(apps, device)
    frames = SubjectDir(Path(apps.subject_dir)).frames()
    idx = torch.nonzero(fit["fitted"]).flatten()[: int(apps.max_frames)]
    params, camera = select(fit, idx)
    message = payload(params, camera.R, camera.t)
    n_values = int(message.shape[1])
    # the receiver: float16 parameters back to float32, the camera rebuilt from its axis-angle rotation
    half = {k: v.half().float() for k, v in params.items()}
    cam_half = type(camera)(K=camera.K, R=kornia.geometry.conversions.axis_angle_to_rotation_matrix(
        rotation_matrix_to_axis_angle(camera.R).half().float()), t=camera.t.half().float(), image_size=camera.image_size)
    start = time.perf_counter()
    full = avatar.render(params, camera)
    seconds = (time.perf_counter() - start) / len(idx)
    quant = avatar.render(half, cam_half)
    size = avatar.image_size
    shown = np.stack([cv2.resize(frames[i], (size, size), interpolation=cv2.INTER_AREA) for i in idx.tolist()])
    report = {
        "frames": len(idx), "values_per_frame": n_values,
        "bytes_per_frame": {"params_float32": 4 * n_values, "params_float16": 2 * n_values},
        "jpeg_bytes_per_frame": {}, "image_size": size, "receiver_render_seconds_per_frame": seconds,
        "float16_render_psnr_db": float(kornia.metrics.psnr(quant, full, 1.0)),
    }
    for q in apps.jpeg_quality:
        report["jpeg_bytes_per_frame"][f"q{q}_{size}px"] = float(np.mean(jpeg_bytes(shown, int(q))))
        report["jpeg_bytes_per_frame"][f"q{q}_{frames.shape[1]}px"] = float(np.mean(jpeg_bytes(frames[idx.numpy()],
                                                                                               int(q))))
    ref = report["jpeg_bytes_per_frame"][f"q{apps.jpeg_quality[0]}_{size}px"]
    report["jpeg_over_float16_ratio"] = ref / report["bytes_per_frame"]["params_float16"]
    write_json(apps.out, report)
    log.info("telepresence: %d values per frame = %d B (float16) vs JPEG q%d %.0f B (%.0fx); the render from float16 "
             "is %.1f dB PSNR from the float32 one; receiver renders %.3f s/frame", n_values, 2 * n_values,
             apps.jpeg_quality[0], ref, report["jpeg_over_float16_ratio"], report["float16_render_psnr_db"], seconds)


if __name__ == "__main__":
    main()
