"""Pretraining of the parametric head model (CNeRF + 2D neural renderer) under a strategy (seed 002, 3.3-3.4).

Each iteration draws a batch whose samples are synthetic with probability p(n) (eq. 9) and real otherwise (the real
image set: its frames, masks and per-image RGB fits). Real samples carry learnable offsets of their fitted vectors
(eq. 8) and, with `z_aug`, a z-distance augmentation (zoom with the matching focal length, p = 0.5). alpha2 renders
its synthetic samples with the mouth-interior head from `mouth_from` on. A beta strategy continues its alpha model
from iteration M. Checkpoints (weights, optimiser, offsets, every RNG) make a killed run resume to the same result.
`python -m avatarlab.train.pretrain strategy=beta6 pretrain.init_model=.../alpha2/model.pt`
"""
from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import hydra
import kornia
import numpy as np
import torch
import torch.nn.functional as F
from omegaconf import DictConfig, OmegaConf

from avatarlab.config import CONF_DIR, autocast, grad_scaler, resolve_device, setup_run
from avatarlab.data.schedule import scaled_schedule
from avatarlab.data.subject_files import load_frame_stack
from avatarlab.data.synthetic import SyntheticGenerator
from avatarlab.headmodel import load_head_model
from avatarlab.io import atomic_path, write_json, write_png
from avatarlab.model.cnerf import CNeRF, CNeRFConfig, render_feature_map
from avatarlab.model.losses import head_model_loss, perceptual_network
from avatarlab.model.renderer2d import NeuralRenderer2D
from avatarlab.render.camera import Camera
from avatarlab.tracking import start_run

log = logging.getLogger(__name__)
OFFSET_KEYS = ("shape", "pose", "expression", "texture", "lighting")


class RealImageSet:
    """Frames, masks and per-image fits of a preprocessed image subject (the FFHQ stand-in or real photos)."""

    def __init__(self, subject_dir: Path, image_size: int, indices=None, interpolated: Path | None = None):
        frames, _ = load_frame_stack(subject_dir)
        with np.load(subject_dir / "masks.npz") as m:
            masks = m["masks"]
        with np.load(subject_dir / "fit_rgb.npz") as f:
            fit = {k: f[k] for k in f.files}
        n = len(fit["fitted"])
        for key in ("shape", "texture", "lighting"):  # a video fit shares these: one row per frame here
            if fit[key].ndim == (1 if key != "lighting" else 2):
                fit[key] = np.broadcast_to(fit[key], (n, *fit[key].shape)).copy()
        if interpolated is not None:
            frames, masks = frames.copy(), masks.copy()
            replace_with_interpolated(frames, masks, fit, Path(interpolated))
        keep = fit["fitted"].copy()
        if indices is not None:  # e.g. the training split of a subject's video
            chosen = np.zeros_like(keep)
            chosen[np.asarray(indices, dtype=int)] = True
            keep &= chosen
        if keep.sum() == 0:
            raise ValueError(f"{subject_dir}/fit_rgb.npz: no fitted image")
        scale = image_size / frames.shape[1]
        self.images = F.interpolate(torch.from_numpy(frames[keep]).permute(0, 3, 1, 2).float() / 255,
                                    size=(image_size, image_size), mode="bilinear", align_corners=False)
        self.masks = F.interpolate(torch.from_numpy(masks[keep][:, None]).float(), size=(image_size, image_size))
        K = torch.from_numpy(fit["K"][keep]).float()
        K[:, :2] *= scale
        self.K, self.R, self.t = K, torch.from_numpy(fit["R"][keep]).float(), torch.from_numpy(fit["t"][keep]).float()
        self.params = {"shape": torch.from_numpy(fit["shape"][keep]).float(),
                       "expression": torch.from_numpy(fit["expression"][keep]).float(),
                       "pose": torch.from_numpy(fit["pose"][keep]).float(),
                       "texture": torch.from_numpy(fit["texture"][keep]).float(),
                       "lighting": torch.from_numpy(fit["lighting"][keep]).float()}
        self.size = image_size

    def __len__(self):
        return self.images.shape[0]


