"""Scoring an avatar on its test frames against trivial baselines (seed 002, 4.1-4.5; INSTA protocol).

The model renders each test frame from the frame's fitted expression, pose and camera; the baselines predict it
from the frames the avatar's run saw alone (its training frames, and its validation frames when it had some): their
pixelwise mean, the last of them, and the one nearest in fitted expression, jaw, neck and camera. All are composited
into the test frame's true mask and scored the same way: PSNR, head-region PSNR (also with each frame's mean colour
matched), SSIM, ST-LPIPS, LPIPS (missing without the VGG backbone), and on all test frames whether the render is a
face: dlib's detection rate, the 68-point NME against the frame's tracked landmarks (outer-eye
normalised) and the identity similarity; also on the mouth-open subset (the widest fitted jaw openings). Beside
them, the avatar alone on some of its own training frames (`trained`): how well it fits what it saw, so that a gap
to the test frames reads as generalisation, not fitting. With held-out clips and `finetune.recording_test_frames`,
the last frames of its training clips are scored apart, with their own baselines (`same_recording`): a later moment
of a recording it trained on (the INSTA protocol), beside the recordings it never saw.
Writes `eval.json` and `test_frames.png` (truth, model, best baseline) and logs into the avatar's MLflow run.
`python -m avatarlab.avatar.evaluate evaluate.model=.../model.pt finetune.subject_dir=... evaluate.out=...`
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch

from avatarlab.data.real_images import RealImageSet
from avatarlab.data.splits import avatar_split, mouth_open_subset
from avatarlab.data.subject_dir import SubjectDir
from avatarlab.metrics import baselines
from avatarlab.metrics.quality import STLPIPS, face_metrics, lpips_metric, psnr, ssim
from avatarlab.metrics.scoring import gains, image_scores
from avatarlab.model.head_nerf import load_model_file, render_frames
from avatarlab.model.losses import composite
from avatarlab.report.figures import labelled_grid
from avatarlab.runtime.entry import entry_point
from avatarlab.runtime.io import write_json, write_png
from avatarlab.runtime.tracking import log_to_run

log = logging.getLogger(__name__)
READS = ("seed", "finetune", "evaluate", "tracking")
BLOCKS = ("expression", "jaw", "neck", "camera")


def to_uint8(images: torch.Tensor) -> np.ndarray:
    return (images.permute(0, 2, 3, 1).clamp(0, 1).numpy() * 255).round().astype(np.uint8)


def last_seen_before(seen: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """For each of `frames` (frame indices), the position in `seen` (frame indices) of the latest seen frame before
    it, or of the latest of all where none comes before: a test clip's or last-frames test frame gets the last frame
    the avatar saw, a same-recording test frame the last training frame of its own clip."""
    order = np.argsort(seen, kind="stable")
    before = np.searchsorted(seen[order], frames, side="left") - 1
    return order[np.where(before >= 0, before, len(seen) - 1)]


def baseline_predictions(train: RealImageSet, test: RealImageSet) -> dict[str, torch.Tensor]:
    last = last_seen_before(np.asarray(train.frame_index), np.asarray(test.frame_index))
    pool = baselines.conditioning_blocks(train.params, train.R, train.t, BLOCKS)
    query = baselines.conditioning_blocks(test.params, test.R, test.t, BLOCKS)
    return {"mean_frame": baselines.mean_frame(train.images, train.masks, test.masks),
            "last_frame": baselines.frames_at(train.images, train.masks, last, test.masks),
            "nearest": baselines.frames_at(train.images, train.masks, baselines.nearest_indices(pool, query),
                                           test.masks)}


def quality_curve(model_path: Path, final: dict, final_scores: dict, test: RealImageSet, target: torch.Tensor,
                  device, st_lpips=None) -> list[dict]:
    """Test PSNR/SSIM (and ST-LPIPS, when its network is given) of the weights kept part-way through fine-tuning
    (snapshots/) and of the final model, against the fine-tuning time at which they were kept: the
    quality-vs-time curve (seed 002, figures 57-58), in step order; the avatar's own point says `model: true`."""
    points = []
    for path in sorted((model_path.parent / "snapshots").glob("step_*.pt")):
        net, content = load_model_file(path, device)
        if int(content["step"]) == int(final["step"]):  # the model chosen on validation frames is that snapshot
            continue
        pred = composite(render_frames(net, test), test.masks)
        points.append({"step": int(content["step"]), "seconds": content.get("seconds"), "psnr": psnr(pred, target),
                       "ssim": ssim(pred, target), "st_lpips": st_lpips(pred, target) if st_lpips else None})
    points.append({"step": int(final["step"]), "seconds": final.get("seconds"), "psnr": final_scores["psnr"],
                   "ssim": final_scores["ssim"], "st_lpips": final_scores.get("st_lpips"),
                   "model": True})  # the avatar (with a validation split: its stop)
    return sorted(points, key=lambda point: point["step"])


