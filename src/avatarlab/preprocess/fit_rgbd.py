"""FLAME fit from RGBD (seed 002, section 2.4, eqs. 2-5).

2D landmarks are lifted to 3D with the depth map; the point cloud (head mask, valid depth) is cropped to the range of
the 3D landmarks. Then three blocks with Adam:
  block 1 (eq. 2): RMSE(lmk3D_gt, lmk3D_pred) over pose and camera extrinsics;
  block 2 (eq. 3): w1 RMSE + w2 (1/|PCD|) sum_p min_q |p - q|^2 over shape, expression, pose and camera;
  block 3 (eq. 4): the point-to-mesh distance over shape;
then texture and lighting by masked photometric L1 (eq. 5). Quality = sqrt(Loss3), in metres (the dissertation:
0.0002 m on its ZED2 captures). Validated here on synthetic RGBD rendered from known parameters with depth noise.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix
from scipy.spatial import cKDTree

from avatarlab.headmodel import HeadModel, load_head_model
from avatarlab.metrics.alignment import procrustes_error_mm, similarity_transform
from avatarlab.render.camera import Camera
from avatarlab.render.head_renderer import HeadRenderer
from avatarlab.render.lighting import default_lighting
from avatarlab.render.mesh_renderer import vertex_normals
from avatarlab.runtime.entry import entry_point
from avatarlab.runtime.io import write_json
from avatarlab.runtime.safe_load import InputFileError, load_arrays

log = logging.getLogger(__name__)
READS = ('seed', 'preprocess', 'fit_rgbd', 'head_model')  # the config sections this step reads (runtime/entry.py)
RELIABLE = np.arange(17, 68)  # inner landmarks: the jaw contour lies on the silhouette, where depth is unreliable


def lift_landmarks(landmarks: np.ndarray, depth: np.ndarray, K: np.ndarray, window: int = 2):
    """landmarks (L,2) pixels, depth (H,W) metres -> points (L,3) camera frame and a validity mask (L,)."""
    h, w = depth.shape
    points = np.zeros((len(landmarks), 3))
    valid = np.zeros(len(landmarks), bool)
    for i, (x, y) in enumerate(landmarks):
        xi, yi = int(round(x - 0.5)), int(round(y - 0.5))
        patch = depth[max(0, yi - window):yi + window + 1, max(0, xi - window):xi + window + 1]
        patch = patch[patch > 0]
        if patch.size == 0:
            continue
        z = np.median(patch)
        points[i] = [(x - K[0, 2]) * z / K[0, 0], (y - K[1, 2]) * z / K[1, 1], z]
        valid[i] = True
    return points, valid


def depth_to_points(depth: np.ndarray, mask: np.ndarray, K: np.ndarray) -> np.ndarray:
    ys, xs = np.nonzero((depth > 0) & (mask > 0))
    z = depth[ys, xs]
    return np.stack([(xs + 0.5 - K[0, 2]) * z / K[0, 0], (ys + 0.5 - K[1, 2]) * z / K[1, 1], z], 1)


def crop_to_landmarks(points: np.ndarray, lmk3d: np.ndarray, margin: float) -> np.ndarray:
    """Keep the points inside the landmarks' bounding box grown by `margin` metres (the forehead by 2x)."""
    lo, hi = lmk3d.min(0) - margin, lmk3d.max(0) + margin
    lo[1] -= margin  # image y points down: extend upwards over the forehead
    keep = ((points >= lo) & (points <= hi)).all(1)
    return points[keep]


def kabsch_init(model: HeadModel, lmk3d: np.ndarray, valid: np.ndarray):
    """Rigid (R, t) taking the neutral model's landmarks onto the lifted ones (Kabsch; no scale: depth is metric)."""
    p = model.zeros(1)
    with torch.no_grad():
        src = model(p["shape"], p["expression"], p["pose"]).landmarks3d[0].cpu().numpy()[valid].astype(np.float64)
    _, R, t = similarity_transform(src, lmk3d[valid], with_scale=False)
    from kornia.geometry.conversions import rotation_matrix_to_axis_angle

    rot = rotation_matrix_to_axis_angle(torch.from_numpy(R).float()[None])[0]
    return rot, torch.from_numpy(t).float()  # on the CPU


