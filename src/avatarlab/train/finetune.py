"""Per-subject avatar: a pretrained head model fine-tuned on one subject's video (seed 002, section 4.1).

The subject's fitted shape and texture stay fixed (no offsets), the first four CNeRF MLP layers are frozen, real frames
get z-distance augmentation and the share of synthetic samples (the head model with the subject's identity) decays
linearly to zero. The last `finetune.test_frames` frames are never trained on (INSTA protocol); the avatar is
evaluated there - PSNR, SSIM, LPIPS (or missing), identity similarity - on all test frames and on the mouth-open
subset (the test frames with the widest fitted jaw opening). Writes `model.pt`, `metrics.json`, `test_frames.png`.
`python -m avatarlab.train.finetune subject.name=synth_talk finetune.init_model=.../beta6_from_alpha2/model.pt`
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from avatarlab.config import CONF_DIR, setup_run
from avatarlab.data.subject_files import load_frame_stack
from avatarlab.evaluate.metrics import identity_similarity, lpips_metric, psnr, ssim
from avatarlab.io import atomic_path, write_json, write_png
from avatarlab.render.camera import Camera
from avatarlab.tracking import start_run
from avatarlab.train.pretrain import RealImageSet, codes, composite, render_in_chunks, train

log = logging.getLogger(__name__)


def split(n_frames: int, fitted: np.ndarray, test_frames: int, variant: str = "a", interpolated=()):
    """Train on the fitted frames before the last `test_frames`; test on the fitted frames among the last ones.

    Interpolation experiment (seed 002, 4.3): variant b keeps every second training frame (the even ones, as the
    interpolation step's split does); c adds back the dropped ones that `interpolated` re-creates."""
    if variant not in ("a", "b", "c"):
        raise ValueError(f"finetune.frames_variant={variant!r}: expected a, b or c")
    test_frames = min(test_frames, n_frames // 2)
    idx = np.arange(n_frames)
    in_train = idx < n_frames - test_frames
    test_idx = idx[~in_train & fitted]
    if variant == "a":
        return idx[in_train & fitted], test_idx
    kept = in_train & fitted & (idx % 2 == 0)
    if variant == "c":
        made = np.zeros(n_frames, bool)
        made[np.asarray(list(interpolated), dtype=int)] = True
        kept |= in_train & made
    return idx[kept], test_idx


def finetune_config(cfg: DictConfig, train_idx: np.ndarray) -> DictConfig:
    ft = cfg.finetune
    return OmegaConf.merge(cfg, {
        "strategy": {"z_aug": True},
        "synthetic": {"fixed_identity": True},
        "pretrain": {"real_subject_dir": ft.subject_dir, "real_indices": train_idx.tolist(),
                     "init_model": ft.init_model, "out_dir": ft.out_dir, "fixed_codes": ["shape", "texture"],
                     "freeze_layers": 4, "finetune_iterations": int(cfg.scale.finetune_iterations),
                     "iterations": None}})


@torch.no_grad()
def evaluate_avatar(net, test: RealImageSet, mouth_open: int, lpips) -> tuple[dict, torch.Tensor, torch.Tensor]:
    net.eval()
    camera = Camera(K=test.K, R=test.R, t=test.t, image_size=(test.size, test.size))
    start = time.perf_counter()
    preds = render_in_chunks(net, *codes(test.params, test.params["lighting"]), camera)
    seconds_per_frame = (time.perf_counter() - start) / len(test)
    pred = composite(preds, test.masks)
    target = composite(test.images, test.masks)
    jaw = test.params["pose"][:, 6]
    subset = torch.argsort(jaw, descending=True)[: max(1, min(mouth_open, len(test)))]

    def scores(sel) -> dict:
        out = {"frames": int(len(sel)), "psnr": psnr(pred[sel], target[sel]), "ssim": ssim(pred[sel], target[sel]),
               "lpips": lpips(pred[sel], target[sel]) if lpips is not None else None}
        ids = [identity_similarity(_u8(pred[i]), _u8(target[i])) for i in sel.tolist()]
        found = [v for v in ids if v is not None]
        out["identity_similarity"] = float(np.mean(found)) if found else None
        out["identity_faces_found"] = len(found)
        return out

    return {"all": scores(torch.arange(len(test))), "mouth_open": scores(subset),
            "render_seconds_per_frame": seconds_per_frame}, pred, target


def _u8(image: torch.Tensor) -> np.ndarray:
    return (image.permute(1, 2, 0).clamp(0, 1).numpy() * 255).round().astype(np.uint8)


@hydra.main(config_path=str(CONF_DIR), config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> None:
    device = setup_run(cfg)
    ft = cfg.finetune
    subject_dir = Path(ft.subject_dir)
    _, meta = load_frame_stack(subject_dir)
    with np.load(subject_dir / "fit_rgb.npz") as fit:
        fitted = fit["fitted"]
    variant, made = str(ft.frames_variant), []
    if variant == "c":
        if not Path(ft.interpolated).is_file():
            raise FileNotFoundError(f"{ft.interpolated}: variant c needs the interpolation step's frames")
        with np.load(ft.interpolated) as f:
            made = f["indices"].tolist()
    train_idx, test_idx = split(meta["count"], fitted, int(ft.test_frames), variant, made)
    if len(test_idx) == 0 or len(train_idx) == 0:
        raise ValueError(f"{subject_dir}: {meta['count']} frames leave no train/test split")
    run_cfg = finetune_config(cfg, train_idx)
    if variant == "c":
        run_cfg.pretrain.real_interpolated = str(ft.interpolated)
    tags = {"subject": cfg.subject.name, "init": ft.init_name, "renderer": cfg.pretrain.renderer,
            "frames_variant": variant}
    run_name = f"{cfg.subject.name}/{ft.init_name}" + ("" if variant == "a" else f"/frames_{variant}")
    with start_run(cfg, "finetune", run_name, tags, bool(cfg.tracking.enabled)) as mlf:
        result = train(run_cfg)
        test = RealImageSet(subject_dir, int(cfg.scale.pretrain_image_size), test_idx.tolist())
        metrics, pred, target = evaluate_avatar(result["net"], test, int(ft.mouth_open_frames),
                                                lpips_metric(ft.lpips_backbone, device))
        out_dir = Path(ft.out_dir)
        with atomic_path(out_dir / "model.pt") as tmp:
            torch.save({"model": result["net"].state_dict(), "step": result["step"],
                        "config": OmegaConf.to_container(run_cfg, resolve=True)}, tmp)
        grid = torch.cat([torch.cat(list(target[:6]), 2), torch.cat(list(pred[:6]), 2)], 1)
        write_png(out_dir / "test_frames.png", _u8(grid))
        new = [h for h in result["history"] if h["step"] > result["start_step"]]
        report = {"subject": cfg.subject.name, "init": ft.init_name, "frames_variant": variant,
                  "train_frames": len(train_idx), "train_indices": train_idx.tolist(),
                  "test_frames": test_idx.tolist(), "iterations": len(new), "train_seconds": result["seconds"],
                  "test": metrics, "lpips_backbone": ft.lpips_backbone, "history": new}
        write_json(out_dir / "metrics.json", report)
        if mlf is not None:
            mlf.log_params({"init": ft.init_name, "subject": cfg.subject.name, "frames_variant": variant,
                            "train_frames": len(train_idx), "test_frames": len(test_idx), "iterations": len(new),
                            "image_size": cfg.scale.pretrain_image_size, "lpips_backbone": ft.lpips_backbone})
            for h in new:
                mlf.log_metrics({k: h[k] for k in ("loss", "psnr", "p_synthetic")}, step=h["step"])
            for part in ("all", "mouth_open"):
                mlf.log_metrics({f"test_{part}_{k}": v for k, v in metrics[part].items()
                                 if isinstance(v, float)})
            mlf.log_metrics({"train_seconds": result["seconds"],
                             "render_seconds_per_frame": metrics["render_seconds_per_frame"]})
            mlf.log_artifact(str(out_dir / "test_frames.png"))
    a = metrics["all"]
    log.info("avatar %s from %s: %d train / %d test frames, %d its in %.0fs; test PSNR %.2f SSIM %.4f LPIPS %s "
             "identity %s", cfg.subject.name, ft.init_name, len(train_idx), len(test_idx), len(new), result["seconds"],
             a["psnr"], a["ssim"], "missing" if a["lpips"] is None else f"{a['lpips']:.4f}",
             a["identity_similarity"])


if __name__ == "__main__":
    main()
