"""Training the XVFI-style frame interpolator self-supervised on frame triplets (predict the middle of three), with
checkpoints that let a killed run resume to the same result; and the frame bookkeeping of the interpolation
experiment (which frames variant (b) keeps, which it holds out). Used by `interp/pretrain.py` (the one training on
every video) and `interp/run.py` (the per-subject experiment).
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf
from tqdm import tqdm

from avatarlab.preprocess.interp.network import XVFILite
from avatarlab.runtime.config import CPU, autocast, grad_scaler
from avatarlab.runtime.io import atomic_path
from avatarlab.runtime.provenance import code_digest
from avatarlab.runtime.provenance import fingerprint as provenance_fingerprint
from avatarlab.runtime.safe_load import load_tensors

log = logging.getLogger(__name__)


def to_tensor(frames: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(frames).permute(0, 3, 1, 2).float() / 255


def split_variants(n: int, clips: np.ndarray | None = None):
    """Indices kept by variant (b) (the even ones) and the held-out frames between two kept ones; with `clips` (the
    clip index of each frame) only those whose two neighbours come from the same clip: a frame beside a cut between
    two recordings has no motion to interpolate."""
    kept = np.arange(0, n, 2)
    held = np.arange(1, n - 1, 2)
    if clips is not None:
        clips = np.asarray(clips)
        held = held[clips[held - 1] == clips[held + 1]]
    return kept, held


def training_triplets(kept: np.ndarray, strides=(1,), clips: np.ndarray | None = None) -> np.ndarray:
    """(left, middle, right) among the frames variant (b) keeps: neighbours `stride` kept frames apart, for every
    stride (several motion speeds); with `clips`, only triplets inside one clip."""
    out = [np.stack([kept[:-2 * s], kept[s:-s], kept[2 * s:]], 1) for s in strides if len(kept) > 2 * s]
    found = np.concatenate(out) if out else np.zeros((0, 3), int)
    if clips is not None and len(found):
        clips = np.asarray(clips)
        found = found[(clips[found[:, 0]] == clips[found[:, 1]]) & (clips[found[:, 1]] == clips[found[:, 2]])]
    return found


def validation_split(triplets: np.ndarray, every: int) -> tuple[np.ndarray, np.ndarray]:
    """(training, validation) triplets: every `every`-th triplet (0: none) is held out to choose the snapshot, and no
    training triplet has a validation triplet's middle frame as its own target (it may be one's input)."""
    triplets = np.asarray(triplets)
    if every <= 0 or len(triplets) < 2:
        return triplets, triplets[:0]
    validation = triplets[np.arange(len(triplets)) % every == every // 2]
    return triplets[~np.isin(triplets[:, 1], validation[:, 1])], validation


@torch.no_grad()
def validation_psnr(model: XVFILite, frames: torch.Tensor, validation: np.ndarray, device: torch.device,
                    groups: np.ndarray | None = None) -> float:
    """The mean over groups (videos) of the PSNR over each group's validation triplets' middle frames (one mean
    squared error per group), so a hard video's large errors do not decide alone; the network in eval mode, then
    back in the mode it was in."""
    training = model.training
    model.eval()
    groups = np.zeros(len(validation), int) if groups is None else np.asarray(groups)
    squared = np.zeros(len(validation))
    for k in range(0, len(validation), 8):
        pick = validation[k:k + 8]
        a, mid, b = (frames[pick[:, j]].to(device) for j in range(3))
        squared[k:k + 8] = ((model(a, b, 0.5).float() - mid) ** 2).flatten(1).mean(1).cpu().numpy()
    model.train(training)
    return float(np.mean([10 * np.log10(1.0 / max(squared[groups == g].mean(), 1e-12)) for g in np.unique(groups)]))


def flow_lengths(candidates, name: str) -> list[float]:
    """Still-flow candidates as floats; a negative length stops with a line naming the setting `name`."""
    lengths = [float(c) for c in candidates]
    if any(c < 0 for c in lengths):
        raise ValueError(f"{name}: a flow length in pixels is >= 0, got {lengths}")
    return lengths


def choose_still_flow(model: XVFILite, frames: torch.Tensor, validation: np.ndarray, device: torch.device,
                      groups: np.ndarray | None, candidates,
                      name: str = "interp.still_flow_candidates") -> list[list[float]]:
    """Sets the model's `still_flow_px` to the candidate that scores best on the validation triplets (the first
    candidate without validation triplets) -> [[candidate, validation PSNR], ...] (empty without them). `name`: the
    setting the candidates come from, for the error."""
    candidates = flow_lengths(candidates, name) or [0.0]
    model.still_flow_px = candidates[0]
    if len(validation) == 0:
        return []
    scores = []
    for c in candidates:
        model.still_flow_px = c
        scores.append([c, validation_psnr(model, frames, validation, device, groups)])
    model.still_flow_px = max(scores, key=lambda cs: cs[1])[0]
    return scores


def train(frames: torch.Tensor, triplets: np.ndarray, cfg, checkpoint: Path,
          device: torch.device = CPU, data: dict | None = None,
          validation: np.ndarray | None = None,
          validation_groups: np.ndarray | None = None) -> tuple[XVFILite, list[float], dict]:
    """Trains on `device` (frames stay where they are; each batch moves), with mixed precision if `cfg.amp`.
    The loss is `interp.loss`: the mean absolute error (l1, XVFI's) or the mean squared error (l2, what PSNR
    scores; it hedged towards blur over three seeds, so l1 is the default).
    With `validation` triplets (and their videos, `validation_groups`), scores the network on them before training
    and at every checkpoint, and returns the best-scoring snapshot (before training it is its starting point: the
    Farneback flows' blend), so training can only improve on where it started as far as frames it never trained to
    predict can tell; without, the last iterate.
    The checkpoint resumes only the same work: settings, code and the data files in `data` (their digests).
    -> (model, training losses, {"curve": [[step, validation PSNR], ...], "best_step": ..., "best_psnr": ...})"""
    torch.manual_seed(int(cfg.seed))
    model = XVFILite(int(cfg.interp.width), int(cfg.interp.scales), str(cfg.interp.flow_init),
                     bool(cfg.interp.keep_unwarped)).to(device)
    optim = torch.optim.Adam(model.parameters(), lr=float(cfg.interp.lr))
    amp = bool(cfg.get("amp", False))
    scaler = grad_scaler(device, amp)
    rng = np.random.default_rng(int(cfg.seed))
    validation = np.zeros((0, 3), int) if validation is None else np.asarray(validation)
    step, losses, curve, best = 0, [], [], None
    settings = {"interp": OmegaConf.to_container(cfg.interp, resolve=True), "seed": int(cfg.seed), "amp": amp,
                "frames": len(frames), "triplets": np.asarray(triplets).tolist(), "validation": validation.tolist(),
                "validation_groups": None if validation_groups is None else np.asarray(validation_groups).tolist()}
    fingerprint = provenance_fingerprint(settings, code_digest(__spec__.name if __spec__ else __name__), data or {})
    state = load_tensors(checkpoint, "an interpolation checkpoint") if checkpoint.is_file() else None
    if state is not None and state.get("fingerprint") != fingerprint:
        log.warning("%s belongs to other settings, code or data: starting afresh", checkpoint)
        state = None
    if state is not None:
        model.load_state_dict(state["model"])
        optim.load_state_dict(state["optim"])
        if state.get("scaler"):
            scaler.load_state_dict(state["scaler"])
        rng.bit_generator.state = state["rng"]
        torch.set_rng_state(state["torch_rng"].cpu())
        step, losses = state["step"], state["losses"]
        curve, best = state.get("curve", []), state.get("best")
        log.info("resuming interpolation training at step %d from %s", step, checkpoint)

    def score() -> None:
        nonlocal best
        if len(validation) == 0:
            return
        value = validation_psnr(model, frames, validation, device, validation_groups)
        curve.append([step, value])
        if best is None or value > best["psnr"]:
            best = {"step": step, "psnr": value, "model": {k: v.detach().clone() for k, v in model.state_dict().items()}}

    if step == 0:
        score()
    iterations, every = int(cfg.interp.iterations), int(cfg.interp.checkpoint_every)
    batch = int(cfg.interp.batch)
    loss_kind = str(cfg.interp.loss)
    if loss_kind not in ("l1", "l2"):
        raise ValueError(f"interp.loss must be l1 or l2, got {loss_kind!r}")
    with tqdm(total=iterations, initial=step, desc="xvfi", unit="it", disable=None) as bar:
        while step < iterations and len(triplets):
            pick = triplets[rng.integers(0, len(triplets), batch)]
            a, mid, b = (frames[pick[:, k]].to(device) for k in range(3))
            if rng.random() < 0.5:  # time reversal and mirror: the same task seen differently
                a, b = b, a
            if rng.random() < 0.5:
                a, mid, b = (x.flip(-1) for x in (a, mid, b))
            optim.zero_grad()
            with autocast(device, amp):
                error = model(a, b, 0.5).float() - mid
                loss = error.square().mean() if loss_kind == "l2" else error.abs().mean()
            scaler.scale(loss).backward()
            scaler.step(optim)
            scaler.update()
            losses.append(float(loss.detach()))
            step += 1
            bar.update(1)
            if step % every == 0 or step == iterations:
                score()
                with atomic_path(checkpoint) as tmp:
                    torch.save({"model": model.state_dict(), "optim": optim.state_dict(), "rng": rng.bit_generator.state,
                                "torch_rng": torch.get_rng_state(), "step": step, "losses": losses,
                                "scaler": scaler.state_dict() if scaler.is_enabled() else None,
                                "curve": curve, "best": best, "fingerprint": fingerprint}, tmp)
    if best is not None:
        model.load_state_dict(best["model"])
    chosen = {"curve": curve, "best_step": best["step"] if best else None, "best_psnr": best["psnr"] if best else None}
    return model, losses, chosen