def robust_landmarks(model: HeadModel, lmk3d: np.ndarray, valid: np.ndarray, depth_range: float = 0.04,
                     residual: float = 0.012):
    """Drop lifted landmarks whose depth is not the face's (e.g. inner lips over an open mouth see the inside of
    the head), then those the rigid Kabsch alignment cannot explain; returns the alignment and the kept set."""
    valid = valid.copy()
    z = lmk3d[valid, 2]
    valid &= np.abs(lmk3d[:, 2] - np.median(z)) < depth_range
    for _ in range(2):
        rot, trans = kabsch_init(model, lmk3d, valid)
        p = model.zeros(1)
        with torch.no_grad():
            src = model(p["shape"], p["expression"], p["pose"]).landmarks3d[0].cpu()
            moved = (src @ axis_angle_to_rotation_matrix(rot[None])[0].T + trans).numpy()
        keep = valid & (np.linalg.norm(moved - lmk3d, axis=1) < residual)
        if keep.sum() < 12 or (keep == valid).all():
            break
        valid = keep
    return rot, trans, valid


def landmark_rmse(lmk_pred: torch.Tensor, lmk_gt: torch.Tensor) -> torch.Tensor:
    """Eq. (2), block 1 of the RGBD fit: RMSE between the predicted and the depth-lifted 3D landmarks."""
    return ((lmk_pred - lmk_gt) ** 2).sum(-1).mean().sqrt()


def point_to_mesh_loss(verts_cam: torch.Tensor, normals_cam: torch.Tensor, cloud: torch.Tensor):
    """Eq. (4), block 3: mean squared distance of the cloud's points to the mesh surface (point-to-plane at the
    nearest vertex), and the point-to-vertex term eq. (3) adds a little of. Returns (point_to_plane, to_vertex)."""
    tree = cKDTree(verts_cam.detach().cpu().numpy())
    _, nn = tree.query(cloud.cpu().numpy(), k=1)
    nn = torch.from_numpy(nn).to(cloud.device)
    diff = cloud - verts_cam[nn]
    to_vertex = (diff**2).sum(-1).mean()
    # min over q in M is a distance to the surface: point-to-plane at the nearest vertex approximates it (the
    # distance to the vertex itself would be biased by the vertex spacing); a little point-to-vertex keeps the
    # surface from sliding along itself
    plane = ((diff * normals_cam[nn]).sum(-1) ** 2).mean()
    return plane, to_vertex


def landmark_and_cloud_loss(lmk_pred, lmk_gt, verts_cam, normals_cam, cloud, weights) -> torch.Tensor:
    """Eq. (3), block 2: w1 * landmark RMSE + w2 * cloud-to-mesh distance."""
    return rgbd_block_losses(lmk_pred, lmk_gt, verts_cam, normals_cam, cloud, weights)["block2"]


def rgbd_block_losses(lmk_pred, lmk_gt, verts_cam, normals_cam, cloud, weights) -> dict[str, torch.Tensor]:
    """Eqs. (2)-(4) for one frame: landmark RMSE, cloud-to-vertex chamfer, and point-to-mesh (point-to-plane).

    lmk (L,3), verts_cam/normals_cam (V,3) camera frame, cloud (P,3). Nearest vertices are found without gradients,
    with a KD-tree on the CPU whatever the device.
    """
    plane, to_vertex = point_to_mesh_loss(verts_cam, normals_cam, cloud)
    to_mesh = plane + 0.05 * to_vertex
    lm = landmark_rmse(lmk_pred, lmk_gt)
    return {"block1": lm, "block2": weights[0] * lm + weights[1] * to_mesh, "block3": plane, "to_vertex": to_vertex}


