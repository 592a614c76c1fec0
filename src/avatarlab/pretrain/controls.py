"""Pretrained head models on held-out frames with one control swept (seed 002, 3.4: figs. 27, 29-32; App. A.1-A.4).

The dissertation shows its pretrained models on images of the test set with one parameter moved at a time - the
jaw (fig. 30: beta4 from alpha1 vs alpha2), the camera distance along z (fig. 31: beta1 vs beta2 from alpha2), the
neck (fig. 32: beta2, beta5, beta6 from alpha2) - each synthesis row under the head model's render of the same
parameters ("even rows synthesis, odd rows FLAME"), and the renders of the fitted parameters themselves (figs. 27,
29). Here the held-out images are frames of the video subjects (never part of the pretraining image set): the
middle fitted frame of each, with its fitted shape, expression, pose, texture, lighting and camera and no learned
offsets (a pretrained model has offsets only for its training images).

Each model row is scored against the head model's renders of the same parameters (the head with the mouth interior
for a model whose synthetic samples had it: alpha2 and its continuations), over the head region (and ST-LPIPS over
the image), beside two trivial predictors on the same renders: `mean_colour` (the held-out frame's mean colour inside
its mask, in every rendered mask) and, where a control moves, `unswept` (the render of the frame's own fitted
parameters, as if the control did nothing). Whether a model follows the control at all is `response_correlation`: the
Pearson correlation, over the head pixels, of the model's change from the sweep's first value with the head model's
change (0 for anything that ignores the control).
Writes a PNG grid and a JSON beside it.
`python -m avatarlab.pretrain.controls controls.models=[a/model.pt,b/model.pt] controls.subject_dirs=[...]
controls.control=jaw controls.out=fig30_jaw.png`
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw

from avatarlab.data.real_images import RealImageSet
from avatarlab.headmodel import load_head_model
from avatarlab.metrics.quality import STLPIPS
from avatarlab.metrics.scoring import gains, image_scores
from avatarlab.model.avatar import Avatar, load_fit, orbit, select, to_uint8
from avatarlab.model.head_nerf import load_model_file, synthetic_mouth
from avatarlab.model.losses import composite
from avatarlab.render.camera import Camera
from avatarlab.render.head_renderer import HeadRenderer
from avatarlab.runtime.entry import entry_point
from avatarlab.runtime.io import write_json, write_png

log = logging.getLogger(__name__)
READS = ("seed", "head_model", "render", "evaluate", "controls")
CONTROLS = ("fitted", "jaw", "distance", "neck", "expression")
LABEL_WIDTH = 150


def variants(params: dict, camera, control: str, cfg) -> tuple[dict, object, list[float]]:
    """The frame's parameters and camera repeated once per value of `control` with that control set -> (params,
    camera, values). `fitted`: the frame's own parameters, once."""
    values = {"fitted": [0.0], "jaw": list(cfg.jaw_rad), "distance": list(cfg.distance_offsets),
              "neck": list(cfg.neck_deg), "expression": list(cfg.expression_values)}[control]
    n = len(values)
    out = {k: v.repeat(n, *[1] * (v.dim() - 1)).clone() for k, v in params.items()}
    cameras = [camera] * n
    column = torch.tensor(values, dtype=torch.float32)
    if control == "jaw":
        out["pose"][:, 6] = column  # jaw opening (rotation about x)
    elif control == "neck":
        out["pose"][:, 4] = torch.deg2rad(column)  # neck yaw
    elif control == "expression":
        out["expression"][:, 0] = column
    elif control == "distance":
        cameras = [orbit(camera, 0.0, dz=d) for d in values]  # the camera moved along its axis
    return out, Camera.cat(cameras), values


