"""Expression and pose transfer (seed 002, 4.4; figure 56): another subject's fitted video drives an avatar.

Per source frame the avatar takes the source's expression ψ, pose θ (neck, jaw, eyes) and camera extrinsics, and keeps
its own identity (shape, texture, lighting from its subject's fit). Writes an MP4 with the source frame beside the
avatar's render, and a JSON with frame count and render speed.
`python -m avatarlab.avatar.reenact apps.avatar=.../model.pt apps.subject_dir=<avatar's subject> apps.source_dir=<other>`
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch

from avatarlab.data.subject_dir import SubjectDir
from avatarlab.model.avatar import load_fit, open_avatar, select, to_uint8
from avatarlab.runtime.entry import entry_point
from avatarlab.runtime.io import write_json, write_video

log = logging.getLogger(__name__)
READS = ('seed', 'apps')  # the config sections this step reads (runtime/entry.py)


def transfer_params(target: dict, source: dict, source_idx: torch.Tensor, identity_frame: int) -> dict:
    """Source motion (expression, neck/jaw/eye pose) on the target's identity (shape, texture, lighting)."""
    n = len(source_idx)
    params = {k: target[k][identity_frame].expand(n, *target[k].shape[1:]).clone()
              for k in ("shape", "texture", "lighting")}
    params["expression"] = source["expression"][source_idx].clone()
    params["pose"] = source["pose"][source_idx].clone()
    return params


@entry_point(READS)
def main(cfg, device) -> None:
    apps = cfg.apps
    avatar, target = open_avatar(apps, device)
    source = load_fit(apps.source_dir, avatar.image_size)
    frames, meta = SubjectDir(Path(apps.source_dir)).frames(), SubjectDir(Path(apps.source_dir)).frames_meta()
    idx = torch.nonzero(source["fitted"]).flatten()[: int(apps.max_frames)]
    if len(idx) == 0:
        raise ValueError(f"{apps.source_dir}/fit_rgb.npz: no fitted frame to transfer")
    identity = int(torch.nonzero(target["fitted"]).flatten()[0])
    params = transfer_params(target, source, idx, identity)
    _, camera = select(source, idx)
    start = time.perf_counter()
    rendered = to_uint8(avatar.render(params, camera))
    seconds = (time.perf_counter() - start) / len(idx)
    size = avatar.image_size
    import cv2

    shown = np.stack([cv2.resize(frames[i], (size, size), interpolation=cv2.INTER_AREA) for i in idx.tolist()])
    write_video(apps.out, np.concatenate([shown, rendered], 2), float(meta.get("fps") or 25.0))
    keyframes = np.linspace(0, len(idx) - 1, min(6, len(idx))).round().astype(int)
    from avatarlab.runtime.io import write_png

    write_png(Path(apps.out).with_suffix(".png"), np.concatenate([np.concatenate(list(shown[keyframes]), 1),
                                                                  np.concatenate(list(rendered[keyframes]), 1)], 0))
    write_json(Path(apps.out).with_suffix(".json"), {
        "avatar": str(apps.avatar), "source": str(apps.source_dir), "frames": len(idx), "size": size,
        "render_seconds_per_frame": seconds, "fps": float(meta.get("fps") or 25.0),
        "mean_abs_jaw_rad": float(params["pose"][:, 6].abs().mean())})
    log.info("expression transfer: %d frames of %s drive %s -> %s (%.3f s/frame)", len(idx), apps.source_dir,
             apps.avatar, apps.out, seconds)


if __name__ == "__main__":
    main()
