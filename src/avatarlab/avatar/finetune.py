"""Per-subject avatar: a pretrained head model fine-tuned on one subject's video (seed 002, section 4.1).

The recipe is the `finetune` config group: `base` (the ablation fine-tunes of sections 4.2-4.3: real frames only)
or `final` (the final recipe: + z-augmentation and a synthetic share decaying linearly to 0, its synthetic samples
from the head the pretrained model ended with: the mouth interior for alpha2 and the betas from it). Both keep the
subject's fitted shape and texture fixed (no offsets) and the first CNeRF MLP layers frozen. The test frames
(data/splits.py) are never trained on; scoring them is the evaluation step's job (avatar/evaluate.py).
With a validation split (`finetune.validation_frames` / `validation_clips`; not in the dissertation, off unless
asked for) the snapshots and the end of training are scored on the validation frames and the best becomes the
avatar: the stop is chosen on held-out frames, never on the test frames.
Writes `model.pt` and `train.json`.
`python -m avatarlab.avatar.finetune finetune=final finetune.subject_dir=... finetune.init_model=.../model.pt`
"""
from __future__ import annotations

import logging
import shutil
from pathlib import Path

import torch
from omegaconf import OmegaConf

from avatarlab.data.batches import BatchSource
from avatarlab.data.real_images import RealImageSet
from avatarlab.data.schedule import Schedule
from avatarlab.data.splits import avatar_split
from avatarlab.data.synthetic import SyntheticGenerator
from avatarlab.headmodel import load_head_model
from avatarlab.metrics.quality import STLPIPS, psnr
from avatarlab.model.head_nerf import load_model_file, model_file, render_frames, synthetic_mouth
from avatarlab.model.losses import composite, perceptual_network
from avatarlab.runtime.entry import entry_point, step_settings
from avatarlab.runtime.io import atomic_path, write_json
from avatarlab.runtime.provenance import code_digest, fingerprint
from avatarlab.runtime.tracking import log_history, start_run
from avatarlab.training.checkpoint import Checkpoint
from avatarlab.training.loop import Recipe, train

log = logging.getLogger(__name__)
READS = ("seed", "amp", "head_model", "render", "model", "synthetic", "finetune", "tracking")


def recipe_of(cfg, start: int) -> Recipe:
    ft, m = cfg.finetune, cfg.model
    schedule = Schedule(M=start, N=start + int(ft.iterations), p_min=0.0, p_max=float(ft.p_max), mouth_from=None)
    count = int(ft.snapshots)  # evenly spaced, the last one being the final model
    snapshots = tuple(sorted({start + round(int(ft.iterations) * k / count) for k in range(1, count)})) if count > 1 \
        else ()
    return Recipe(schedule=schedule, start=start, batch=int(ft.batch), lr=float(ft.lr), offset_lr=float(ft.offset_lr),
                  renderer_lr=float(ft.renderer_lr),
                  z_aug=bool(ft.z_aug), z_aug_range=tuple(ft.z_aug_range), fixed_codes=tuple(ft.fixed_codes),
                  freeze_layers=int(ft.freeze_layers), w_mse=float(m.w_mse), w_perceptual=float(m.w_perceptual),
                  w_mask=float(m.w_mask), w_st_lpips=float(ft.w_st_lpips), st_lpips_crop=int(ft.st_lpips_crop),
                  st_lpips_decay=float(ft.st_lpips_decay), st_lpips_net=str(ft.st_lpips_net),
                  w_distortion=float(ft.w_distortion),
                  offset_weights=dict(m.offset_weights), checkpoint_every=int(ft.checkpoint_every),
                  log_every=int(ft.log_every), amp=bool(cfg.amp), mlp_precision=str(m.mlp_precision),
                  snapshots=snapshots, lr_decay=str(ft.lr_decay),
                  lr_final=float(ft.lr_final), ema_decay=float(ft.ema_decay))


