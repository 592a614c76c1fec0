"""Pretraining of the parametric head model (CNeRF + 2D neural renderer) under a strategy (seed 002, 3.3-3.4).

Each iteration draws a batch whose samples are synthetic with probability p(n) (eq. 9) and real otherwise (the real
image set: its frames, masks and per-image RGB fits); the loop is training/loop.py. alpha1/alpha2 train from scratch
(alpha2 renders its synthetic samples with the mouth-interior head from `mouth_from` on); a beta strategy continues
its alpha model (`pretrain.init_model`) from iteration M with real images, the synthetic share of its schedule and
z-augmentation, its synthetic samples from the head its parent ended with (the mouth interior after alpha2). `pretrain.iterations` sets a fixed synthetic-only budget instead (the renderer experiment).
Writes `model.pt` and `train.json` (history, time, samples/s); scoring is the evaluation step's job.
`python -m avatarlab.pretrain.train strategy=beta6 pretrain.init_model=.../alpha2/model.pt`
"""
from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import torch
from omegaconf import OmegaConf

from avatarlab.data.batches import BatchSource
from avatarlab.data.real_images import RealImageSet
from avatarlab.data.schedule import Schedule, scaled_schedule
from avatarlab.data.synthetic import SyntheticGenerator
from avatarlab.headmodel import load_head_model
from avatarlab.model.head_nerf import build_model, load_model_file, model_file, synthetic_mouth
from avatarlab.model.losses import perceptual_network
from avatarlab.runtime.entry import ConfigError, entry_point, step_settings
from avatarlab.runtime.io import atomic_path, write_json
from avatarlab.runtime.provenance import code_digest, fingerprint
from avatarlab.runtime.tracking import log_history, start_run
from avatarlab.training.checkpoint import Checkpoint
from avatarlab.training.loop import Recipe, train

log = logging.getLogger(__name__)
READS = ("seed", "amp", "head_model", "render", "model", "synthetic", "strategy", "pretrain", "tracking")


def strategy_schedule(strategy, pre) -> Schedule:
    """The strategy's M, N, p_min, p_max (and alpha2's mouth phase) at this scale, or a fixed synthetic-only
    budget (`pretrain.iterations`)."""
    if pre.iterations is not None:
        n = int(pre.iterations)
        return Schedule(M=n, N=n, p_min=1.0, p_max=1.0, mouth_from=None)
    return scaled_schedule(strategy, int(pre.alpha_iterations), int(pre.beta_iterations))


def recipe_of(cfg, schedule: Schedule, start: int) -> Recipe:
    pre, m = cfg.pretrain, cfg.model
    return Recipe(schedule=schedule, start=start, batch=int(pre.batch), lr=float(pre.lr),
                  offset_lr=float(pre.offset_lr), renderer_lr=float(pre.renderer_lr), z_aug=bool(cfg.strategy.z_aug),
                  z_aug_range=tuple(pre.z_aug_range), w_mse=float(m.w_mse), w_perceptual=float(m.w_perceptual),
                  w_mask=float(m.w_mask),
                  offset_weights=dict(m.offset_weights), checkpoint_every=int(pre.checkpoint_every),
                  log_every=int(pre.log_every), amp=bool(cfg.amp), mlp_precision=str(m.mlp_precision),
                  lr_decay=str(pre.lr_decay), lr_final=float(pre.lr_final), ema_decay=float(pre.ema_decay))