class RGBDFitter:
    """The three blocks of eqs. (2)-(4) on one frame. `prior_weight` scales the Gaussian prior |shape|^2 + |expr|^2
    added to every block: it must stay well below block 3's point-to-plane loss (about 1e-6 m^2 at 1 mm of depth
    noise), or more block-3 iterations pull the shape toward the mean instead of onto the cloud. `cosine_decay`
    lowers each block's learning rate to zero along a cosine, so the last iterations settle instead of jitter."""

    def __init__(self, model: HeadModel, lr: float, block_weights=(1.0, 1.0e4), prior_weight: float = 1e-8,
                 cosine_decay: bool = True):
        self.model = model
        self.lr = lr
        self.block_weights = block_weights
        self.prior_weight = prior_weight
        self.cosine_decay = cosine_decay

    def geometry(self, state):
        out = self.model(state["shape"], state["expression"], state["pose"])
        R = axis_angle_to_rotation_matrix(state["rot"])
        verts = out.vertices @ R.transpose(1, 2) + state["trans"][:, None]
        lmk = out.landmarks3d @ R.transpose(1, 2) + state["trans"][:, None]
        return verts, lmk

    def fit_frame(self, lmk_gt, lmk_valid, cloud, init_rot, init_trans, iterations):
        """On the model's device; lmk_gt (L,3), lmk_valid (L,), cloud (P,3) numpy; init_rot/init_trans (3,)."""
        m = self.model
        device = m.faces.device
        state = {"shape": torch.zeros(1, m.n_shape), "expression": torch.zeros(1, m.n_expression),
                 "pose": torch.zeros(1, 15), "rot": init_rot[None].clone(), "trans": init_trans[None].clone()}
        state = {k: v.to(device).requires_grad_(True) for k, v in state.items()}
        faces = m.faces
        lmk_gt, cloud = torch.from_numpy(lmk_gt).float().to(device), torch.from_numpy(cloud).float().to(device)
        valid = torch.from_numpy(lmk_valid).to(device)
        history = {}
        blocks = (("block1", ("pose", "rot", "trans")),
                  ("block2", ("shape", "expression", "pose", "rot", "trans")),
                  ("block3", ("shape",)))
        for (name, free), steps in zip(blocks, iterations):
            optim = torch.optim.Adam([{"params": [state[k]], "lr": self.lr * (0.1 if k == "trans" else 1.0)}
                                      for k in free])
            decay = torch.optim.lr_scheduler.CosineAnnealingLR(optim, max(steps, 1)) if self.cosine_decay else None
            for _ in range(steps):
                optim.zero_grad()
                verts, lmk = self.geometry(state)
                normals = vertex_normals(verts, faces)
                terms = rgbd_block_losses(lmk[0, valid], lmk_gt[valid], verts[0], normals[0], cloud,
                                          self.block_weights)
                reg = self.prior_weight * ((state["shape"] ** 2).sum() + (state["expression"] ** 2).sum())
                (terms[name] + reg).backward()
                optim.step()
                if decay is not None:
                    decay.step()
            history[name] = float(terms[name].detach())
        with torch.no_grad():
            verts, lmk = self.geometry(state)
            final = rgbd_block_losses(lmk[0, valid], lmk_gt[valid], verts[0], vertex_normals(verts, faces)[0], cloud,
                                      self.block_weights)
        history["loss3"] = float(final["block3"])
        return {k: v.detach() for k, v in state.items()}, history


def texture_fit_loss(pred_rgb: torch.Tensor, pred_mask: torch.Tensor, target: torch.Tensor, mask: torch.Tensor):
    """Eq. (5): mean absolute colour error over the pixels inside both the ground-truth mask and the render."""
    m = mask * pred_mask
    return ((pred_rgb - target).abs() * m).sum() / (3 * m.sum()).clamp(min=1)