def replace_with_interpolated(frames: np.ndarray, masks: np.ndarray, fit: dict, path: Path) -> np.ndarray:
    """Variant (c) of the interpolation experiment: the frames that variant (b) drops are re-created without looking
    at them - the image by the frame interpolator (`interpolated.npz`), the mask as the mean of the two neighbours'
    masks (their union), the fitted parameters and camera as the mean of the neighbours' (a real pipeline would fit
    the new frame; the neighbours' mean is what is known without it). Modifies the arrays in place; returns the
    indices replaced (those whose neighbours were both fitted)."""
    with np.load(path) as f:
        indices, images = f["indices"], f["frames"]
    if images.shape[1:3] != frames.shape[1:3]:
        raise ValueError(f"{path}: interpolated frames are {images.shape[1:3]}, the subject's frames {frames.shape[1:3]}")
    done = []
    for i, image in zip(indices.tolist(), images):
        a, b = i - 1, i + 1
        if a < 0 or b >= len(frames) or not (fit["fitted"][a] and fit["fitted"][b]):
            fit["fitted"][i] = False
            continue
        frames[i] = image
        masks[i] = np.maximum(masks[a], masks[b])
        for key in ("shape", "expression", "pose", "texture", "lighting", "K", "t"):
            fit[key][i] = (fit[key][a].astype(np.float64) + fit[key][b]) / 2
        u, _, vt = np.linalg.svd((fit["R"][a].astype(np.float64) + fit["R"][b]) / 2)  # nearest rotation to the mean
        fit["R"][i] = u @ vt
        fit["fitted"][i] = True
        done.append(i)
    return np.asarray(done, dtype=int)


def z_augment(images, masks, K, g: torch.Generator, low: float, high: float, p: float):
    """Zoom each image about its centre by s ~ U[low, high] (p of them) and scale the focal length by s."""
    n = images.shape[0]
    s = torch.where(torch.rand(n, generator=g) < p, low + (high - low) * torch.rand(n, generator=g), torch.ones(n))
    theta = torch.zeros(n, 2, 3)
    theta[:, 0, 0] = theta[:, 1, 1] = 1 / s
    grid = F.affine_grid(theta, list(images.shape), align_corners=False)
    images = F.grid_sample(images, grid, align_corners=False, padding_mode="border")
    masks = F.grid_sample(masks, grid, align_corners=False)
    K = K.clone()
    K[:, 0, 0] *= s
    K[:, 1, 1] *= s
    return images, masks, K


def codes(params: dict, lighting: torch.Tensor, offsets: dict | None = None):
    """geometry code = [shape, pose (neck, jaw, eyes), expression]; appearance code = [texture, lighting (27)]."""
    def get(k, v):
        return v + offsets[k] if offsets is not None and k in offsets else v

    geometry = torch.cat([get("shape", params["shape"]), get("pose", params["pose"][:, 3:]),
                          get("expression", params["expression"])], 1)
    appearance = torch.cat([get("texture", params["texture"]), get("lighting", lighting.reshape(-1, 27))], 1)
    return geometry, appearance


class HeadNeRFModel(torch.nn.Module):
    def __init__(self, nerf_cfg: CNeRFConfig, renderer_kind: str, feature_size: int):
        super().__init__()
        self.nerf = CNeRF(nerf_cfg)
        self.renderer = NeuralRenderer2D(nerf_cfg.feature_channels, renderer_kind)
        self.feature_size = feature_size

    def forward(self, geometry, appearance, camera: Camera, stratified: bool = True):
        fmap, _ = render_feature_map(self.nerf, camera, (self.feature_size, self.feature_size), geometry, appearance,
                                     stratified)
        return self.renderer(fmap)


def nerf_config(cfg: DictConfig, model) -> CNeRFConfig:
    m = cfg.model
    return CNeRFConfig(frequencies=m.frequencies, depth=m.depth, width=m.width, skip_layer=m.skip_layer,
                       feature_channels=m.feature_channels, samples=m.samples, near=m.near, far=m.far,
                       n_shape=model.n_shape, n_expression=model.n_expression, n_texture=model.n_texture)


def composite(images, masks, background: float = 0.5):
    return images * masks + background * (1 - masks)


@torch.no_grad()
def evaluate_on_head_model(net: HeadNeRFModel, generator: SyntheticGenerator, count: int, seed: int):
    """PSNR/SSIM of the model against head-model renders of held-out synthetic parameters (fixed seed)."""
    g = torch.Generator().manual_seed(10_000 + seed)
    batch = generator.sample(count, g)
    pred = render_in_chunks(net, *codes(batch["params"], batch["lighting"]), batch["camera"])
    images, masks = batch["images"].cpu(), batch["masks"].cpu()
    target = composite(images, masks)
    pred_c = composite(pred, masks)
    mse_in = (((pred - images) * masks) ** 2).sum() / (3 * masks.sum())
    return {"psnr": float(kornia.metrics.psnr(pred_c, target, 1.0)),
            "psnr_head": float(-10 * torch.log10(mse_in)),
            "ssim": float(kornia.metrics.ssim(pred_c, target, 11).mean())}, pred_c, target


