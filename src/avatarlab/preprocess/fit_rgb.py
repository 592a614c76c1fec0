"""FLAME fit from RGB (seed 002, section 2.3, eq. 1), for a single image or a video.

Video: keyframes (at most a quarter of the frames, spread over the yaw range, extremes included) get the full fit of
shared shape, texture, lighting and focal length plus per-frame expression, pose and extrinsics; the other frames
keep the shared values fixed and fit extrinsics, expression and pose with fewer iterations, warm-started from the
nearest frame already fitted. Each fit starts rigid (extrinsics on the inner 51 landmarks), as in
photometric_optimization. A subject filmed in several clips (several recordings: other rooms, cameras, white
balance) then gets one SH lighting per clip (`fit_rgb.lighting_per_clip`), refitted photometrically on a few frames
of each clip from the shared one with everything else fixed, so the appearance code carries each recording's light
and colour, a clip never trained on included. Writes `fit_rgb.npz` (lighting (9, 3), or (frames, 9, 3) per clip),
`fit_rgb.json` and an overlay PNG.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix
from omegaconf import DictConfig

from avatarlab.data.splits import held_out
from avatarlab.data.subject_dir import SubjectDir
from avatarlab.headmodel import HeadModel, load_head_model
from avatarlab.headmodel.flame import rodrigues
from avatarlab.metrics.alignment import procrustes_error_mm
from avatarlab.render.camera import Camera, intrinsics
from avatarlab.render.head_renderer import HeadRenderer
from avatarlab.render.lighting import default_lighting
from avatarlab.runtime.config import CPU
from avatarlab.runtime.entry import entry_point
from avatarlab.runtime.io import write_json, write_png

log = logging.getLogger(__name__)
READS = ('seed', 'preprocess', 'fit_rgb', 'head_model', 'render')  # the config sections this step reads (runtime/entry.py)
INNER = slice(17, 68)  # the 51 landmarks without the jaw contour (rigid stage)


@dataclass
class FitWeights:
    photometric: float = 8.0
    landmarks: float = 1.0
    shape_reg: float = 1e-4
    expression_reg: float = 1e-4
    texture_reg: float = 1e-4
    pose_reg: float = 1e-2
    eye_symmetry: float = 1e-1


def rgb_fit_loss(pred_rgb, gt_rgb, mask, pred_lmk, gt_lmk, lmk_valid, shape, expression, texture, pose,
                 weights: FitWeights, image_size: int, landmark_idx=slice(None)) -> dict[str, torch.Tensor]:
    """Eq. (1): masked photometric L1 + landmark L1 + coefficient priors + pose prior + eye symmetry.

    pred_rgb, gt_rgb (B,3,H,W); mask (B,1,H,W); landmarks (B,68,2) in pixels, compared in units of the image size;
    coefficients are in units of their standard deviation (sigma = 1), so the priors are plain squares.
    """
    terms = {}
    if weights.photometric > 0:
        terms["photometric"] = weights.photometric * ((pred_rgb - gt_rgb).abs() * mask).sum() / (
            3 * mask.sum()).clamp(min=1)
    diff = ((pred_lmk - gt_lmk) / image_size).abs()[:, landmark_idx] * lmk_valid[:, None, None]
    terms["landmarks"] = weights.landmarks * diff.sum() / (2 * diff.shape[1] * lmk_valid.sum().clamp(min=1))
    terms["shape_reg"] = weights.shape_reg * (shape**2).sum()
    terms["expression_reg"] = weights.expression_reg * (expression**2).sum() / expression.shape[0]
    terms["texture_reg"] = weights.texture_reg * (texture**2).sum()
    rot = rodrigues(pose[:, 3:].reshape(-1, 4, 3))  # neck, jaw, eyes; rest pose theta* = 0 -> R = I
    terms["pose_reg"] = weights.pose_reg * ((rot - torch.eye(3, device=rot.device)) ** 2).sum() / pose.shape[0]
    terms["eye_symmetry"] = weights.eye_symmetry * 0.5 * ((pose[:, 9:12] - pose[:, 12:15]) ** 2).sum() / pose.shape[0]
    terms["total"] = sum(terms.values())
    return terms


def pnp_extrinsics(model: HeadModel, landmarks: np.ndarray, K: np.ndarray):
    """Per-frame (rvec, tvec) from the neutral model's 3D landmarks and the detected 2D ones (OpenCV PnP)."""
    p = model.zeros(1)
    with torch.no_grad():
        lm3d = model(p["shape"], p["expression"], p["pose"]).landmarks3d[0].cpu().numpy().astype(np.float64)
    model_width = np.linalg.norm(lm3d[0] - lm3d[16])
    rvecs, tvecs = [], []
    for pts in landmarks:
        # start from a frontal head at the distance its landmark spread implies, so PnP cannot flip behind
        distance = K[0, 0] * model_width / max(np.linalg.norm(pts[0] - pts[16]), 1.0)
        centre = (pts.mean(0) - K[:2, 2]) * distance / K[0, 0]
        rvec0 = np.array([[np.pi], [0.0], [0.0]])
        tvec0 = np.array([[centre[0]], [centre[1]], [distance]])
        ok, rvec, tvec = cv2.solvePnP(lm3d, pts.astype(np.float64), K, None, rvec0, tvec0, useExtrinsicGuess=True,
                                      flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok or tvec[2] <= 0:
            rvec, tvec = rvec0, tvec0
        rvecs.append(rvec.reshape(3))
        tvecs.append(tvec.reshape(3))
    return np.array(rvecs), np.array(tvecs)


def yaw_of(rvecs: np.ndarray) -> np.ndarray:
    """Head yaw (degrees) seen by the camera, from world->camera rotations."""
    R = axis_angle_to_rotation_matrix(torch.from_numpy(rvecs).float()).numpy()
    forward = R @ np.array([0, 0, 1.0])  # the face direction in camera axes
    return np.degrees(np.arctan2(forward[:, 0], -forward[:, 2]))


def choose_keyframes(yaw: np.ndarray, count: int) -> np.ndarray:
    """`count` frames spread over the yaw range, extremes included (the dissertation's -90/0/90 keyframes)."""
    order = np.argsort(yaw)
    if count >= len(yaw):
        return np.sort(order)
    targets = np.linspace(yaw[order[0]], yaw[order[-1]], count)
    chosen: list[int] = []
    for target in targets:
        for i in np.argsort(np.abs(yaw - target)):
            if i not in chosen:
                chosen.append(int(i))
                break
    return np.sort(np.array(chosen))


class RGBFitter:
    """Parameters as tensors, one Adam per stage, each loss term a named line with its weight from config."""

    def __init__(self, model: HeadModel, image_size: int, weights: FitWeights, lr: float, background,
                 jaw_limits: tuple[float, float] | None = None):
        self.model = model
        self.size = image_size
        self.weights = weights
        self.lr = lr
        #: the jaw's opening angle (radians, pose[:, 6]) is kept in these bounds after every step: a jaw turned
        #: 48 degrees the closed way once fitted the last frames of a talking video (and so its test frames)
        self.jaw_limits = jaw_limits
        self.renderer = HeadRenderer(model, background=background)

    def render(self, shape, expression, pose, texture, lighting, focal, rot, trans):
        n = expression.shape[0]
        K = intrinsics(1.0, (self.size, self.size), n).to(focal.device)
        K[:, 0, 0] = K[:, 1, 1] = focal.exp().expand(n)  # one shared focal length, optimised in log space
        camera = Camera(K=K, R=axis_angle_to_rotation_matrix(rot), t=trans, image_size=(self.size, self.size))
        params = {"shape": shape.expand(n, -1), "expression": expression, "pose": pose,
                  "texture": texture.expand(n, -1)}
        return self.renderer(params, camera, lighting.expand(n, -1, -1)), camera

    def optimize(self, images, landmarks, masks, valid, init: dict, free: set[str], iterations: int,
                 rigid_iterations: int, lr: float | None = None) -> tuple[dict, list[float]]:
        """images (B,3,H,W), landmarks (B,68,2), masks (B,1,H,W), valid (B,). Optimises the names in `free`, with
        the step `lr` (None: the fitter's)."""
        lr = self.lr if lr is None else lr
        state = {k: v.clone().requires_grad_(k in free | {"rot", "trans"}) for k, v in init.items()}
        history = []
        for stage, steps, names in (("rigid", rigid_iterations, {"rot", "trans"}),
                                    ("full", iterations, free | {"rot", "trans"})):
            if steps <= 0:
                continue
            # translations are in metres: a tenth of the step of the unitless coefficients and radians
            optim = torch.optim.Adam([{"params": [state[k]], "lr": lr * (0.1 if k == "trans" else 1.0)}
                                      for k in names])
            for _ in range(steps):
                optim.zero_grad()
                out, _ = self.render(**state)
                w = self.weights if stage == "full" else FitWeights(photometric=0.0, landmarks=1.0, shape_reg=0,
                                                                  expression_reg=0, texture_reg=0, pose_reg=0,
                                                                  eye_symmetry=0)
                terms = rgb_fit_loss(out.rgb, images, masks, out.landmarks2d, landmarks, valid, state["shape"],
                                     state["expression"], state["texture"], state["pose"], w, self.size,
                                     INNER if stage == "rigid" else slice(None))
                terms["total"].backward()
                optim.step()
                if self.jaw_limits is not None and "pose" in names:
                    with torch.no_grad():
                        state["pose"][:, 6].clamp_(*self.jaw_limits)
                history.append(float(terms["total"].detach()))
        return {k: v.detach() for k, v in state.items()}, history


def initial_state(model: HeadModel, n: int, focal: float, rvecs, tvecs, device=None) -> dict:
    state = {"shape": torch.zeros(1, model.n_shape), "texture": torch.zeros(1, model.n_texture),
             "lighting": default_lighting(1), "focal": torch.tensor([np.log(focal)], dtype=torch.float32),
             "expression": torch.zeros(n, model.n_expression), "pose": torch.zeros(n, 15),
             "rot": torch.from_numpy(rvecs).float(), "trans": torch.from_numpy(tvecs).float()}
    return {k: v.to(device) for k, v in state.items()}


def fit_clip_lighting(fitter: RGBFitter, shared: dict, result: dict, fitted: np.ndarray, images, lm_t, mask_t,
                      clips: np.ndarray, fit,
                      open_frames: np.ndarray | None = None) -> tuple[torch.Tensor, list[float]]:
    """One SH lighting per clip: from the shared one, refitted (photometric + landmark terms, lighting and
    extrinsics free, shape, texture, expression and pose fixed) on up to `fit.lighting_frames` fitted frames of each
    clip, with the step `fit.lighting_lr`. `open_frames` (N,) bool: the frames outside the avatar's test and
    validation split; a clip that has some is lit from them alone (a training clip's same-recording test frames
    never reach its training frames' lighting), a held-out clip from its own frames. -> lighting per frame
    (N, 9, 3), the clips' final losses."""
    lighting = shared["lighting"].expand(len(clips), -1, -1).clone()
    losses = []
    open_frames = np.ones(len(clips), bool) if open_frames is None else open_frames
    for clip in np.unique(clips):
        members = np.nonzero((clips == clip) & fitted)[0]
        if open_frames[members].any():
            members = members[open_frames[members]]
        if len(members) == 0:
            continue
        ids = members[np.unique(np.linspace(0, len(members) - 1, min(int(fit.lighting_frames), len(members)))
                                .round().astype(int))]
        init = dict(shared, expression=result["expression"][ids], pose=result["pose"][ids], rot=result["rot"][ids],
                    trans=result["trans"][ids])
        out, hist = fitter.optimize(images[ids], lm_t[ids], mask_t[ids], torch.ones(len(ids), device=images.device),
                                    init, {"lighting"}, int(fit.lighting_iterations), 0, lr=float(fit.lighting_lr))
        lighting[torch.from_numpy(clips == clip).to(lighting.device)] = out["lighting"]
        losses.append(hist[-1] if hist else float("nan"))
    return lighting, losses


def identity_frames(fit, clips: np.ndarray | None, n: int, source: str = "the subject") -> np.ndarray:
    """(n,) bool: the frames the shared identity (shape, texture, focal, lighting) may be fitted on: all but the
    avatar's test and validation frames (`fit_rgb.held_out`, the split of data/splits.py), so that nothing a test
    frame shows reaches the avatar except its own expression, pose and camera (and, for a held-out clip, that
    clip's lighting): the preprocessing side of the validation wall."""
    h = fit.held_out
    in_test, in_validation, _ = held_out(np.zeros(n, int) if clips is None else np.asarray(clips),
                                         int(h.test_frames), int(h.test_clips), int(h.validation_frames),
                                         int(h.validation_clips), source, int(h.recording_test_frames))
    return ~(in_test | in_validation)


def fit_video(cfg: DictConfig, frames: np.ndarray, landmarks: np.ndarray, found: np.ndarray, masks: np.ndarray,
              device: torch.device = CPU, clips: np.ndarray | None = None, source: str = "the subject"):
    """Fits on `device` (the model, frames and parameters live there); the results stay there too. `clips`: each
    frame's clip (video mode: more than one gives one lighting per clip, when the config asks for it). Video mode
    takes its keyframes (the identity) among the frames `identity_frames` allows; the held-out frames are fitted
    last, in chunks of their own, with the identity fixed."""
    fit = cfg.fit_rgb
    model = load_head_model(cfg.head_model).to(device)
    size = frames.shape[1]
    weights = FitWeights(**fit.weights)
    if fit.mode == "video":  # one identity over many frames: each frame's expression under its own prior
        weights = replace(weights, expression_reg=float(fit.video_expression_reg))
    fitter = RGBFitter(model, size, weights, float(fit.lr), tuple(cfg.render.background),
                       tuple(np.radians(float(v)) for v in fit.jaw_limits_deg))
    focal0 = float(fit.initial_focal) * size
    K0 = intrinsics(focal0, (size, size))[0].numpy().astype(np.float64)
    idx = np.nonzero(found)[0]
    if len(idx) == 0:
        raise ValueError("no frame has landmarks: nothing to fit")
    rvecs, tvecs = pnp_extrinsics(model, landmarks[idx], K0)
    yaw = yaw_of(rvecs)
    video = fit.mode == "video"
    open_frames = identity_frames(fit, clips, len(frames), source) if video else np.ones(len(frames), bool)
    allowed = open_frames[idx]
    if not allowed.any():
        raise ValueError(f"{source}: no frame with landmarks outside the test and validation split to fit the "
                         "identity on (fit_rgb.held_out)")
    candidates = np.nonzero(allowed)[0]
    n_key = max(1, min(int(fit.max_keyframes), len(candidates) // 4 if len(candidates) >= 4 else 1))
    key_local = candidates[choose_keyframes(yaw[candidates], n_key)]
    images = (torch.from_numpy(frames).permute(0, 3, 1, 2).float() / 255).to(device)
    mask_t = torch.from_numpy(masks[:, None]).float().to(device)
    lm_t = torch.from_numpy(np.nan_to_num(landmarks)).float().to(device)
    ones = torch.ones(len(frames), device=device)

    n = len(frames)
    result = {"expression": torch.zeros(n, model.n_expression, device=device),
              "pose": torch.zeros(n, 15, device=device), "rot": torch.zeros(n, 3, device=device),
              "trans": torch.zeros(n, 3, device=device)}
    fitted = np.zeros(n, bool)
    if fit.mode == "images":  # unrelated photographs: every image its own identity, camera and lighting
        return fit_images(fitter, model, fit, images, lm_t, mask_t, idx, rvecs, tvecs, focal0, result, fitted)
    key = idx[key_local]
    state = initial_state(model, len(key), focal0, rvecs[key_local], tvecs[key_local], device)
    start = time.perf_counter()
    state, hist_key = fitter.optimize(images[key], lm_t[key], mask_t[key], ones[key], state,
                                      {"shape", "texture", "lighting", "focal", "expression", "pose"},
                                      int(fit.keyframe_iterations), int(fit.rigid_iterations))
    shared = {k: state[k] for k in ("shape", "texture", "lighting", "focal")}
    for k in result:
        result[k][key] = state[k]
    fitted[key] = True
    log.info("keyframes %s (yaw %s deg) fitted in %.1fs, loss %.4f -> %.4f", key.tolist(),
             np.round(yaw[key_local]).astype(int).tolist(), time.perf_counter() - start, hist_key[0], hist_key[-1])
    keys = set(key.tolist())
    rest = [i for i, ok in zip(idx.tolist(), allowed) if ok and i not in keys]  # fitted first, then the held-out
    held = [i for i, ok in zip(idx.tolist(), allowed) if not ok]
    chunk = int(fit.chunk)
    batches = [group[c:c + chunk] for group in (rest, held) for c in range(0, len(group), chunk)]
    rvec_of = dict(zip(idx.tolist(), rvecs))
    tvec_of = dict(zip(idx.tolist(), tvecs))
    hist_rest = []
    for batch in batches:
        ids = np.array(batch)
        done = np.nonzero(fitted)[0]
        nearest = done[np.abs(done[None, :] - ids[:, None]).argmin(1)]
        init = dict(shared, expression=result["expression"][nearest].clone(), pose=result["pose"][nearest].clone(),
                    rot=torch.from_numpy(np.array([rvec_of[i] for i in ids])).float().to(device),
                    trans=torch.from_numpy(np.array([tvec_of[i] for i in ids])).float().to(device))
        out, hist = fitter.optimize(images[ids], lm_t[ids], mask_t[ids], ones[ids], init, {"expression", "pose"},
                                    int(fit.frame_iterations), int(fit.frame_rigid_iterations))
        for k in result:
            result[k][ids] = out[k]
        fitted[ids] = True
        hist_rest.append(hist[-1])
    if clips is not None and len(np.unique(clips)) > 1 and fit.lighting_per_clip:
        shared["lighting"], losses = fit_clip_lighting(fitter, shared, result, fitted, images, lm_t, mask_t, clips, fit,
                                                       open_frames)
        log.info("one lighting per clip (%d clips), final losses %s", len(losses), np.round(losses, 4).tolist())
    seconds = time.perf_counter() - start
    return model, fitter, shared, result, fitted, key, seconds, hist_key


def fit_images(fitter, model, fit, images, lm_t, mask_t, idx, rvecs, tvecs, focal0, result, fitted):
    n, device = len(images), images.device
    shared = {"shape": torch.zeros(n, model.n_shape, device=device),
              "texture": torch.zeros(n, model.n_texture, device=device), "lighting": default_lighting(n, device=device),
              "focal": torch.full((n,), float(np.log(focal0)), device=device)}
    start = time.perf_counter()
    hist = [0.0]
    chunk = int(fit.chunk)
    for c in range(0, len(idx), chunk):
        ids = idx[c:c + chunk]
        local = np.arange(c, c + len(ids))
        init = {"shape": shared["shape"][ids], "texture": shared["texture"][ids], "lighting": shared["lighting"][ids],
                "focal": shared["focal"][ids], "expression": result["expression"][ids], "pose": result["pose"][ids],
                "rot": torch.from_numpy(rvecs[local]).float().to(device),
                "trans": torch.from_numpy(tvecs[local]).float().to(device)}
        out, hist = fitter.optimize(images[ids], lm_t[ids], mask_t[ids], torch.ones(len(ids), device=device), init,
                                    {"shape", "texture", "lighting", "focal", "expression", "pose"},
                                    int(fit.keyframe_iterations), int(fit.rigid_iterations))
        for k in shared:
            shared[k][ids] = out[k]
        for k in result:
            result[k][ids] = out[k]
        fitted[ids] = True
    return model, fitter, shared, result, fitted, idx, time.perf_counter() - start, hist


@torch.no_grad()
def evaluate_fit(fitter: RGBFitter, shared, result, fitted, images, landmarks, found, masks):
    ids = np.nonzero(fitted)[0]
    per_image = shared["shape"].shape[0] > 1
    pick = (lambda v: v[ids]) if per_image else (lambda v: v)  # noqa: E731
    lighting = shared["lighting"][ids] if shared["lighting"].shape[0] > 1 else shared["lighting"]  # per frame or one
    out, camera = fitter.render(pick(shared["shape"]), result["expression"][ids], result["pose"][ids],
                                pick(shared["texture"]), lighting, pick(shared["focal"]),
                                result["rot"][ids], result["trans"][ids])
    lm_err = np.linalg.norm(out.landmarks2d.cpu().numpy() - landmarks[ids], axis=-1)
    iod = np.linalg.norm(landmarks[ids, 36] - landmarks[ids, 45], axis=-1)
    m = torch.from_numpy(masks[ids, None]).float().to(images.device)
    photo = ((out.rgb - images[ids]).abs() * m).sum() / (3 * m.sum())
    return out, camera, {"landmark_error_px": float(lm_err.mean()), "landmark_nme": float((lm_err.mean(1) / iod).mean()),
                         "photometric_l1": float(photo)}


@torch.no_grad()
def fold_root_into_camera(model: HeadModel, shape: torch.Tensor, pose: torch.Tensor, R: torch.Tensor,
                          t: torch.Tensor):
    """The root joint's rotation moves every vertex rigidly, x -> R0 (x - J0) + J0 (pose correctives exclude it),
    so it is exactly a change of camera: R' = R R0, t' = t + R J0 - R R0 J0, with the root set to zero. The head
    model network sees neck, jaw and eyes only (seed 002, 3.1.1): a root left in theta would be lost there.
    shape (B, S), pose (B, 15), R (B, 3, 3), t (B, 3) -> pose, R, t."""
    zeros = torch.zeros(len(pose), model.n_expression, device=pose.device)
    j0 = model(shape, zeros, torch.zeros_like(pose)).joints[:, 0]  # rest-pose root joint
    r0 = rodrigues(pose[:, :3])
    R_new = R @ r0
    t_new = t + (R @ j0[..., None]).squeeze(-1) - (R_new @ j0[..., None]).squeeze(-1)
    pose = pose.clone()
    pose[:, :3] = 0
    return pose, R_new, t_new




@torch.no_grad()
def compare_with_truth(model: HeadModel, shared, result, fitted, truth_path: str) -> dict:
    with np.load(truth_path) as t:
        truth = {k: t[k] for k in ("shape", "expression", "pose")}
    ids = np.nonzero(fitted)[0]
    zeros = torch.zeros(1, model.n_expression)
    fit_neutral = model(shared["shape"], zeros, torch.zeros(1, 15)).vertices[0].numpy()
    true_neutral = model(torch.from_numpy(truth["shape"])[None], zeros, torch.zeros(1, 15)).vertices[0].numpy()
    face = model.regions["face"].numpy()
    expr_errors, jaw_errors = [], []
    for i in ids:
        pose_fit = result["pose"][i:i + 1].clone()
        pose_true = torch.from_numpy(truth["pose"][i:i + 1]).clone()
        pose_fit[:, :6] = 0  # compare expression + jaw in the head's own frame
        pose_true[:, :6] = 0
        v_fit = model(shared["shape"], result["expression"][i:i + 1], pose_fit).vertices[0].numpy()
        v_true = model(torch.from_numpy(truth["shape"])[None], torch.from_numpy(truth["expression"][i:i + 1]),
                       pose_true).vertices[0].numpy()
        expr_errors.append(1000 * np.linalg.norm((v_fit - fit_neutral) - (v_true - true_neutral), axis=1)[face].mean())
        jaw_errors.append(np.degrees(abs(float(result["pose"][i, 6]) - float(truth["pose"][i, 6]))))
    return {"shape_error_mm": procrustes_error_mm(fit_neutral[face], true_neutral[face]),
            "expression_error_mm": float(np.mean(expr_errors)), "jaw_error_deg": float(np.mean(jaw_errors))}


def overlay_sheet(frames: np.ndarray, rendered: np.ndarray, landmarks: np.ndarray, count: int = 6) -> np.ndarray:
    """Top: frames with detected (red) landmarks; bottom: the fit blended over the frame with its landmarks."""
    sel = np.linspace(0, len(frames) - 1, min(count, len(frames))).round().astype(int)
    top = [frames[i].copy() for i in sel]
    bottom = [(0.5 * frames[i] + 0.5 * rendered[i]).astype(np.uint8) for i in sel]
    for img, i in zip(top, sel):
        for x, y in np.nan_to_num(landmarks[i]).astype(int):
            cv2.circle(img, (int(x), int(y)), 1, (255, 0, 0), -1)
    return np.concatenate([np.concatenate(top, 1), np.concatenate(bottom, 1)], 0)


@entry_point(READS)
def main(cfg, device) -> None:
    subject_dir = Path(cfg.preprocess.subject_dir)
    subject = SubjectDir(subject_dir)
    frames = subject.frames()
    landmarks, found = subject.landmarks()
    with np.load(subject_dir / "masks.npz") as mk:
        masks = mk["masks"]
    clips = subject.frame_clips()
    model, fitter, shared, result, fitted, key, seconds, hist = fit_video(cfg, frames, landmarks, found, masks,
                                                                          device, clips, str(subject_dir))
    images = (torch.from_numpy(frames).permute(0, 3, 1, 2).float() / 255).to(device)
    out, camera, report = evaluate_fit(fitter, shared, result, fitted, images, np.nan_to_num(landmarks), found,
                                       masks)
    # the rest (truth comparison, files) on the CPU
    model, camera = model.cpu(), camera.to("cpu")
    shared, result = ({k: v.cpu() for k, v in d.items()} for d in (shared, result))
    rendered_rgb = out.rgb.cpu()
    report.update({"frames": len(frames), "fitted": int(fitted.sum()), "keyframes": key.tolist(),
                   "seconds": seconds, "focal_px": float(shared["focal"].exp().mean()), "head_model": model.source,
                   "mode": cfg.fit_rgb.mode})
    truth = cfg.preprocess.get("truth")
    if truth and Path(truth).is_file() and cfg.fit_rgb.mode == "video":
        report["truth"] = compare_with_truth(model, shared, result, fitted, truth)
    n = len(frames)
    K = np.zeros((n, 3, 3), np.float32)
    R = np.zeros((n, 3, 3), np.float32)
    ids = np.nonzero(fitted)[0]
    per_image = cfg.fit_rgb.mode == "images"
    shape_of = shared["shape"][torch.from_numpy(ids)] if per_image else shared["shape"].expand(len(ids), -1)
    pose, R_ids, t_ids = fold_root_into_camera(model, shape_of, result["pose"][ids], camera.R, result["trans"][ids])
    result["pose"][ids], result["trans"][ids] = pose, t_ids
    K[ids], R[ids] = camera.K.numpy(), R_ids.numpy()
    one = (lambda v: v.numpy()) if per_image else (lambda v: v[0].numpy())  # noqa: E731
    # per frame (image sets, clips with their own light) or the video's one
    lighting = shared["lighting"].numpy() if shared["lighting"].shape[0] > 1 else one(shared["lighting"])
    SubjectDir(subject_dir).write_fit(shape=one(shared["shape"]), texture=one(shared["texture"]),
                                      lighting=lighting, expression=result["expression"].numpy(),
                                      pose=result["pose"].numpy(), K=K, R=R, t=result["trans"].numpy(),
                                      fitted=fitted, keyframes=key, image_size=frames.shape[1])
    rendered = np.zeros_like(frames)
    rendered[ids] = (rendered_rgb.permute(0, 2, 3, 1).numpy() * 255).astype(np.uint8)
    write_png(subject_dir / "fit_rgb_overlay.png", overlay_sheet(frames[ids], rendered[ids], landmarks[ids]))
    write_json(subject_dir / "fit_rgb.json", report)
    log.info("RGB fit (%s mode) of %d frames in %.0fs: landmark error %.2f px (NME %.4f), photometric L1 %.4f%s",
             cfg.fit_rgb.mode, fitted.sum(),
             seconds, report["landmark_error_px"], report["landmark_nme"], report["photometric_l1"],
             "; vs truth: shape %.2f mm, expression %.2f mm, jaw %.2f deg" % tuple(report["truth"].values())
             if "truth" in report else "")


if __name__ == "__main__":
    main()
