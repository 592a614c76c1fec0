"""The training loop of the head model, shared by pretraining (strategies alpha1-beta6) and fine-tuning (avatars).

One iteration: draw a batch (synthetic with probability p(n), eq. 9; data/batches.py), assemble the codes with the
real samples' learnable offsets, render, compute eq. (8), step Adam. What differs between runs is a `Recipe`: the
schedule, the iterations, the learning rates, the z-augmentation, which codes have no offsets and how many MLP
layers stay frozen. Checkpoints every `checkpoint_every` iterations hold everything a resumed run needs to continue
exactly where it stopped (weights, optimiser, offsets, every RNG, the history and the time spent so far).
"""
from __future__ import annotations

import contextlib
import logging
import math
import time
from dataclasses import dataclass, field

import kornia
import torch
import torch.nn.functional as F

from avatarlab.data.batches import Batch, BatchSource, BatchStream
from avatarlab.data.schedule import Schedule
from avatarlab.metrics.quality import STLPIPSDistance
from avatarlab.model.head_nerf import HeadNeRFModel, assemble_codes
from avatarlab.model.losses import composite, head_model_loss
from avatarlab.runtime.config import autocast, grad_scaler
from avatarlab.runtime.errors import TrainingError
from avatarlab.training.checkpoint import Checkpoint

log = logging.getLogger(__name__)
OFFSET_KEYS = ("shape", "pose", "expression", "texture", "lighting")


@dataclass(frozen=True)
class Recipe:
    """What one training run does, from iteration `start` (exclusive) to `schedule.N`."""

    schedule: Schedule
    start: int
    batch: int
    lr: float  # the CNeRF MLP
    offset_lr: float  # eq. (8)'s per-sample offsets
    renderer_lr: float | None = None  # the 2D renderer (and the background feature); None: lr
    z_aug: bool = False
    z_aug_range: tuple[float, float] = (0.8, 1.2)
    fixed_codes: tuple[str, ...] = ()  # codes without learnable offsets (fine-tuning: the subject's shape, texture)
    freeze_layers: int = 0  # first CNeRF MLP layers kept as they are (fine-tuning: 4)
    w_mse: float = 1.0
    w_perceptual: float = 0.1
    w_mask: float = 0.0  # not in eq. (8): L1 between the feature map's opacity and the head mask (0: off)
    w_st_lpips: float = 0.0  # not in eq. (8): the ST-LPIPS distance between render and target (0: off)
    st_lpips_crop: int = 0  # that term on one window of this many pixels per sample (0: the whole image)
    st_lpips_decay: float = 0.0  # that term's weight falls linearly to (1 - this) x w_st_lpips at the last iteration
    st_lpips_net: str = "alex"  # that term's network: alex (the reported metric's own) | vgg (its VGG16 variant)
    w_distortion: float = 0.0  # not in eq. (8): Mip-NeRF 360's distortion loss on the rays' weights (0: off)
    offset_weights: dict = field(default_factory=dict)
    checkpoint_every: int = 25
    log_every: int = 25
    amp: bool = False
    mlp_precision: str = "float32"  # float32 | bfloat16: the CNeRF MLP alone under bfloat16 autocast (model section)
    snapshots: tuple[int, ...] = ()  # iterations after which the weights are handed to `on_snapshot`
    lr_decay: str = "none"  # none (constant rates) | cosine (every rate falls along a cosine from `start` to N)
    lr_final: float = 0.0  # cosine: the rates at N, as a fraction of the initial ones
    ema_decay: float = 0.0  # >0: the result (and the snapshots) are an exponential moving average of the weights,
    #                         ema = d * ema + (1 - d) * w after every iteration, started from the initial weights


LR_DECAYS = ("none", "cosine")
MLP_PRECISIONS = {"float32": None, "bfloat16": torch.bfloat16}


