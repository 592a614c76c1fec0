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

from avatarlab.config import CPU, autocast, grad_scaler
from avatarlab.io import atomic_path
from avatarlab.preprocess.interp.network import XVFILite
from avatarlab.provenance import code_digest
from avatarlab.provenance import fingerprint as provenance_fingerprint
from avatarlab.safe_load import load_tensors

log = logging.getLogger(__name__)


def to_tensor(frames: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(frames).permute(0, 3, 1, 2).float() / 255


def split_variants(n: int):
    """Indices kept by variant (b) and the held-out frames between two kept ones."""
    kept = np.arange(0, n, 2)
    held = np.arange(1, n - 1, 2)
    return kept, held


def training_triplets(kept: np.ndarray, strides=(1,)) -> np.ndarray:
    """(left, middle, right) among the frames variant (b) keeps: neighbours `stride` kept frames apart, for every
    stride (several motion speeds)."""
    out = [np.stack([kept[:-2 * s], kept[s:-s], kept[2 * s:]], 1) for s in strides if len(kept) > 2 * s]
    return np.concatenate(out) if out else np.zeros((0, 3), int)


def train(frames: torch.Tensor, triplets: np.ndarray, cfg, checkpoint: Path,
          device: torch.device = CPU, data: dict | None = None) -> tuple[XVFILite, list[float]]:
    """Trains on `device` (frames stay where they are; each batch moves), with mixed precision if `cfg.amp`.
    The checkpoint resumes only the same work: settings, code and the data files in `data` (their digests)."""
    torch.manual_seed(int(cfg.seed))
    model = XVFILite(int(cfg.interp.width), int(cfg.interp.scales), str(cfg.interp.flow_init)).to(device)
    optim = torch.optim.Adam(model.parameters(), lr=float(cfg.interp.lr))
    amp = bool(cfg.get("amp", False))
    scaler = grad_scaler(device, amp)
    rng = np.random.default_rng(int(cfg.seed))
    step, losses = 0, []
    settings = {"interp": OmegaConf.to_container(cfg.interp, resolve=True), "seed": int(cfg.seed), "amp": amp,
                "frames": len(frames), "triplets": np.asarray(triplets).tolist()}
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
        log.info("resuming interpolation training at step %d from %s", step, checkpoint)
    iterations, every = int(cfg.interp.iterations), int(cfg.interp.checkpoint_every)
    batch = int(cfg.interp.batch)
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
                loss = (model(a, b, 0.5).float() - mid).abs().mean()
            scaler.scale(loss).backward()
            scaler.step(optim)
            scaler.update()
            losses.append(float(loss.detach()))
            step += 1
            bar.update(1)
            if step % every == 0 or step == iterations:
                with atomic_path(checkpoint) as tmp:
                    torch.save({"model": model.state_dict(), "optim": optim.state_dict(), "rng": rng.bit_generator.state,
                                "torch_rng": torch.get_rng_state(), "step": step, "losses": losses,
                                "scaler": scaler.state_dict() if scaler.is_enabled() else None,
                                "fingerprint": fingerprint}, tmp)
    return model, losses