def fit_texture(model: HeadModel, state, image, mask, K, iterations: int, lr: float):
    """Eq. (5): texture and lighting by masked photometric L1 with the geometry and camera fixed."""
    size, device = image.shape[:2], state["rot"].device
    renderer = HeadRenderer(model)
    camera = Camera(K=torch.from_numpy(K)[None].float().to(device), R=axis_angle_to_rotation_matrix(state["rot"]),
                    t=state["trans"], image_size=size)
    texture = torch.zeros(1, model.n_texture, device=device, requires_grad=True)
    lighting = default_lighting(1, device=device).requires_grad_(True)
    target = (torch.from_numpy(image).permute(2, 0, 1)[None].float() / 255).to(device)
    m = torch.from_numpy(mask)[None, None].float().to(device)
    optim = torch.optim.Adam([texture, lighting], lr=lr)
    loss = torch.tensor(0.0, device=device)
    for _ in range(iterations):
        optim.zero_grad()
        params = {"shape": state["shape"], "expression": state["expression"], "pose": state["pose"],
                  "texture": texture}
        out = renderer(params, camera, lighting)
        loss = texture_fit_loss(out.rgb, out.mask, target, m)
        loss.backward()
        optim.step()
    return texture.detach(), lighting.detach(), float(loss.detach())


def read_video(path: str | Path) -> list[np.ndarray]:
    import cv2

    cap = cv2.VideoCapture(str(path))
    video = []
    while True:
        ok, frame = cap.read()
        if not ok:
            return video
        video.append(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))


def frame_observations(fit, truth: dict, video: list, i: int, rng: np.random.Generator):
    """What the fit sees of frame i: the depth with sensor noise, the 2D landmarks (dlib's, or the truth's where dlib
    finds none or `detected_landmarks` is off) and the camera intrinsics."""
    depth = truth["depth"][i] + (truth["depth"][i] > 0) * rng.normal(0, float(fit.depth_noise_m),
                                                                     truth["depth"][i].shape)
    lm2d = truth["landmarks2d"][i]
    if bool(fit.detected_landmarks):
        from avatarlab.preprocess.landmarks import detect_landmarks

        det = detect_landmarks(video[i])
        lm2d = det.landmarks if det is not None else lm2d
    return depth, lm2d, truth["K"][i]


def true_geometry(model: HeadModel, truth: dict, i: int, device):
    """The true vertices of frame i in camera space (numpy) and as a tensor with their normals."""
    as_t = lambda a: torch.from_numpy(a).to(device)  # noqa: E731
    with torch.no_grad():
        verts = model(as_t(truth["shape"])[None], as_t(truth["expression"][i:i + 1]),
                      as_t(truth["pose"][i:i + 1])).vertices[0].cpu().numpy()
    cam = (verts @ truth["R"][i].T + truth["t"][i]).astype(np.float32)
    cam_t = torch.from_numpy(cam).to(device)[None]
    return cam, cam_t, vertex_normals(cam_t, model.faces)


def fit_one_frame(model: HeadModel, fitter: RGBDFitter, fit, truth: dict, video: list, i: int,
                  rng: np.random.Generator, device) -> dict:
    """Blocks 1-3 and the texture fit on frame i, scored against the truth; `noise_floor_mm` is sqrt(Loss3) of the
    true geometry on the same noisy cloud (what a perfect fit would score)."""
    depth, lm2d, K = frame_observations(fit, truth, video, i, rng)
    lmk3d, valid = lift_landmarks(lm2d, depth, K)
    valid[np.setdiff1d(np.arange(68), RELIABLE)] = False
    rot0, trans0, valid = robust_landmarks(model, lmk3d, valid)
    cloud = crop_to_landmarks(depth_to_points(depth, truth["masks"][i], K), lmk3d[valid], float(fit.crop_margin_m))
    if len(cloud) > int(fit.max_points):
        cloud = cloud[rng.choice(len(cloud), int(fit.max_points), replace=False)]
    state, hist = fitter.fit_frame(lmk3d, valid, cloud, rot0, trans0, list(fit.block_iterations))
    texture, lighting, photo = fit_texture(model, state, video[i], truth["masks"][i], K,
                                           int(fit.texture_iterations), float(fit.lr))
    true_cam, true_t, true_normals = true_geometry(model, truth, i, device)
    with torch.no_grad():
        verts_fit, _ = fitter.geometry(state)
        floor, _ = point_to_mesh_loss(true_t[0], true_normals[0], torch.from_numpy(cloud).float().to(device))
    face = model.regions["face"].numpy()
    vertex_err = 1000 * np.linalg.norm(verts_fit[0].cpu().numpy() - true_cam, axis=1)[face].mean()
    zeros = lambda n: torch.zeros(1, n, device=device)  # noqa: E731
    with torch.no_grad():
        neutral = lambda s: model(s, zeros(model.n_expression), zeros(15)).vertices[0].cpu().numpy()  # noqa: E731
        shape_err = procrustes_error_mm(neutral(state["shape"])[face],
                                        neutral(torch.from_numpy(truth["shape"]).to(device)[None])[face])
    return {"frame": int(i), "accuracy_mm": 1000 * np.sqrt(hist["loss3"]),
            "noise_floor_mm": 1000 * float(floor.sqrt()), "landmark_rmse_mm": 1000 * hist["block1"],
            "vertex_error_mm": float(vertex_err), "shape_error_mm": shape_err, "photometric_l1": photo,
            "points": int(len(cloud))}