@torch.no_grad()
def choose_stop(net, snapshot_dir: Path, validation: RealImageSet, end_step: int, end_seconds: float,
                device) -> dict:
    """Scores every snapshot and the end of training (`net`) on the validation frames (PSNR, eq. 10, of the render
    composited into the frame's mask, as the evaluation scores test frames; ST-LPIPS beside it, recorded, not
    chosen on) -> {"scores": [{step, seconds, psnr, st_lpips}] in step order, "step", "seconds", "psnr" of the best
    PSNR (the earliest on a tie), "state": its weights (None: the end of training)}."""
    target = composite(validation.images, validation.masks)
    st_lpips = STLPIPS(device)

    def score(model) -> dict:
        pred = composite(render_frames(model, validation), validation.masks)
        return {"psnr": psnr(pred, target), "st_lpips": st_lpips(pred, target)}

    candidates = []
    for path in sorted(snapshot_dir.glob("step_*.pt")):
        model, content = load_model_file(path, device)
        if int(content["step"]) < end_step:  # (a resumed run's copy of the end of training is the end itself)
            candidates.append({"step": int(content["step"]), "seconds": content.get("seconds"), **score(model),
                               "state": content["state"]})
    candidates.append({"step": end_step, "seconds": end_seconds, **score(net.eval()), "state": None})
    best = max(candidates, key=lambda c: (c["psnr"], -c["step"]))
    return {"scores": [{k: c[k] for k in ("step", "seconds", "psnr", "st_lpips")} for c in candidates],
            "step": best["step"], "seconds": best["seconds"], "psnr": best["psnr"], "st_lpips": best["st_lpips"],
            "state": best["state"]}