def trained_frame_scores(net, subject_dir, train: np.ndarray, size: int, count: int, perceptual: dict) -> dict | None:
    """The avatar's scores on `count` of its training frames (evenly spaced over `train`, the split's training
    indices; never a validation or test frame), rendered from their fitted codes without the per-frame offsets it
    learned for them, as every test frame is rendered. None when `count` is 0."""
    if count <= 0 or len(train) == 0:
        return None
    chosen = train[np.linspace(0, len(train) - 1, min(count, len(train))).round().astype(int)]
    frames = RealImageSet(subject_dir, size, chosen)
    pred = composite(render_frames(net, frames), frames.masks)
    scores = image_scores(pred, composite(frames.images, frames.masks), frames.masks, perceptual)
    return {"frames": int(len(chosen)), "indices": chosen.tolist(), "model": scores}


def add_face_metrics(part: dict, predictions: dict, target, frames: RealImageSet, subject_dir, size: int) -> float:
    """dlib's face measures of every prediction (the model's, each baseline's) added to a scored `part`, against the
    frames' tracked landmarks; -> the share of true frames where dlib finds a face."""
    points, found = SubjectDir(subject_dir).landmarks()
    frame_size = SubjectDir(subject_dir).frames_meta()["size"]
    truth = points[frames.frame_index] * (size / frame_size)
    truth[~found[frames.frame_index]] = np.nan
    target_u8, targets_seen = to_uint8(target), {}  # each truth frame's face and descriptor, found once
    for name, images in predictions.items():
        faces = face_metrics(to_uint8(images), target_u8, truth, targets_seen)
        (part["model"] if name == "model" else part["baselines"][name]).update(faces)
    return face_metrics(target_u8, target_u8, truth, targets_seen, identity=False)["face_detection_rate"]


def same_recording_scores(net, subject_dir, split, seen: RealImageSet, size: int, perceptual: dict,
                          faces: bool) -> dict | None:
    """The avatar on its same-recording test frames (`split.recording`: the last frames of its training clips), beside
    the trivial baselines from the frames it saw, scored as the test frames are; None without such frames."""
    if len(split.recording) == 0:
        return None
    frames = RealImageSet(subject_dir, size, split.recording)
    target = composite(frames.images, frames.masks)
    predictions = {"model": composite(render_frames(net, frames), frames.masks),
                   **baseline_predictions(seen, frames)}
    part = scored(predictions, target, frames.masks, perceptual, torch.arange(len(frames)))
    if faces:
        add_face_metrics(part, predictions, target, frames, subject_dir, size)
    part["gain"] = gains(part["model"], part["baselines"])
    part["indices"] = split.recording.tolist()
    return part


def scored(predictions: dict, target, masks, perceptual, sel) -> dict:
    model = image_scores(predictions["model"][sel], target[sel], masks[sel], perceptual)
    base = {k: image_scores(p[sel], target[sel], masks[sel], perceptual) for k, p in predictions.items()
            if k != "model"}
    return {"frames": int(len(sel)), "model": model, "baselines": base}