@entry_point(READS)
def main(cfg, device) -> None:
    fit = cfg.fit_rgbd
    truth_path = cfg.preprocess.truth
    if not truth_path or not Path(truth_path).is_file():
        raise InputFileError(f"{truth_path}: the RGBD fit runs on synthetic RGBD (a subject with ground truth)")
    truth = load_arrays(truth_path, ("depth", "masks", "landmarks2d", "K", "R", "t", "shape", "expression", "pose"),
                        "a synthetic subject's truth")
    video = read_video(fit.video)
    rng = np.random.default_rng(int(cfg.seed))
    frames = np.unique(np.linspace(0, len(truth["depth"]) - 1, int(fit.frames)).round().astype(int))
    model = load_head_model(cfg.head_model).to(device)
    fitter = RGBDFitter(model, float(fit.lr), tuple(fit.block_weights), float(fit.prior_weight),
                        bool(fit.cosine_decay))
    per_frame, start = [], time.perf_counter()
    for i in frames:
        per_frame.append(fit_one_frame(model, fitter, fit, truth, video, int(i), rng, device))
        log.info("frame %d: sqrt(Loss3) %.3f mm (noise floor %.3f mm), face vertex error %.2f mm, shape error "
                 "%.2f mm", i, per_frame[-1]["accuracy_mm"], per_frame[-1]["noise_floor_mm"],
                 per_frame[-1]["vertex_error_mm"], per_frame[-1]["shape_error_mm"])
    mean = lambda key: float(np.mean([f[key] for f in per_frame]))  # noqa: E731
    report = {"frames": [int(i) for i in frames], "per_frame": per_frame, "depth_noise_m": float(fit.depth_noise_m),
              "accuracy_mm": mean("accuracy_mm"), "noise_floor_mm": mean("noise_floor_mm"),
              "accuracy_over_noise_floor": mean("accuracy_mm") / max(mean("noise_floor_mm"), 1e-9),
              "vertex_error_mm": mean("vertex_error_mm"), "shape_error_mm": mean("shape_error_mm"),
              "landmark_rmse_mm": mean("landmark_rmse_mm"), "seconds": time.perf_counter() - start,
              "landmarks": "dlib" if bool(fit.detected_landmarks) else "ground truth", "published_accuracy_mm": 0.2}
    rgb_report = Path(fit.rgb_report) if fit.rgb_report else None
    if rgb_report is not None and rgb_report.is_file():
        import json

        report["rgb_fit_shape_error_mm"] = json.loads(rgb_report.read_text()).get("truth", {}).get("shape_error_mm")
    write_json(fit.out, report)
    log.info("RGBD fit on %d frames: sqrt(Loss3) %.3f mm = %.2f x its noise floor %.3f mm (published 0.2 mm on ZED2), "
             "face vertex error %.2f mm, shape error %.2f mm", len(frames), report["accuracy_mm"],
             report["accuracy_over_noise_floor"], report["noise_floor_mm"], report["vertex_error_mm"],
             report["shape_error_mm"])


if __name__ == "__main__":
    main()
