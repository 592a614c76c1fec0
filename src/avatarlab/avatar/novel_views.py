"""Novel views and parameter sweeps of an avatar (seed 002, 4.4; figures 4-7 and 55 of the dissertation).

From one test frame of the subject: rows of (1) novel views - the camera orbited about the head (changed extrinsics),
(2) neck rotation, (3) jaw opening, (4) camera distance, (5) expression component 1. Writes a PNG grid and a JSON
with what each row varies.
`python -m avatarlab.avatar.novel_views apps.avatar=.../model.pt apps.subject_dir=... apps.out=grid.png`
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

from avatarlab.model.avatar import open_avatar, orbit, select, to_uint8
from avatarlab.runtime.entry import entry_point
from avatarlab.runtime.io import write_json, write_png

log = logging.getLogger(__name__)
READS = ('seed', 'apps')  # the config sections this step reads (runtime/entry.py)


def stack_cameras(cameras: list) -> object:
    first = cameras[0]
    return type(first)(K=torch.cat([c.K for c in cameras]), R=torch.cat([c.R for c in cameras]),
                       t=torch.cat([c.t for c in cameras]), image_size=first.image_size)


def sweeps(avatar, fit: dict, frame: int, cfg) -> tuple[list[np.ndarray], dict]:
    params, camera = select(fit, [frame])
    n = len(cfg.yaw_deg)
    base = {k: v.repeat(n, *[1] * (v.dim() - 1)) for k, v in params.items()}
    base_cam = stack_cameras([camera] * n)

    def vary(key: str, column: int, values) -> torch.Tensor:
        changed = {k: v.clone() for k, v in base.items()}
        changed[key][:, column] = torch.tensor(list(values), dtype=torch.float32)[:n]
        return avatar.render(changed, base_cam)

    rows = {"novel_view_yaw_deg": avatar.render(base, stack_cameras([orbit(camera, y) for y in cfg.yaw_deg])),
            "neck_yaw_deg": vary("pose", 4, np.radians(list(cfg.neck_deg))),
            "jaw_rad": vary("pose", 6, cfg.jaw_rad),
            "distance_offset": avatar.render(base, stack_cameras([orbit(camera, 0.0, dz=d)
                                                                   for d in cfg.distance_offsets])),
            "expression_1": vary("expression", 0, cfg.expression_values)}
    labels = {"novel_view_yaw_deg": list(cfg.yaw_deg), "neck_yaw_deg": list(cfg.neck_deg),
              "jaw_rad": list(cfg.jaw_rad), "distance_offset": list(cfg.distance_offsets),
              "expression_1": list(cfg.expression_values)}
    return [np.concatenate(list(to_uint8(r)), 1) for r in rows.values()], labels


@entry_point(READS)
def main(cfg, device) -> None:
    apps = cfg.apps
    avatar, fit = open_avatar(apps, device)
    frames = torch.nonzero(fit["fitted"]).flatten()
    frame = int(frames[-1])  # a test frame (the last fitted one)
    for key in ("neck_deg", "jaw_rad", "distance_offsets", "expression_values"):
        if len(apps[key]) != len(apps.yaw_deg):
            raise ValueError(f"apps.{key} has {len(apps[key])} values; every sweep needs {len(apps.yaw_deg)} "
                             "(as many as apps.yaw_deg)")
    rows, labels = sweeps(avatar, fit, frame, apps)
    write_png(apps.out, np.concatenate(rows, 0))
    write_json(Path(apps.out).with_suffix(".json"), {"frame": frame, "rows": list(labels), "values": labels,
                                                     "avatar": str(apps.avatar)})
    log.info("novel views and sweeps of frame %d -> %s", frame, apps.out)


if __name__ == "__main__":
    main()
