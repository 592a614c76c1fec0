"""The thesis' interpolation experiment on one subject (seed 002, section 4.3 / figure 54).

Variants of the training frames: (a) all frames, (b) every second frame removed, (c) (b) plus the removed frames
re-created by interpolation. The XVFI-style network is the one trained once on every subject's video
(`interp/pretrain.py`, self-supervised on the frames that (b) keeps: predict the middle of three); here it fills the
removed frames, and the Farneback baseline and a plain cross-fade do the same. Interpolation PSNR/SSIM are measured
on the removed (held-out) frames. Writes `interp.json`, `interpolated.npz` (variant (c)'s new frames) and a
comparison PNG.

Before it interpolates, the step chooses the network's still-flow length (`still_flow_px`: flows shorter than it are
not warped) for this subject among `interp.subject_still_flow_candidates`, on the subject's own triplets of kept
frames (the frames variant (b) keeps, neighbours 4 apart: never a held-out frame). One length for every video is a
trade: 0.5 px lifts the synthetic subjects, whose small flows are noise on a still head, and costs real footage,
whose small flows are partly a real drift; chosen per subject, each keeps its gain.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import kornia
import numpy as np
import torch

from avatarlab.data.subject_dir import SubjectDir
from avatarlab.metrics.quality import STLPIPS, psnr_per_image
from avatarlab.metrics.seeds import gain_verdict, mean_ci
from avatarlab.preprocess.interp.network import load_interpolator
from avatarlab.preprocess.interp.optical_flow import interpolate_farneback
from avatarlab.preprocess.interp.training import (
    choose_still_flow,
    flow_lengths,
    split_variants,
    to_tensor,
    training_triplets,
)
from avatarlab.runtime.entry import entry_point
from avatarlab.runtime.io import atomic_path, write_json, write_png

log = logging.getLogger(__name__)
READS = ('seed', 'amp', 'preprocess', 'interp', 'evaluate')  # the config sections this step reads (runtime/entry.py)


def quality(pred: torch.Tensor, target: torch.Tensor, st_lpips=None) -> dict[str, float | None]:
    """PSNR, SSIM and ST-LPIPS (None when `evaluate.st_lpips` is off) of interpolated frames against the real ones."""
    return {"psnr": float(kornia.metrics.psnr(pred, target, 1.0)),
            "ssim": float(kornia.metrics.ssim(pred, target, 11).mean()),
            "st_lpips": st_lpips(pred, target) if st_lpips is not None else None}


def frame_psnr(pred: torch.Tensor, target: torch.Tensor) -> np.ndarray:
    """(N,) the PSNR of each frame (MAX = 1, as the pooled figures beside it)."""
    return psnr_per_image(pred.float(), target.float(), 1.0).numpy()


def write_interpolated(subject_dir: Path, held: np.ndarray, frames_u8: np.ndarray, kept: np.ndarray) -> None:
    """interpolated.npz: the re-created frames (K, H, W, 3) uint8 at `held`, beside the frames variant (b) keeps."""
    with atomic_path(subject_dir / "interpolated.npz") as tmp:
        np.savez_compressed(tmp, indices=held, frames=frames_u8, kept=kept)


def paired_gain(model: np.ndarray, baseline: np.ndarray) -> dict:
    """The model's per-frame PSNR gain over a baseline on the same held-out frames: mean, 95 % CI half-width (Student's
    t over frames), frames won, and whether the CI excludes zero (a gain, a loss, or within the frames' spread)."""
    d = np.asarray(model, float) - np.asarray(baseline, float)
    if len(d) < 2:
        return {"frames": len(d), "mean_db": float(d.mean()) if len(d) else None, "ci95_db": None,
                "wins": int((d > 0).sum()), "verdict": "too few frames for a CI"}
    mean, half, _ = mean_ci(d)
    verdict = gain_verdict(mean, half, "frames'")
    return {"frames": len(d), "mean_db": mean, "ci95_db": half, "wins": int((d > 0).sum()), "verdict": verdict}


def choose_subject_still_flow(model, frames: torch.Tensor, triplets: np.ndarray, candidates,
                               device) -> list[list[float]]:
    """Sets `model.still_flow_px` to the candidate that scores best on the subject's `triplets` of kept frames
    -> [[candidate, PSNR], ...]; without candidates or triplets, [] and the network keeps the length it was saved
    with."""
    name = "interp.subject_still_flow_candidates"
    candidates = flow_lengths(candidates, name)
    if not candidates or not len(triplets):
        return []
    return choose_still_flow(model, frames, triplets, device, None, candidates, name=name)


def interpolate_subject(cfg, device) -> dict:
    """The step on `preprocess.subject_dir`: writes interp.json, interpolated.npz and the comparison PNG -> the
    report."""
    subject_dir = Path(cfg.preprocess.subject_dir)
    subject = SubjectDir(subject_dir)
    frames_np = subject.frames()
    frames = to_tensor(frames_np)
    clips = subject.frame_clips()
    kept, held = split_variants(len(frames), clips)
    if len(held) == 0:  # e.g. a few frames over many clips: nothing to score, and variant (c) adds nothing
        reason = f"none of its {len(frames)} frames lies between two frames of one clip"
        log.warning("%s: no interpolation experiment: %s", subject.frames_json, reason)
        write_interpolated(subject_dir, held, np.zeros((0, *frames_np.shape[1:]), np.uint8), kept)
        write_png(subject_dir / "interp_comparison.png", frames_np[0])
        skipped = {"frames": len(frames), "kept_b": len(kept), "held_out": 0, "model": str(cfg.interp.model),
                   "skipped": reason, "xvfi": None, "farneback": None, "cross_fade": None, "paired_psnr_gain": None}
        write_json(subject_dir / "interp.json", skipped)
        return skipped
    own = training_triplets(kept, (1,), clips)  # neighbours one kept frame apart, inside one clip
    model = load_interpolator(cfg.interp.model, device)
    saved_still = model.still_flow_px
    still_choice = choose_subject_still_flow(model, frames, own, list(cfg.interp.subject_still_flow_candidates), device)
    start = time.perf_counter()
    with torch.no_grad():
        xvfi = torch.cat([model(frames[held - 1][k:k + 8].to(device), frames[held + 1][k:k + 8].to(device)).cpu()
                          for k in range(0, len(held), 8)])
    seconds = time.perf_counter() - start
    flow = to_tensor(np.stack([interpolate_farneback(frames_np[i - 1], frames_np[i + 1]) for i in held]))
    fade = 0.5 * (frames[held - 1] + frames[held + 1])
    target = frames[held]
    perceptual = STLPIPS(device) if cfg.evaluate.st_lpips else None
    report = {"frames": len(frames), "kept_b": len(kept), "held_out": len(held), "model": str(cfg.interp.model),
              "still_flow_px": model.still_flow_px, "still_flow_px_saved": saved_still,
              "still_flow_subject_psnr": still_choice, "seconds_per_frame": seconds / len(held),
              "xvfi": quality(xvfi, target, perceptual), "farneback": quality(flow, target, perceptual),
              "cross_fade": quality(fade, target, perceptual),
              "paired_psnr_gain": {name: paired_gain(frame_psnr(xvfi, target), frame_psnr(pred, target))
                                   for name, pred in (("farneback", flow), ("cross_fade", fade))},
              "variants": {"a": len(frames), "b": len(kept), "c": len(kept) + len(held)}}
    out_u8 = (xvfi.permute(0, 2, 3, 1).numpy() * 255).round().astype(np.uint8)
    write_interpolated(subject_dir, held, out_u8, kept)
    show = np.linspace(0, len(held) - 1, min(3, len(held))).round().astype(int)
    rows = [np.concatenate([frames_np[held[k]], out_u8[k], (flow[k].permute(1, 2, 0).numpy() * 255).astype(np.uint8)],
                           1) for k in show]
    write_png(subject_dir / "interp_comparison.png", np.concatenate(rows, 0))
    write_json(subject_dir / "interp.json", report)
    if still_choice:
        log.info("pixels whose flow is shorter than %.2f px are not warped: chosen on this subject's %d triplets of "
                 "kept frames (PSNR by that length: %s)", model.still_flow_px, len(own),
                 ", ".join(f"{c:g} px {v:.2f} dB" for c, v in still_choice))
    log.info("interpolation on %d held-out frames: XVFI-style PSNR %.2f dB SSIM %.4f | Farneback %.2f / %.4f | "
             "cross-fade %.2f / %.4f (the shared network %s)", len(held), report["xvfi"]["psnr"],
             report["xvfi"]["ssim"], report["farneback"]["psnr"], report["farneback"]["ssim"],
             report["cross_fade"]["psnr"], report["cross_fade"]["ssim"], cfg.interp.model)
    for name, gain in report["paired_psnr_gain"].items():
        log.info("XVFI-style over %s per frame: %+.2f dB +- %s, %d of %d frames won: %s", name, gain["mean_db"],
                 "n/a" if gain["ci95_db"] is None else f"{gain['ci95_db']:.2f}", gain["wins"], gain["frames"],
                 gain["verdict"])
    return report


@entry_point(READS)
def main(cfg, device) -> None:
    interpolate_subject(cfg, device)


if __name__ == "__main__":
    main()