def lr_factor(recipe: Recipe, step: int) -> float:
    """The learning rates of iteration `step` (1-based) as a fraction of the recipe's: 1 (constant), or a cosine from
    1 at the first iteration after `start` to `lr_final` at the last. A function of the iteration alone, so a
    resumed run takes the same steps as an uninterrupted one. (The dissertation names Adam and no schedule.)"""
    if recipe.lr_decay == "none":
        return 1.0
    if recipe.lr_decay != "cosine":
        raise ValueError(f"lr_decay must be one of {LR_DECAYS}, got {recipe.lr_decay!r}")
    return recipe.lr_final + (1.0 - recipe.lr_final) * 0.5 * (1.0 + math.cos(math.pi * progress(recipe, step)))


def progress(recipe: Recipe, step: int) -> float:
    """How far iteration `step` (1-based) lies through the run: 0 at the first iteration after `start`, 1 at the
    last (clamped outside)."""
    span = recipe.schedule.N - recipe.start
    return min(max((step - 1 - recipe.start) / max(span - 1, 1), 0.0), 1.0)


@dataclass
class TrainResult:
    history: list[dict]  # one entry per iteration of this run, over all resumed segments
    seconds: float  # training time over all segments
    start: int
    step: int
    batch: int
    offsets: torch.nn.ParameterDict

    @property
    def samples_per_second(self) -> float:
        return (self.step - self.start) * self.batch / max(self.seconds, 1e-9)


class WeightAverage:
    """An exponential moving average of a network's floating-point weights and buffers (Polyak averaging): the
    weights of the last ~1 / (1 - decay) iterations averaged, so the result is not one noisy iterate. Not in the
    dissertation, which takes the last iterate; a setting of the fine-tuning recipe (README, "Weight averaging")."""

    def __init__(self, net: torch.nn.Module, decay: float, state: dict | None = None):
        if not 0.0 < decay < 1.0:
            raise ValueError(f"ema_decay must lie in (0, 1), got {decay}")
        self.decay = decay
        current = net.state_dict()
        self.names = [k for k, v in current.items() if v.is_floating_point()]
        source = state if state is not None else current
        self.values = {k: source[k].detach().clone().to(current[k]) for k in self.names}

    @torch.no_grad()
    def update(self, net: torch.nn.Module) -> None:
        current = net.state_dict()
        torch._foreach_lerp_([self.values[k] for k in self.names], [current[k] for k in self.names],
                             1.0 - self.decay)

    def state_dict(self) -> dict:
        return dict(self.values)

    @torch.no_grad()
    def copy_to(self, net: torch.nn.Module) -> None:
        net.load_state_dict(self.values, strict=False)

    @contextlib.contextmanager
    def swapped_in(self, net: torch.nn.Module):
        """The average in `net` for the block (e.g. a snapshot), the training weights back after it."""
        kept = {k: v.detach().clone() for k, v in net.state_dict().items() if k in self.values}
        self.copy_to(net)
        try:
            yield net
        finally:
            net.load_state_dict(kept, strict=False)


def offset_table(real_count: int, dims: dict[str, int], fixed, device) -> torch.nn.ParameterDict:
    """Eq. (8)'s learnable offsets: one row per real image for every code not in `fixed`."""
    return torch.nn.ParameterDict({k: torch.zeros(real_count, d) for k, d in dims.items()
                                   if k not in set(fixed)}).to(device)


def make_optimizer(net: HeadNeRFModel, offsets, recipe: Recipe, device) -> torch.optim.Adam:
    """Adam over the CNeRF MLP (lr), the 2D renderer (renderer_lr: a convolutional decoder learns ~10x faster with a
    larger step than the MLP tolerates) and the offsets (offset_lr); frozen layers are left out."""
    for p in net.nerf.frozen_prefix(recipe.freeze_layers):
        p.requires_grad_(False)
    decoder = [p for n, p in net.named_parameters() if not n.startswith("nerf.") and p.requires_grad]
    groups = [{"params": [p for p in net.nerf.parameters() if p.requires_grad]},
              {"params": decoder, "lr": recipe.renderer_lr or recipe.lr},
              {"params": list(offsets.parameters()), "lr": recipe.offset_lr}]
    return torch.optim.Adam(groups, lr=recipe.lr, fused=True if device.type in ("cpu", "cuda") else None)


