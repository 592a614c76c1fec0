"""The thesis' interpolation experiment on one subject (seed 002, section 4.3 / figure 54).

Variants of the training frames: (a) all frames, (b) every second frame removed, (c) (b) plus the removed frames
re-created by interpolation. The XVFI-style network is the one trained once on every subject's video
(`interp/pretrain.py`, self-supervised on the frames that (b) keeps: predict the middle of three); here it fills the
removed frames, and the Farneback baseline and a plain cross-fade do the same. Interpolation PSNR/SSIM are measured
on the removed (held-out) frames. Writes `interp.json`, `interpolated.npz` (variant (c)'s new frames) and a
comparison PNG. `train` (with checkpoints that let a killed run resume to the same result) serves the shared
training.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import kornia
import numpy as np
import torch
from omegaconf import OmegaConf
from tqdm import tqdm

from avatarlab.config import CPU, autocast, grad_scaler
from avatarlab.data.subject_dir import SubjectDir
from avatarlab.entry import entry_point
from avatarlab.io import atomic_path, write_json, write_png
from avatarlab.preprocess.interp.network import XVFILite, load_interpolator
from avatarlab.preprocess.interp.optical_flow import interpolate_farneback
from avatarlab.provenance import code_digest
from avatarlab.provenance import fingerprint as provenance_fingerprint
from avatarlab.safe_load import load_tensors

log = logging.getLogger(__name__)
READS = ('seed', 'amp', 'preprocess', 'interp')  # the config sections this step reads (avatarlab/entry.py)


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
    model = XVFILite(int(cfg.interp.width), int(cfg.interp.scales)).to(device)
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


def quality(pred: torch.Tensor, target: torch.Tensor) -> dict[str, float]:
    return {"psnr": float(kornia.metrics.psnr(pred, target, 1.0)),
            "ssim": float(kornia.metrics.ssim(pred, target, 11).mean())}


@entry_point(READS)
def main(cfg, device) -> None:
    subject_dir = Path(cfg.preprocess.subject_dir)
    frames_np = SubjectDir(subject_dir).frames()
    frames = to_tensor(frames_np)
    kept, held = split_variants(len(frames))
    if len(held) == 0:
        raise ValueError(f"{subject_dir}: {len(frames)} frames are too few to hold any frame out")
    model = load_interpolator(cfg.interp.model, device)
    start = time.perf_counter()
    with torch.no_grad():
        xvfi = torch.cat([model(frames[held - 1][k:k + 8].to(device), frames[held + 1][k:k + 8].to(device)).cpu()
                          for k in range(0, len(held), 8)])
    seconds = time.perf_counter() - start
    flow = to_tensor(np.stack([interpolate_farneback(frames_np[i - 1], frames_np[i + 1]) for i in held]))
    fade = 0.5 * (frames[held - 1] + frames[held + 1])
    target = frames[held]
    report = {"frames": len(frames), "kept_b": len(kept), "held_out": len(held), "model": str(cfg.interp.model),
              "seconds_per_frame": seconds / len(held),
              "xvfi": quality(xvfi, target), "farneback": quality(flow, target), "cross_fade": quality(fade, target),
              "variants": {"a": len(frames), "b": len(kept), "c": len(kept) + len(held)}}
    out_u8 = (xvfi.permute(0, 2, 3, 1).numpy() * 255).round().astype(np.uint8)
    with atomic_path(subject_dir / "interpolated.npz") as tmp:
        np.savez_compressed(tmp, indices=held, frames=out_u8, kept=kept)
    show = np.linspace(0, len(held) - 1, min(3, len(held))).round().astype(int)
    rows = [np.concatenate([frames_np[held[k]], out_u8[k], (flow[k].permute(1, 2, 0).numpy() * 255).astype(np.uint8)],
                           1) for k in show]
    write_png(subject_dir / "interp_comparison.png", np.concatenate(rows, 0))
    write_json(subject_dir / "interp.json", report)
    log.info("interpolation on %d held-out frames: XVFI-style PSNR %.2f dB SSIM %.4f | Farneback %.2f / %.4f | "
             "cross-fade %.2f / %.4f (the shared network %s)", len(held), report["xvfi"]["psnr"],
             report["xvfi"]["ssim"], report["farneback"]["psnr"], report["farneback"]["ssim"],
             report["cross_fade"]["psnr"], report["cross_fade"]["ssim"], cfg.interp.model)


if __name__ == "__main__":
    main()
