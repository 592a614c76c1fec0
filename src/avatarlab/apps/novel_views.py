"""Novel views and parameter sweeps of an avatar (seed 002, 4.4; figures 4-7 and 55 of the dissertation).

From one test frame of the subject: rows of (1) novel views - the camera orbited about the head (changed extrinsics),
(2) neck rotation, (3) jaw opening, (4) camera distance, (5) expression component 1. Writes a PNG grid and a JSON
with what each row varies.
`python -m avatarlab.apps.novel_views apps.avatar=.../model.pt apps.subject_dir=... apps.out=grid.png`
"""
from __future__ import annotations

import logging
from pathlib import Path

import hydra
import numpy as np
import torch
from omegaconf import DictConfig

from avatarlab.apps.avatar import load_avatar, load_fit, orbit, select, to_uint8
from avatarlab.config import CONF_DIR, setup_run
from avatarlab.io import write_json, write_png

log = logging.getLogger(__name__)


def sweeps(avatar, fit: dict, frame: int, cfg) -> tuple[list[np.ndarray], dict]:
    params, camera = select(fit, [frame])
    rows, labels = [], {}
    values = list(cfg.yaw_deg)
    n = len(values)

    def repeat(p, cam):
        return ({k: v.repeat(n, *[1] * (v.dim() - 1)) for k, v in p.items()},
                type(cam)(K=cam.K.repeat(n, 1, 1), R=cam.R.repeat(n, 1, 1), t=cam.t.repeat(n, 1), image_size=cam.image_size))

    base_p, base_c = repeat(params, camera)
    views = [orbit(camera, yaw) for yaw in values]
    cams = type(camera)(K=torch.cat([v.K for v in views]), R=torch.cat([v.R for v in views]),
                        t=torch.cat([v.t for v in views]), image_size=camera.image_size)
    rows.append(avatar.render(base_p, cams))
    labels["novel_view_yaw_deg"] = values
    neck = {k: v.clone() for k, v in base_p.items()}
    neck["pose"][:, 4] = torch.tensor(np.radians(list(cfg.neck_deg)), dtype=torch.float32)[:n]
    rows.append(avatar.render(neck, base_c))
    labels["neck_yaw_deg"] = list(cfg.neck_deg)
    jaw = {k: v.clone() for k, v in base_p.items()}
    jaw["pose"][:, 6] = torch.tensor(list(cfg.jaw_rad), dtype=torch.float32)[:n]
    rows.append(avatar.render(jaw, base_c))
    labels["jaw_rad"] = list(cfg.jaw_rad)
    dist = [orbit(camera, 0.0, dz=dz) for dz in cfg.distance_offsets]
    cams = type(camera)(K=torch.cat([v.K for v in dist]), R=torch.cat([v.R for v in dist]),
                        t=torch.cat([v.t for v in dist]), image_size=camera.image_size)
    rows.append(avatar.render(base_p, cams))
    labels["distance_offset"] = list(cfg.distance_offsets)
    expr = {k: v.clone() for k, v in base_p.items()}
    expr["expression"][:, 0] = torch.tensor(list(cfg.expression_values), dtype=torch.float32)[:n]
    rows.append(avatar.render(expr, base_c))
    labels["expression_1"] = list(cfg.expression_values)
    return [np.concatenate(list(to_uint8(r)), 1) for r in rows], labels


@hydra.main(config_path=str(CONF_DIR), config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> None:
    setup_run(cfg)
    apps = cfg.apps
    avatar = load_avatar(apps.avatar)
    fit = load_fit(apps.subject_dir, avatar.image_size)
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