def finetune_avatar(cfg, device):
    """One fine-tuning run from a step config (the READS sections): trains, writes model.pt, snapshots and
    train.json, deletes its checkpoint. -> (net, TrainResult, the train.json contents)."""
    ft = cfg.finetune
    out_dir = Path(ft.out_dir)
    split = avatar_split(ft)
    net, parent = load_model_file(ft.init_model, device)
    size = int(parent["spec"]["feature_size"]) * 8
    real = RealImageSet(ft.subject_dir, size, split.train, ft.interpolated if ft.frames_variant == "c" else None)
    recipe = recipe_of(cfg, int(parent["step"]))
    synthetic, mouth = None, synthetic_mouth(parent)
    if recipe.schedule.p_max > 0:  # the head the parent's synthetic samples ended with (the mouth after alpha2)
        synthetic = SyntheticGenerator(load_head_model(cfg.head_model, mouth_interior=mouth), real.params,
                                       cfg.synthetic, size, tuple(cfg.render.background), device, fixed_identity=True)
    source = BatchSource(synthetic=synthetic, real=real, schedule=recipe.schedule, batch_size=recipe.batch,
                         device=device, z_aug=recipe.z_aug, z_aug_range=recipe.z_aug_range)
    settings = step_settings(cfg, tuple(k for k in READS if k != "tracking"))
    subject = Path(ft.subject_dir)
    data = {"fit": subject / "fit_rgb.npz", "masks": subject / "masks.npz", "frames": subject / "frames.json",
            "parent": ft.init_model, "interpolated": ft.interpolated if ft.frames_variant == "c" else None}
    checkpoint = Checkpoint(out_dir / "checkpoint.pt", fingerprint(settings, code_digest(__spec__.name), data))
    resume = checkpoint.load()
    if resume is None:  # a fresh run: no snapshot of an earlier run may join this one's curve
        shutil.rmtree(out_dir / "snapshots", ignore_errors=True)
    run_name = (f"{ft.subject}/{ft.init_name}" + ("" if ft.frames_variant == "a" else f"/frames_{ft.frames_variant}")
                + (f"/seed{cfg.seed}" if int(cfg.seed) else ""))
    tags = {"subject": ft.subject, "init": ft.init_name, "recipe": ft.name, "renderer": parent["spec"]["renderer"],
            "frames_variant": ft.frames_variant, "seed": int(cfg.seed)}
    with start_run(cfg, "finetune", run_name, tags, run_id=(resume or {}).get("run_id"), output=out_dir) as run:
        run_id = run.info.run_id if run is not None else None
        if run is not None and resume is None:
            import mlflow

            mlflow.log_params({"init": ft.init_name, "recipe": ft.name, "subject": ft.subject,
                               "frames_variant": ft.frames_variant, "train_frames": len(split.train),
                               "test_frames": len(split.test), "validation_frames": len(split.validation),
                               "split": split.protocol, "iterations": ft.iterations,
                               "lr": recipe.lr, "z_aug": recipe.z_aug, "p_max": recipe.schedule.p_max,
                               "image_size": size})
        config = OmegaConf.to_container(cfg, resolve=True)

        def snapshot(step: int, seconds: float) -> None:  # weights part-way, for the quality-vs-time curve
            with atomic_path(out_dir / "snapshots" / f"step_{step:07d}.pt") as tmp:
                torch.save(model_file(net, step, config, seconds=seconds, run_id=run_id, stage="finetune"), tmp)

        result = train(net, source, recipe, perceptual_network(cfg.model.vgg16_weights).to(device), device,
                       checkpoint, int(cfg.seed), resume, extra={"run_id": run_id},
                       on_progress=lambda entries: log_history(run, entries), on_snapshot=snapshot)
        stop = {"step": result.step, "seconds": result.seconds}
        if len(split.validation):
            validation = RealImageSet(ft.subject_dir, size, split.validation)
            stop = choose_stop(net, out_dir / "snapshots", validation, result.step, result.seconds, device)
            log.info("validation PSNR (ST-LPIPS) on %d held-out frames: %s -> the avatar is step %d", len(validation),
                     ", ".join(f"{c['step']}: {c['psnr']:.2f} ({c['st_lpips']:.3f})" for c in stop["scores"]),
                     stop["step"])
            if stop["state"] is not None:  # an earlier snapshot wins: keep the end of training on the curve
                snapshot(result.step, result.seconds)
                net.load_state_dict(stop["state"])
        with atomic_path(out_dir / "model.pt") as tmp:
            torch.save(model_file(net, stop["step"], config, name=run_name, run_id=run_id, stage="finetune",
                                  seconds=stop["seconds"], synthetic_mouth=mouth, trained_to=result.step), tmp)
        report = {"subject": ft.subject, "init": ft.init_name, "recipe": ft.name, "frames_variant": ft.frames_variant,
                  "split": split.protocol, "train_frames": len(split.train), "train_indices": split.train.tolist(),
                  "test_indices": split.test.tolist(), "iterations": result.step - recipe.start,
                  "validation_indices": split.validation.tolist(), "chosen_step": stop["step"],
                  "validation_psnr": stop.get("psnr"), "validation_st_lpips": stop.get("st_lpips"),
                  "validation_scores": stop.get("scores", []),
                  "train_seconds": result.seconds, "samples_per_second": result.samples_per_second,
                  "synthetic_samples": "none" if synthetic is None else ("mouth interior" if mouth else "plain head"),
                  "history": result.history, "run_id": run_id}
        write_json(out_dir / "train.json", report)
        if run is not None:
            import mlflow

            mlflow.log_metrics({"train_seconds": result.seconds, "samples_per_second": result.samples_per_second,
                                **({"chosen_step": stop["step"], "validation_psnr": stop["psnr"],
                                       "validation_st_lpips": stop["st_lpips"]} if "psnr" in stop else {})})
    checkpoint.remove()
    return net, result, report


@entry_point(READS)
def main(cfg, device) -> None:
    _, result, report = finetune_avatar(cfg, device)
    log.info("avatar %s from %s (%s recipe): %d train / %d test frames, %d iterations in %.0f s", report["subject"],
             report["init"], report["recipe"], report["train_frames"], len(report["test_indices"]),
             report["iterations"], result.seconds)


if __name__ == "__main__":
    main()