@torch.no_grad()
def evaluate_avatar(cfg, device) -> tuple[dict, torch.Tensor]:
    ev, ft = cfg.evaluate, cfg.finetune
    split = avatar_split(ft)
    net, content = load_model_file(ev.model, device)
    size = int(content["spec"]["feature_size"]) * 8
    variant_c = ft.frames_variant == "c"
    test = RealImageSet(ft.subject_dir, size, split.test)
    train = RealImageSet(ft.subject_dir, size, split.seen, ft.interpolated if variant_c else None)
    start = time.perf_counter()
    render = render_frames(net, test)
    seconds_per_frame = (time.perf_counter() - start) / len(test)
    target = composite(test.images, test.masks)
    predictions = {"model": composite(render, test.masks), **baseline_predictions(train, test)}
    perceptual = {"st_lpips": STLPIPS(device) if ev.st_lpips else None,
                  "lpips": lpips_metric(ev.lpips_backbone, device)}
    every = torch.arange(len(test))
    mouth = torch.as_tensor(mouth_open_subset(test.params["pose"][:, 6].numpy(), int(ev.mouth_open_frames)))
    report = {"all": scored(predictions, target, test.masks, perceptual, every),
              "mouth_open": scored(predictions, target, test.masks, perceptual, mouth)}
    if ev.face_metrics:
        report["ground_truth_face_detection_rate"] = add_face_metrics(report["all"], predictions, target, test,
                                                                      ft.subject_dir, size)
    for part in ("all", "mouth_open"):
        report[part]["gain"] = gains(report[part]["model"], report[part]["baselines"])
    report["same_recording"] = same_recording_scores(net, ft.subject_dir, split, train, size, perceptual,
                                                     bool(ev.face_metrics))
    report["trained"] = trained_frame_scores(net, ft.subject_dir, split.train, size, int(ev.trained_frames),
                                             perceptual)
    report["curve"] = quality_curve(Path(ev.model), content, report["all"]["model"], test, target, device,
                                    perceptual["st_lpips"])
    best = report["all"]["gain"]["psnr"]["best_baseline"]
    show = np.linspace(0, len(test) - 1, min(6, len(test))).round().astype(int)
    grid = torch.cat([torch.cat(list(row[show]), 2) for row in (target, predictions["model"], predictions[best])], 1)
    report.update({"subject": ft.subject, "init": ft.init_name, "recipe": ft.name, "frames_variant": ft.frames_variant,
                   "split": split.protocol, "test_indices": split.test.tolist(), "train_frames": len(split.train),
                   "image_size": size, "render_seconds_per_frame": seconds_per_frame, "step": int(content["step"]),
                   "trained_to": int(content.get("trained_to", content["step"])),
                   "validation_frames": len(split.validation),
                   "run_id": content.get("run_id"),
                   "perceptual": {k: (m.name if m is not None else None) for k, m in perceptual.items()}})
    return report, grid


def run_extras(report: dict, part: str) -> dict:
    """What the avatar's MLflow run gets beside the `part`'s scores: the render time, and with the test frames
    (`all`) the scores on its training frames as `trained_<metric>`."""
    extras = {"render_seconds_per_frame": report["render_seconds_per_frame"]}
    if part == "all" and report.get("trained"):
        extras.update({f"trained_{k}": v for k, v in report["trained"]["model"].items()})
    return extras


@entry_point(READS)
def main(cfg, device) -> None:
    report, grid = evaluate_avatar(cfg, device)
    out = Path(cfg.evaluate.out)
    rows = to_uint8(grid[None])[0]  # truth, avatar, best baseline, stacked
    height = rows.shape[0] // 3
    best = report["all"]["gain"]["psnr"]["best_baseline"]
    labels = ("truth", "avatar", f"best baseline: {best}")
    frames = report["test_indices"]
    shown = np.linspace(0, len(frames) - 1, rows.shape[1] // height).round().astype(int)
    write_png(out.with_name("test_frames.png"), labelled_grid(
        [(label, rows[i * height:(i + 1) * height]) for i, label in enumerate(labels)],
        [f"test frame {frames[i]}" for i in shown]))
    write_json(out, report)
    for part, prefix in (("all", "test_all"), ("mouth_open", "test_mouth_open"), ("same_recording",
                                                                                      "test_same_recording")):
        if report.get(part) is None:
            continue
        log_to_run(cfg, report["run_id"], report[part]["model"], report[part]["baselines"], report[part]["gain"],
                   prefix, artifact=out.with_name("test_frames.png") if part == "all" else None,
                   extra=run_extras(report, part))
    a, g = report["all"]["model"], report["all"]["gain"]["psnr"]
    log.info("avatar %s (%s): test PSNR %.2f dB vs best baseline %s %.2f dB (gain %+.2f), SSIM %.3f, ST-LPIPS %s, "
             "faces found %s, NME %s, identity %s", report["subject"], report["init"], a["psnr"], g["best_baseline"],
             g["baseline"], g["gain"], a["ssim"], a.get("st_lpips"), a.get("face_detection_rate"),
             a.get("landmark_nme"), a.get("identity_similarity"))
    if report["trained"] is not None:
        t = report["trained"]["model"]
        log.info("the same avatar on %d of its training frames: PSNR %.2f dB, SSIM %.3f (test: %.2f dB, %.3f)",
                 report["trained"]["frames"], t["psnr"], t["ssim"], a["psnr"], a["ssim"])
    if report["same_recording"] is not None:
        r, rg = report["same_recording"]["model"], report["same_recording"]["gain"]["psnr"]
        log.info("on %d later frames of its training recordings: PSNR %.2f dB vs best baseline %s %.2f dB (gain "
                 "%+.2f), SSIM %.3f", report["same_recording"]["frames"], r["psnr"], rg["best_baseline"],
                 rg["baseline"], rg["gain"], r["ssim"])


if __name__ == "__main__":
    main()