def held_out_frames(subject_dirs, image_size: int) -> list[tuple[str, int, dict]]:
    """(subject, frame, fit) of the middle fitted frame of each subject."""
    frames = []
    for folder in subject_dirs:
        fit = load_fit(folder, image_size)
        fitted = torch.nonzero(fit["fitted"]).flatten()
        if len(fitted) == 0:
            raise ValueError(f"{folder}/fit_rgb.npz: no fitted frame")
        frames.append((Path(folder).name, int(fitted[len(fitted) // 2]), fit))
    return frames


def frame_image(subject_dir: str | Path, frame: int, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The held-out frame and its head mask at `size` -> (3, S, S), (1, S, S)."""
    real = RealImageSet(subject_dir, size, indices=[frame])
    return real.images[0], real.masks[0]


def response_correlation(pred: torch.Tensor, truth: torch.Tensor, masks: torch.Tensor) -> float | None:
    """Pearson correlation, over the pixels inside any of the masks, of each render's change from the first."""
    if pred.shape[0] < 2:
        return None
    union = (masks > 0.5).any(0, keepdim=True).expand_as(pred[1:])
    a = (pred[1:] - pred[:1])[union.expand(-1, 3, -1, -1)].double()
    b = (truth[1:] - truth[:1])[union.expand(-1, 3, -1, -1)].double()
    a, b = a - a.mean(), b - b.mean()
    denominator = float(a.norm() * b.norm())
    return float(a @ b) / denominator if denominator > 0 else 0.0


def label(strip: np.ndarray, text: str, note: str = "") -> np.ndarray:
    """A row of images with a white margin on the left carrying `text` (and a grey `note`)."""
    h = strip.shape[0]
    canvas = Image.new("RGB", (LABEL_WIDTH + strip.shape[1], h), (255, 255, 255))
    canvas.paste(Image.fromarray(strip), (LABEL_WIDTH, 0))
    draw = ImageDraw.Draw(canvas)
    draw.text((4, h // 2 - 12), text[:24], fill=(0, 0, 0))
    draw.text((4, h // 2 + 2), note[:24], fill=(90, 90, 90))
    return np.asarray(canvas)


@torch.no_grad()
def control_figure(cfg, device) -> tuple[np.ndarray, dict]:
    c = cfg.controls
    if c.control not in CONTROLS:
        raise ValueError(f"controls.control={c.control!r}: one of {', '.join(CONTROLS)}")
    if not c.models or not c.subject_dirs:
        raise ValueError("controls.models and controls.subject_dirs each need at least one entry")
    loaded, mouths = {}, {}
    for path in c.models:
        net, content = load_model_file(path, device)
        name = Path(path).parent.name
        loaded[name] = Avatar(net, content["config"], int(content["spec"]["feature_size"]) * 8)
        mouths[name] = synthetic_mouth(content)
    sizes = {a.image_size for a in loaded.values()}
    if len(sizes) > 1:
        raise ValueError(f"controls.models render at different sizes ({sorted(sizes)}); one figure needs one size")
    size = sizes.pop()
    heads = {mouth: HeadRenderer(load_head_model(cfg.head_model, mouth_interior=mouth).to(device),
                                 background=tuple(cfg.render.background),
                                 backface_shade=float(cfg.render.backface_shade))
             for mouth in sorted(set(mouths.values()))}
    rows, report = [], {"control": c.control, "image_size": size, "frames": [], "models": {}}
    per_model = {name: {"pred": [], "truth": [], "masks": [], "mean_colour": [], "unswept": [], "response": []}
                 for name in loaded}
    values = None
    for folder, (subject, frame, fit) in zip(c.subject_dirs, held_out_frames(c.subject_dirs, size)):
        params, camera = select(fit, [frame])
        image, mask = frame_image(folder, frame, size)
        report["frames"].append({"subject": subject, "frame": frame})
        swept, cameras, values = variants(params, camera, c.control, c)
        mean = (image * mask).sum((1, 2)) / mask.sum().clamp(min=1)
        original = to_uint8(composite(image[None], mask[None]))[0]
        blank = np.full_like(original, 255)
        renders = {}  # per head variant: the swept renders (composited), their masks and the unswept render
        for mouth, renderer in heads.items():
            lighting = swept["lighting"].to(device)
            out = renderer({k: v.to(device) for k, v in swept.items()}, cameras.to(device), lighting,
                           geometry_images=False)
            own = renderer({k: v.to(device) for k, v in params.items()}, camera.to(device), lighting[:1],
                           geometry_images=False)
            masks = out.mask.cpu()
            renders[mouth] = composite(out.rgb.cpu(), masks), masks, own.rgb.cpu()
        for name, avatar in loaded.items():
            truth, masks, own = renders[mouths[name]]
            pred = composite(avatar.render(swept, cameras), masks)
            stats = per_model[name]
            stats["pred"].append(pred), stats["truth"].append(truth), stats["masks"].append(masks)
            stats["mean_colour"].append(composite(mean[None, :, None, None].expand_as(truth), masks))
            stats["unswept"].append(composite(own.expand_as(truth), masks))
            stats["response"].append(response_correlation(pred, truth, masks))
            head_name = "head model + mouth" if mouths[name] else "head model"
            rows.append(label(np.concatenate([original] + list(to_uint8(truth)), 1), head_name,
                              f"{subject} frame {frame}"))
            rows.append(label(np.concatenate([blank] + list(to_uint8(pred)), 1), name, c.control))
    perceptual = {"st_lpips": STLPIPS(device) if cfg.evaluate.st_lpips else None}
    for name, stats in per_model.items():
        truth, masks = torch.cat(stats["truth"]), torch.cat(stats["masks"])
        model = image_scores(torch.cat(stats["pred"]), truth, masks, perceptual)
        kept = ("mean_colour",) if c.control == "fitted" else ("mean_colour", "unswept")  # fitted: unswept = truth
        baselines = {b: image_scores(torch.cat(stats[b]), truth, masks, perceptual) for b in kept}
        responses = [r for r in stats["response"] if r is not None]
        report["models"][name] = {
            "model": model, "baselines": baselines, "gain": gains(model, baselines),
            "synthetic_mouth": mouths[name],
            "response_correlation": float(np.mean(responses)) if responses else None}
    report["values"] = values
    return np.concatenate(rows, 0), report


@entry_point(READS)
def main(cfg, device) -> None:
    grid, report = control_figure(cfg, device)
    out = Path(cfg.controls.out)
    write_png(out, grid)
    write_json(out.with_suffix(".json"), report)
    for name, r in report["models"].items():
        g = r["gain"]["psnr_head"]
        response = r["response_correlation"]
        log.info("%s, %s swept on %d held-out frames: head-region PSNR %.2f dB vs the head model (best baseline %s "
                 "%.2f, gain %+.2f); response correlation %s", name, report["control"], len(report["frames"]),
                 r["model"]["psnr_head"], g["best_baseline"], g["baseline"], g["gain"],
                 "n/a" if response is None else f"{response:.3f}")


if __name__ == "__main__":
    main()