def pretrain_model(cfg, device):
    """One pretraining run from a step config (the READS sections): trains, writes model.pt and train.json,
    deletes its checkpoint. -> (net, TrainResult, the train.json contents)."""
    pre, strategy = cfg.pretrain, cfg.strategy
    name = pre.name or strategy.name
    out_dir = Path(pre.out_dir)
    head = load_head_model(cfg.head_model)
    schedule = strategy_schedule(strategy, pre)
    size = int(cfg.model.image_size)
    real = RealImageSet(pre.real_subject_dir, size)
    background = tuple(cfg.render.background)
    synthetic = SyntheticGenerator(head, real.params, cfg.synthetic, size, background, device)
    mouth = None

    def mouth_generator():
        return SyntheticGenerator(load_head_model(cfg.head_model, mouth_interior=True), real.params, cfg.synthetic,
                                  size, background, device)

    if schedule.mouth_from is not None:
        mouth = mouth_generator()
    torch.manual_seed(int(cfg.seed))
    net = build_model(cfg, head).to(device)
    start, init_name = 0, ""
    if strategy.init is not None and pre.iterations is None:  # a beta strategy continues its alpha model
        parent, content = load_model_file(pre.init_model, device)
        if int(content["step"]) != schedule.M:
            raise ConfigError(f"{pre.init_model}: the parent stopped at iteration {content['step']}, strategy "
                              f"{strategy.name} continues from M = {schedule.M} (trained with another alpha budget?)")
        net.load_state_dict(parent.state_dict())
        start, init_name = schedule.M, str(content.get("name") or strategy.init)
        if synthetic_mouth(content) and mouth is None:  # continuing alpha2: its synthetic samples keep the mouth
            schedule, mouth = dataclasses.replace(schedule, mouth_from=start - 1), mouth_generator()
        log.info("%s continues %s from iteration %d%s", name, pre.init_model, start,
                 " (synthetic samples with the mouth interior, as its parent's)" if mouth is not None else "")
    recipe = recipe_of(cfg, schedule, start)
    source = BatchSource(synthetic=synthetic, real=real, schedule=schedule, batch_size=recipe.batch, device=device,
                         z_aug=recipe.z_aug, z_aug_range=recipe.z_aug_range, synthetic_mouth=mouth)
    settings = step_settings(cfg, tuple(k for k in READS if k != "tracking"))
    data = {"fit": Path(pre.real_subject_dir) / "fit_rgb.npz", "masks": Path(pre.real_subject_dir) / "masks.npz",
            "frames": Path(pre.real_subject_dir) / "frames.json", "parent": pre.init_model if start else None}
    checkpoint = Checkpoint(out_dir / "checkpoint.pt", fingerprint(settings, code_digest(__spec__.name), data))
    resume = checkpoint.load()
    tags = {"strategy": name, "renderer": cfg.model.renderer, "init": init_name, "seed": int(cfg.seed)}
    with start_run(cfg, "pretrain", name, tags, run_id=(resume or {}).get("run_id"), output=out_dir) as run:
        run_id = run.info.run_id if run is not None else None
        if run is not None and resume is None:
            import mlflow

            mlflow.log_params({"M": schedule.M, "N": schedule.N, "p_min": schedule.p_min, "p_max": schedule.p_max,
                               "z_aug": recipe.z_aug, "batch": recipe.batch, "lr": recipe.lr, "image_size": size,
                               "renderer": cfg.model.renderer, "amp": recipe.amp})
        result = train(net, source, recipe, perceptual_network(cfg.model.vgg16_weights).to(device), device,
                       checkpoint, int(cfg.seed), resume, extra={"run_id": run_id},
                       on_progress=lambda entries: log_history(run, entries))
        config = OmegaConf.to_container(cfg, resolve=True)
        with atomic_path(out_dir / "model.pt") as tmp:
            torch.save(model_file(net, result.step, config, name=name, run_id=run_id, stage="pretrain",
                                  synthetic_mouth=mouth is not None), tmp)
        report = {"name": name, "strategy": strategy.name, "init": init_name, "mouth_from": schedule.mouth_from,
                  "renderer": cfg.model.renderer, "M": schedule.M,
                  "N": schedule.N, "start_step": start, "iterations": result.step - start, "seconds": result.seconds,
                  "samples_per_second": result.samples_per_second, "batch": recipe.batch, "image_size": size,
                  "history": result.history, "run_id": run_id}
        write_json(out_dir / "train.json", report)
        if run is not None:
            import mlflow

            mlflow.log_metrics({"train_seconds": result.seconds, "samples_per_second": result.samples_per_second})
    checkpoint.remove()
    return net, result, report


@entry_point(READS)
def main(cfg, device) -> None:
    _, result, report = pretrain_model(cfg, device)
    log.info("%s: %d iterations (%d..%d) in %.0f s, %.1f samples/s", report["name"], report["iterations"],
             result.start, result.step, result.seconds, result.samples_per_second)


if __name__ == "__main__":
    main()