@torch.no_grad()
def render_in_chunks(net: HeadNeRFModel, geometry: torch.Tensor, appearance: torch.Tensor, camera: Camera,
                     chunk: int = 4) -> torch.Tensor:
    """Deterministic renders (no ray jitter) of a batch, `chunk` images at a time on the net's device; on the CPU."""
    device = next(net.parameters()).device
    geometry, appearance, camera = geometry.to(device), appearance.to(device), camera.to(device)
    return torch.cat([net(geometry[k:k + chunk], appearance[k:k + chunk], _slice_camera(camera, slice(k, k + chunk)),
                          stratified=False).cpu() for k in range(0, len(geometry), chunk)])


def _slice_camera(camera: Camera, s: slice) -> Camera:
    return Camera(K=camera.K[s], R=camera.R[s], t=camera.t[s], image_size=camera.image_size)


def _cat_cameras(a: Camera | None, b: Camera | None) -> Camera:
    if a is None:
        return b
    if b is None:
        return a
    return Camera(K=torch.cat([a.K, b.K]), R=torch.cat([a.R, b.R]), t=torch.cat([a.t, b.t]), image_size=a.image_size)


def fingerprint(cfg: DictConfig) -> str:
    keep = {k: OmegaConf.to_container(cfg[k], resolve=True) for k in ("model", "strategy", "pretrain", "synthetic")}
    keep["scale"] = cfg.scale.name
    keep["seed"] = cfg.seed
    return json.dumps(keep, sort_keys=True, default=str)


