"""Scoring a pretrained head model against its trivial baselines (seed 002, 3.4; the claim "~30 dB vs FLAME renders").

The held-out set: `evaluate.samples` head-model renders of parameters drawn as training draws them (a real image's
fit plus noise, random neck, jaw and camera) from a seed no training run uses. The model renders the same parameters;
the baselines are the mean colour of training samples inside the true mask, and the training sample nearest in
conditioning (shape, expression, neck, jaw, camera) among a pool of training draws and the real image set. Writes
`eval.json` and `eval_samples.png` (truth, model, nearest baseline) and logs to the model's MLflow run.
`python -m avatarlab.pretrain.evaluate evaluate.model=results/tiny/pretrain/alpha1/model.pt evaluate.out=...`
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

from avatarlab.data.real_images import RealImageSet
from avatarlab.data.subject_dir import SubjectDir
from avatarlab.data.synthetic import SyntheticGenerator
from avatarlab.headmodel import load_head_model
from avatarlab.metrics import baselines
from avatarlab.metrics.quality import STLPIPS, lpips_metric, psnr_per_image
from avatarlab.metrics.scoring import gains, image_scores
from avatarlab.metrics.seeds import mean_ci
from avatarlab.model.head_nerf import assemble_codes, load_model_file, render_in_chunks
from avatarlab.model.losses import composite
from avatarlab.runtime.entry import entry_point
from avatarlab.runtime.io import write_json, write_png
from avatarlab.runtime.tracking import log_to_run

log = logging.getLogger(__name__)
READS = ("seed", "head_model", "render", "synthetic", "evaluate", "tracking")
BLOCKS = ("shape", "expression", "neck", "jaw", "camera")


def real_params(subject_dir: Path) -> dict:
    fit = SubjectDir(subject_dir).fit()
    keep = fit["fitted"].astype(bool)
    return {k: torch.from_numpy(np.ascontiguousarray(fit[k][keep])).float()
            for k in ("shape", "expression", "texture", "lighting")}


@torch.no_grad()
def evaluate_pretrained(cfg, device) -> dict:
    """Scores the model file `evaluate.model`; writes eval_samples.png beside `evaluate.out`."""
    net, content = load_model_file(cfg.evaluate.model, device)
    report, grid = score_pretrained(net, int(content["spec"]["feature_size"]) * 8, cfg, device)
    write_png(Path(cfg.evaluate.out).with_name("eval_samples.png"),
              (grid.permute(1, 2, 0).clamp(0, 1).numpy() * 255).round().astype(np.uint8))
    return {**report, "step": int(content["step"]), "name": content.get("name"), "run_id": content.get("run_id")}


@torch.no_grad()
def score_pretrained(net, size: int, cfg, device, real_pool: bool = True) -> tuple[dict, torch.Tensor]:
    """A network's scores and its baselines' on the held-out renders (sections head_model, render, synthetic,
    evaluate of `cfg`) -> report, image grid (truth, model, nearest baseline). `real_pool=False`: the baselines'
    pool holds training draws only, not the real image set's images (a test's stand-in set of noise images)."""
    ev = cfg.evaluate
    head = load_head_model(cfg.head_model)
    generator = SyntheticGenerator(head, real_params(Path(ev.real_subject_dir)), cfg.synthetic, size,
                                   tuple(cfg.render.background), device)
    test = generator.sample(int(ev.samples), torch.Generator().manual_seed(10_000 + int(cfg.seed)))
    pool = generator.sample(int(ev.baseline_pool), torch.Generator().manual_seed(20_000 + int(cfg.seed)))
    real = RealImageSet(ev.real_subject_dir, size)
    pick = torch.randperm(len(real), generator=torch.Generator().manual_seed(int(cfg.seed)))[
        : int(ev.baseline_pool) if real_pool else 0]
    pool_images = torch.cat([pool["images"].cpu(), real.images[pick]])
    pool_masks = torch.cat([pool["masks"].cpu(), real.masks[pick]])
    cams = [pool["camera"].to("cpu"), real.camera(pick)]
    pool_params = {k: torch.cat([pool["params"][k].cpu(), real.params[k][pick]])
                   for k in ("shape", "expression", "pose")}
    pool_blocks = baselines.conditioning_blocks(pool_params, torch.cat([c.R for c in cams]),
                                                torch.cat([c.t for c in cams]), BLOCKS)
    tp = {k: v.cpu() for k, v in test["params"].items()}
    test_blocks = baselines.conditioning_blocks(tp, test["camera"].R.cpu(), test["camera"].t.cpu(), BLOCKS)
    images, masks = test["images"].cpu(), test["masks"].cpu()
    target = composite(images, masks)
    pred = composite(render_in_chunks(net, *assemble_codes(test["params"], test["lighting"]), test["camera"]), masks)
    nearest = baselines.nearest_indices(pool_blocks, test_blocks)
    predictions = {"mean_colour": baselines.mean_colour(pool_images, pool_masks, masks),
                   "nearest": baselines.frames_at(pool_images, pool_masks, nearest, masks)}
    perceptual = {"st_lpips": STLPIPS(device) if ev.st_lpips else None,
                  "lpips": lpips_metric(ev.lpips_backbone, device)}
    model = image_scores(pred, target, masks, perceptual)
    base = {name: image_scores(p, target, masks, perceptual) for name, p in predictions.items()}
    grid = torch.cat([torch.cat(list(row[:6]), 2) for row in (target, pred, predictions["nearest"])], 1)
    # the spread of the model's PSNR over the held-out samples: the noise of its absolute level (report/claims.py)
    psnr_ci95 = mean_ci(psnr_per_image(pred, target).tolist())[1]
    return {"model": model, "baselines": base, "gain": gains(model, base), "samples": int(ev.samples),
            "psnr_ci95": psnr_ci95,
            "baseline_pool": len(pool_images), "image_size": size}, grid


@entry_point(READS)
def main(cfg, device) -> None:
    report = evaluate_pretrained(cfg, device)
    write_json(cfg.evaluate.out, report)
    log_to_run(cfg, report.get("run_id"), report["model"], report["baselines"], report["gain"],
               artifact=Path(cfg.evaluate.out).with_name("eval_samples.png"))
    m, g = report["model"], report["gain"]["psnr_head"]
    log.info("%s: held-out head-region PSNR %.2f dB (best baseline %s %.2f dB, gain %+.2f dB), PSNR %.2f, SSIM %.3f, "
             "ST-LPIPS %s", report["name"], m["psnr_head"], g["best_baseline"], g["baseline"], g["gain"], m["psnr"],
             m["ssim"], "missing" if m["st_lpips"] is None else f"{m['st_lpips']:.3f}")


if __name__ == "__main__":
    main()