def batch_offsets(batch: Batch, offsets) -> dict[str, torch.Tensor]:
    """Each sample's offsets: its real image's row, zero for synthetic samples."""
    real = batch.real_index >= 0
    rows = batch.real_index.clamp(min=0)
    return {k: offsets[k].index_select(0, rows) * real[:, None] for k in OFFSET_KEYS if k in offsets}


def st_lpips_weight(recipe: Recipe, step: int) -> float:
    """The ST-LPIPS term's weight at iteration `step` (1-based): `w_st_lpips` at the first iteration after `start`,
    falling linearly to (1 - `st_lpips_decay`) x `w_st_lpips` at the last. A function of the iteration alone (resumes
    take the same steps)."""
    return recipe.w_st_lpips * (1.0 - recipe.st_lpips_decay * progress(recipe, step))


def train_step(net, batch: Batch, offsets, features, optim, scaler, recipe: Recipe, device,
               st_lpips: STLPIPSDistance | None = None, step: int = 0) -> dict:
    """One iteration of eq. (8) (iteration `step`, 1-based): forward, loss, backward, Adam. -> the logged numbers."""
    off = batch_offsets(batch, offsets)
    geometry, appearance = assemble_codes(batch.params, batch.lighting, off)
    optim.zero_grad(set_to_none=True)
    with autocast(device, recipe.amp):  # low precision for the networks; the loss sums in float32
        pred, opacity, *distortion = net(geometry, appearance, batch.camera, with_opacity=True,
                                         with_distortion=recipe.w_distortion > 0)
        pred = pred.float()
        target = composite(batch.images, batch.masks)
        terms = head_model_loss(pred, target, batch.masks, features, off, recipe.offset_weights,
                                batch.real_index >= 0, recipe.w_mse, recipe.w_perceptual)
        if recipe.w_mask > 0:
            coverage = F.adaptive_avg_pool2d(batch.masks, opacity.shape[-2:])
            terms["mask"] = recipe.w_mask * (opacity.float() - coverage).abs().mean()
            terms["total"] = terms["total"] + terms["mask"]
        if recipe.w_distortion > 0:
            terms["distortion"] = recipe.w_distortion * distortion[0]
            terms["total"] = terms["total"] + terms["distortion"]
        if st_lpips is not None:
            terms["st_lpips"] = st_lpips_weight(recipe, step) * st_lpips.distance(pred, target, batch.masks)
            terms["total"] = terms["total"] + terms["st_lpips"]
    scaler.scale(terms["total"]).backward()
    scaler.step(optim)
    scaler.update()
    with torch.no_grad():
        psnr = float(kornia.metrics.psnr(composite(pred, batch.masks), target, 1.0))
    return {"loss": float(terms["total"].detach()), "mse": float(terms["mse"].detach()),
            "perceptual": float(terms["perceptual"].detach()),
            "offsets": float(terms["offsets"].detach()), "psnr": psnr, "p_synthetic": batch.p_synthetic,
            "n_synthetic": batch.n_synthetic,
            **({"st_lpips_term": float(terms["st_lpips"].detach())} if st_lpips is not None else {}),
            **({"distortion_term": float(terms["distortion"].detach())} if "distortion" in terms else {})}