def train(cfg: DictConfig) -> dict:
    pre, strat = cfg.pretrain, cfg.strategy
    out_dir = Path(pre.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    head = load_head_model(cfg.head_model)
    mouth_cfg = OmegaConf.merge(cfg.head_model, {"mouth_interior": True})
    schedule = scaled_schedule(strat, int(cfg.scale.pretrain_alpha_iterations), int(cfg.scale.pretrain_beta_iterations))
    if pre.iterations is not None:  # e.g. the renderer experiment: a fixed budget of synthetic-only training
        schedule = type(schedule)(M=int(pre.iterations), N=int(pre.iterations), p_min=1.0, p_max=1.0, mouth_from=None)
    size = int(cfg.scale.pretrain_image_size)
    real = RealImageSet(Path(pre.real_subject_dir), size, pre.get("real_indices"), pre.get("real_interpolated"))
    background = tuple(cfg.render.background)
    device, amp = resolve_device(cfg), bool(cfg.get("amp", False))
    synth = SyntheticGenerator(head, real.params, cfg.synthetic, size, background, device)
    synth_mouth = None
    if schedule.mouth_from is not None:
        synth_mouth = SyntheticGenerator(load_head_model(mouth_cfg), real.params, cfg.synthetic, size, background,
                                         device)
    torch.manual_seed(int(cfg.seed))
    net = HeadNeRFModel(nerf_config(cfg, head), pre.renderer, int(cfg.scale.pretrain_feature_size))
    fixed = set(pre.get("fixed_codes") or [])  # fine-tuning keeps the subject's shape and texture fixed
    dims = {"shape": head.n_shape, "pose": 12, "expression": head.n_expression, "texture": head.n_texture,
            "lighting": 27}
    net.to(device)
    offsets = torch.nn.ParameterDict({k: torch.zeros(len(real), d) for k, d in dims.items() if k not in fixed}).to(device)
    for p in net.nerf.frozen_prefix(int(pre.get("freeze_layers") or 0)):
        p.requires_grad_(False)
    optim = torch.optim.Adam([{"params": [p for p in net.parameters() if p.requires_grad]},
                              {"params": offsets.parameters(), "lr": float(pre.offset_lr)}], lr=float(pre.lr))
    features = perceptual_network(cfg.model.vgg16_weights).to(device)
    scaler = grad_scaler(device, amp)
    g = torch.Generator().manual_seed(int(cfg.seed))
    step, start_step = 0, 0
    history: list[dict] = []
    if strat.init or pre.get("finetune_iterations"):  # continue a pretrained model (beta, or fine-tuning)
        if not pre.init_model or not Path(pre.init_model).is_file():
            raise FileNotFoundError(f"{pre.init_model}: strategy {strat.name} continues a pretrained model "
                                    "(pretrain.init_model)")
        parent = torch.load(pre.init_model, map_location="cpu", weights_only=False)
        net.load_state_dict(parent["model"])
        step = start_step = int(parent["step"])
        log.info("%s continues %s from iteration %d", pre.name or strat.name, pre.init_model, step)
    if pre.get("finetune_iterations"):  # per-subject fine-tuning: synthetic share decays linearly to 0 (eq. 9)
        schedule = type(schedule)(M=start_step, N=start_step + int(pre.finetune_iterations), p_min=0.0,
                                  p_max=float(pre.finetune_p_max), mouth_from=None)
    checkpoint = out_dir / "checkpoint.pt"
    fp = fingerprint(cfg)
    if checkpoint.is_file():
        state = torch.load(checkpoint, map_location="cpu", weights_only=False)
        if state.get("fingerprint") == fp:
            net.load_state_dict(state["model"])
            offsets.load_state_dict(state["offsets"])
            optim.load_state_dict(state["optim"])
            if state.get("scaler"):
                scaler.load_state_dict(state["scaler"])
            g.set_state(state["generator"])
            torch.set_rng_state(state["torch_rng"])
            step, start_step, history = state["step"], state["start_step"], state["history"]
            log.info("resuming from %s at iteration %d", checkpoint, step)
        else:
            log.warning("%s was written with other settings: starting afresh", checkpoint)
    batch_size = int(cfg.scale.pretrain_batch)
    offset_w = {k: float(cfg.model.offset_weights[k]) for k in OFFSET_KEYS if k in offsets}
    t0 = time.perf_counter()
    while step < schedule.N:
        p = schedule.probability(step + 1)
        n_syn = int(torch.binomial(torch.tensor(float(batch_size)), torch.tensor(p), generator=g)) if 0 < p < 1 else (
            batch_size if p >= 1 else 0)
        gen = synth_mouth if synth_mouth is not None and step >= schedule.mouth_from else synth
        images, masks, params, lights, cams, is_real = [], [], [], [], None, []
        real_idx = torch.zeros(0, dtype=torch.long)
        if n_syn:
            s = gen.sample(n_syn, g)
            images.append(s["images"]), masks.append(s["masks"]), lights.append(s["lighting"])
            params.append(s["params"])
            cams = s["camera"]
            is_real.append(torch.zeros(n_syn, dtype=torch.bool))
        n_real = batch_size - n_syn
        if n_real:
            real_idx = torch.randint(0, len(real), (n_real,), generator=g)
            r_img, r_mask, r_K = real.images[real_idx], real.masks[real_idx], real.K[real_idx]
            if strat.z_aug:
                r_img, r_mask, r_K = z_augment(r_img, r_mask, r_K, g, *cfg.pretrain.z_aug_range, p=0.5)
            images.append(r_img.to(device)), masks.append(r_mask.to(device))
            lights.append(real.params["lighting"][real_idx].to(device))
            params.append({k: real.params[k][real_idx].to(device) for k in ("shape", "expression", "pose", "texture")})
            cams = _cat_cameras(cams, Camera(K=r_K, R=real.R[real_idx], t=real.t[real_idx],
                                             image_size=(size, size)).to(device))
            is_real.append(torch.ones(n_real, dtype=torch.bool))
        # the batch is drawn on the CPU (random choices, real frames), rendered (synthetic samples) and trained on
        # `device`
        images, masks = torch.cat(images), torch.cat(masks)
        merged = {k: torch.cat([p_[k] for p_ in params]) for k in ("shape", "expression", "pose", "texture")}
        lighting = torch.cat(lights)
        real_mask = torch.cat(is_real).to(device)
        batch_offsets = {k: torch.cat([torch.zeros(n_syn, offsets[k].shape[1], device=device),
                                       offsets[k][real_idx.to(device)]])
                         for k in OFFSET_KEYS if k in offsets}
        geometry, appearance = codes(merged, lighting, batch_offsets)
        optim.zero_grad()
        with autocast(device, amp):
            # in low precision: the net and the perceptual network's convolutions; the loss sums in float32
            pred = net(geometry, appearance, cams).float()
            target = composite(images, masks)
            terms = head_model_loss(pred, target, masks, features, batch_offsets, offset_w, real_mask,
                                    float(cfg.model.w_mse), float(cfg.model.w_perceptual))
        scaler.scale(terms["total"]).backward()
        scaler.step(optim)
        scaler.update()
        step += 1
        with torch.no_grad():
            psnr = float(kornia.metrics.psnr(composite(pred, masks), target, 1.0))
        history.append({"step": step, "loss": float(terms["total"].detach()), "mse": float(terms["mse"].detach()),
                        "perceptual": float(terms["perceptual"].detach()), "psnr": psnr, "p_synthetic": p,
                        "n_synthetic": n_syn})
        if step % int(pre.checkpoint_every) == 0 or step == schedule.N:
            with atomic_path(checkpoint) as tmp:
                torch.save({"model": net.state_dict(), "offsets": offsets.state_dict(), "optim": optim.state_dict(),
                            "generator": g.get_state(), "torch_rng": torch.get_rng_state(), "step": step,
                            "start_step": start_step, "history": history, "fingerprint": fp,
                            "scaler": scaler.state_dict() if scaler.is_enabled() else None}, tmp)
        if step % max(1, int(pre.log_every)) == 0:
            log.info("it %d/%d p=%.2f loss %.4f psnr %.2f", step, schedule.N, p, history[-1]["loss"], psnr)
    seconds = time.perf_counter() - t0
    metrics, pred_c, target = evaluate_on_head_model(net, synth, int(pre.eval_samples), int(cfg.seed))
    return {"net": net, "history": history, "metrics": metrics, "seconds": seconds, "schedule": schedule,
            "step": step, "start_step": start_step, "samples": (pred_c, target), "perceptual": features.name,
            "real_images": len(real), "offsets": offsets, "real": real}


@hydra.main(config_path=str(CONF_DIR), config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> None:
    setup_run(cfg)
    pre = cfg.pretrain
    out_dir = Path(pre.out_dir)
    tags = {"strategy": pre.name or cfg.strategy.name, "renderer": pre.renderer, "init": cfg.strategy.init or ""}
    with start_run(cfg, "pretrain", pre.name or cfg.strategy.name, tags, enabled=bool(cfg.tracking.enabled)) as mlf:
        result = train(cfg)
        history, metrics = result["history"], result["metrics"]
        new = [h for h in history if h["step"] > result["start_step"]]
        if mlf is not None:
            mlf.log_params({"M": result["schedule"].M, "N": result["schedule"].N, "p_min": cfg.strategy.p_min,
                            "p_max": cfg.strategy.p_max, "z_aug": cfg.strategy.z_aug, "batch": cfg.scale.pretrain_batch,
                            "image_size": cfg.scale.pretrain_image_size, "renderer": pre.renderer,
                            "perceptual": result["perceptual"]})
            for h in new:
                mlf.log_metrics({k: h[k] for k in ("loss", "mse", "perceptual", "psnr", "p_synthetic")}, step=h["step"])
            mlf.log_metrics({f"eval_{k}": v for k, v in metrics.items()})
        with atomic_path(out_dir / "model.pt") as tmp:
            torch.save({"model": result["net"].state_dict(), "step": result["step"],
                        "config": OmegaConf.to_container(cfg, resolve=True)}, tmp)
        pred, target = result["samples"]
        grid = torch.cat([torch.cat(list(target[:6]), 2), torch.cat(list(pred[:6]), 2)], 1)
        write_png(out_dir / "samples.png", (grid.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8))
        if mlf is not None:
            mlf.log_artifact(str(out_dir / "samples.png"))
        report = {"strategy": cfg.strategy.name, "name": pre.name, "renderer": pre.renderer, "M": result["schedule"].M,
                  "N": result["schedule"].N, "iterations": len(new), "start_step": result["start_step"],
                  "seconds": result["seconds"], "eval": metrics, "perceptual": result["perceptual"],
                  "real_images": result["real_images"], "history": new,
                  "samples_per_second": len(new) * int(cfg.scale.pretrain_batch) / max(result["seconds"], 1e-9)}
        write_json(out_dir / "metrics.json", report)
    log.info("%s: %d iterations in %.0fs, held-out head-model renders PSNR %.2f dB (head region %.2f dB), SSIM %.3f",
             pre.name or cfg.strategy.name, len(new), result["seconds"], metrics["psnr"], metrics["psnr_head"],
             metrics["ssim"])


if __name__ == "__main__":
    main()