def train(net: HeadNeRFModel, source: BatchSource, recipe: Recipe, features, device: torch.device,
          checkpoint: Checkpoint, seed: int, resume: dict | None = None, extra: dict | None = None,
          on_progress=None, on_snapshot=None) -> TrainResult:
    """Train `net` (already holding its initial or parent weights) by `recipe`, continuing `resume` (what
    `checkpoint.load()` returned) when given. `extra`: plain values kept in every checkpoint (e.g. the MLflow run
    id). `on_progress(entries)` receives the history entries of each segment between checkpoints (e.g. to log
    them), exactly once each, also across resumes. `on_snapshot(step, seconds)` is called after the iterations in
    `recipe.snapshots` (e.g. to save the weights for a quality-vs-time curve)."""
    dims = {"shape": source.real.params["shape"].shape[1], "pose": 12,
            "expression": source.real.params["expression"].shape[1],
            "texture": source.real.params["texture"].shape[1], "lighting": 27}
    offsets = offset_table(len(source.real), dims, recipe.fixed_codes, device)
    optim = make_optimizer(net, offsets, recipe, device)
    base_lrs = [group["lr"] for group in optim.param_groups]  # before a resumed state brings its decayed rates
    scaler = grad_scaler(device, recipe.amp)
    g = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    step, seconds, history = recipe.start, 0.0, []
    state = resume
    if state is not None:
        net.load_state_dict(state["model"])
        offsets.load_state_dict(state["offsets"])
        optim.load_state_dict(state["optim"])
        if state.get("scaler"):
            scaler.load_state_dict(state["scaler"])
        g.set_state(state["generator"])
        torch.set_rng_state(state["torch_rng"])
        step, seconds, history = int(state["step"]), float(state["seconds"]), list(state["history"])
    reported = len(history)
    saved_at = step if state is not None else None  # the iteration the checkpoint on disk holds
    ema = WeightAverage(net, recipe.ema_decay, (state or {}).get("ema")) if recipe.ema_decay > 0 else None
    stream = BatchStream(source, step, recipe.schedule.N, g)
    net.train()
    net.nerf.compute_dtype = MLP_PRECISIONS[recipe.mlp_precision]
    st_lpips = (STLPIPSDistance(recipe.st_lpips_crop, recipe.st_lpips_net).to(device) if recipe.w_st_lpips > 0
                else None)
    if st_lpips is not None:
        log.info("loss: + %g x %s (not in eq. 8; %s)", recipe.w_st_lpips, st_lpips.name,
                 "the reported ST-LPIPS is this network's" if st_lpips.net == "alex" else
                 "the reported ST-LPIPS is AlexNet's, not this network's")
    try:
        t0 = time.perf_counter()
        while step < recipe.schedule.N:
            factor = lr_factor(recipe, step + 1)
            for group, base in zip(optim.param_groups, base_lrs):
                group["lr"] = base * factor
            entry = train_step(net, stream.next(), offsets, features, optim, scaler, recipe, device, st_lpips,
                               step + 1)
            if not math.isfinite(entry["loss"]):
                kept = (f"the last checkpoint, of iteration {saved_at}, is kept in {checkpoint.path}"
                        if saved_at is not None else "no checkpoint was written yet")
                raise TrainingError(f"{checkpoint.path.parent}: training stopped at iteration {step + 1} of "
                                    f"{recipe.schedule.N}: the loss is {entry['loss']} (not finite; an input may hold a "
                                    f"NaN or an infinity, or the learning rate is too high); {kept}")
            step += 1
            if ema is not None:
                ema.update(net)
            history.append({"step": step, **entry, "lr_factor": factor})
            if step % max(1, recipe.log_every) == 0:
                log.info("it %d/%d p=%.2f loss %.4f psnr %.2f", step, recipe.schedule.N, entry["p_synthetic"],
                         entry["loss"], entry["psnr"])
            if on_snapshot is not None and step in recipe.snapshots:
                # a snapshot is scored as the evaluation scores the result: in float32
                with ema.swapped_in(net) if ema is not None else contextlib.nullcontext(), \
                        net.nerf.computing_in(None):
                    on_snapshot(step, seconds + time.perf_counter() - t0)
            if step % max(1, recipe.checkpoint_every) == 0 or step == recipe.schedule.N:
                seconds += time.perf_counter() - t0
                t0 = time.perf_counter()
                checkpoint.save({"model": net.state_dict(), "offsets": offsets.state_dict(),
                                 "optim": optim.state_dict(), "scaler": scaler.state_dict() if scaler.is_enabled()
                                 else None, "generator": stream.resume_state(), "torch_rng": torch.get_rng_state(),
                                 "step": step, "seconds": seconds, "history": history,
                                 "ema": ema.state_dict() if ema is not None else None, **(extra or {})})
                saved_at = step
                if on_progress is not None:
                    on_progress(history[reported:])
                reported = len(history)
    finally:
        stream.close()
        net.nerf.compute_dtype = None
    if ema is not None:
        ema.copy_to(net)
    net.eval()
    return TrainResult(history=history, seconds=seconds, start=recipe.start, step=step, batch=recipe.batch,
                       offsets=offsets)
