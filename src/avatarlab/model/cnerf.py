"""CNeRF: a NeRF conditioned on FLAME's shape, pose and expression (density), and texture and lighting (features).

Per sample point (seed 002, 3.1.1, figure 13): PE(xyz) + beta + theta + psi -> MLP (with an input skip) -> density
sigma and a hidden vector; hidden -> 1 FC -> + tau + lambda -> 2 FC -> feature v. No view direction.
Feature maps come from volume rendering (eq. 7) along rays through the pixels of a low-resolution feature map whose
intrinsics are the image's scaled by (h_feature / h_image, w_feature / w_image).

Two things make it cheap without changing the model:
- A linear layer over a concatenation [PE(x), code] is W_x PE(x) + W_c code: the code part is the same for every point
  of one sample, so it is computed once per sample and added per point (the layers and weights are the dissertation's
  concatenated ones; `CNeRF.forward_dense` is the literal reading, kept for tests).
- Rays are sampled only inside the head's bounding sphere (its centre and radius are buffers, measured from the head
  model in `head_bounds`), so the interval follows each frame's camera; rays that miss it carry zero features.
"""
from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from avatarlab.render.camera import Camera


def positional_encoding(x: torch.Tensor, frequencies: int) -> torch.Tensor:
    """x (..., 3) -> (..., 3 + 6 * frequencies): x, sin(2^k pi x), cos(2^k pi x)."""
    scales = (2.0 ** torch.arange(frequencies, device=x.device, dtype=x.dtype)) * torch.pi
    angles = x[..., None] * scales  # (..., 3, F)
    return torch.cat([x, angles.sin().flatten(-2), angles.cos().flatten(-2)], -1)


@dataclass
class CNeRFConfig:
    frequencies: int = 10
    depth: int = 8
    width: int = 384
    skip_layer: int = 5  # the layer whose input is [hidden, PE(x), geometry code] again (after five layers)
    feature_channels: int = 256
    samples: int = 64
    coordinate_scale: float = 5.0  # world metres -> network units (the head spans about +-1)
    density_scale: float = 1.0  # sigma = density_scale * softplus(raw - 1), per metre: with samples ~2 cm apart a
    #                             scale of ~100 makes a surface opaque at raw ~ 2 instead of ~100
    n_shape: int = 100
    n_expression: int = 50
    n_pose: int = 12  # neck, jaw, eyes (the root is folded into the camera by the RGB fit)
    n_texture: int = 50
    n_lighting: int = 27
    bound_center: tuple[float, float, float] = (0.0, 0.0, 0.0)  # world metres: the head's bounding sphere
    bound_radius: float = 0.25


def _linear_split(layer: nn.Linear, per_point: torch.Tensor, per_sample: torch.Tensor, sample_of_point: torch.Tensor,
                  split: int) -> torch.Tensor:
    """layer([per_point, per_sample[sample_of_point]]) without repeating the per-sample part for every point."""
    weight = layer.weight
    return (F.linear(per_point, weight[:, :split], layer.bias)
            + F.linear(per_sample, weight[:, split:]).index_select(0, sample_of_point))


class CNeRF(nn.Module):
    def __init__(self, cfg: CNeRFConfig):
        super().__init__()
        self.cfg = cfg
        self.pe_dim = 3 + 6 * cfg.frequencies
        self.geometry_dim = cfg.n_shape + cfg.n_pose + cfg.n_expression
        self.appearance_dim = cfg.n_texture + cfg.n_lighting
        in_dim = self.pe_dim + self.geometry_dim
        self.layers = nn.ModuleList(
            nn.Linear(in_dim if i == 0 else cfg.width + (in_dim if i == cfg.skip_layer else 0), cfg.width)
            for i in range(cfg.depth))
        self.density = nn.Linear(cfg.width, 1)
        self.hidden = nn.Linear(cfg.width, cfg.width)
        self.appearance = nn.Sequential(nn.Linear(cfg.width + self.appearance_dim, cfg.width // 2),
                                        nn.ReLU(inplace=True), nn.Linear(cfg.width // 2, cfg.feature_channels))
        self.register_buffer("bound_center", torch.tensor(cfg.bound_center, dtype=torch.float32))
        self.register_buffer("bound_radius", torch.tensor(float(cfg.bound_radius)))
        # None: the MLP computes in the surrounding precision; torch.bfloat16: its matmuls under bfloat16 autocast,
        # outputs float32 (`model.mlp_precision`; set by the training loop for training only, not saved)
        self.compute_dtype: torch.dtype | None = None

    def forward(self, points: torch.Tensor, sample_of_point: torch.Tensor, geometry_code: torch.Tensor,
                appearance_code: torch.Tensor):
        """points (N, 3) world; sample_of_point (N,) long, the batch sample each point belongs to;
        geometry_code (B, S+12+E); appearance_code (B, T+27) -> sigma (N,), features (N, C)."""
        kind = points.device.type
        if self.compute_dtype is None or torch.is_autocast_enabled(kind):
            return self._forward(points, sample_of_point, geometry_code, appearance_code)
        with torch.autocast(kind, dtype=self.compute_dtype):
            sigma, v = self._forward(points, sample_of_point, geometry_code, appearance_code)
        return sigma.float(), v.float()

    @contextlib.contextmanager
    def computing_in(self, dtype: torch.dtype | None):
        """`compute_dtype` set to `dtype` inside the block, and back to what it was after it."""
        before, self.compute_dtype = self.compute_dtype, dtype
        try:
            yield
        finally:
            self.compute_dtype = before

    def _forward(self, points, sample_of_point, geometry_code, appearance_code):
        pe = positional_encoding(points * self.cfg.coordinate_scale, self.cfg.frequencies)
        h = F.relu(_linear_split(self.layers[0], pe, geometry_code, sample_of_point, self.pe_dim))
        for i in range(1, len(self.layers)):
            if i == self.cfg.skip_layer:
                h = _linear_split(self.layers[i], torch.cat([h, pe], -1), geometry_code, sample_of_point,
                                  self.cfg.width + self.pe_dim)
            else:
                h = self.layers[i](h)
            h = F.relu(h)
        sigma = self.cfg.density_scale * F.softplus(self.density(h).squeeze(-1) - 1.0)
        first, *rest = self.appearance
        v = _linear_split(first, self.hidden(h), appearance_code, sample_of_point, self.cfg.width)
        for layer in rest:
            v = layer(v)
        return sigma, v

    def forward_dense(self, points: torch.Tensor, geometry_code: torch.Tensor, appearance_code: torch.Tensor):
        """The literal figure 13: every point's input is the concatenation [PE(x), beta, theta, psi].
        points (B, P, 3) -> sigma (B, P), features (B, P, C). Same numbers as `forward` (tested)."""
        n = points.shape[1]
        x_in = torch.cat([positional_encoding(points * self.cfg.coordinate_scale, self.cfg.frequencies),
                          geometry_code[:, None].expand(-1, n, -1)], -1)
        h = x_in
        for i, layer in enumerate(self.layers):
            h = F.relu(layer(torch.cat([h, x_in], -1) if i == self.cfg.skip_layer else h))
        sigma = self.cfg.density_scale * F.softplus(self.density(h).squeeze(-1) - 1.0)
        v = self.appearance(torch.cat([self.hidden(h), appearance_code[:, None].expand(-1, n, -1)], -1))
        return sigma, v

    def frozen_prefix(self, count: int):
        """Parameters of the first `count` MLP layers (frozen during per-subject fine-tuning)."""
        return [p for layer in self.layers[:count] for p in layer.parameters()]


def camera_rays(camera: Camera, size: tuple[int, int]):
    """Rays through the pixel centres of a (h, w) map of `camera` (intrinsics scaled). -> origins, dirs (B,h*w,3)
    in world coordinates; each direction has camera z = 1, so the ray parameter t is the camera depth."""
    cam = camera.scaled(size)
    h, w = size
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    pix = torch.stack([xs + 0.5, ys + 0.5, torch.ones_like(xs)], -1).reshape(-1, 3).to(cam.K)
    dirs_cam = torch.einsum("bij,pj->bpi", torch.linalg.inv(cam.K), pix)
    R_t = cam.R.transpose(1, 2)
    dirs = torch.einsum("bij,bpj->bpi", R_t, dirs_cam)
    origins = (-torch.einsum("bij,bj->bi", R_t, cam.t))[:, None].expand_as(dirs)
    return origins, dirs


def sphere_interval(origins: torch.Tensor, dirs: torch.Tensor, center: torch.Tensor, radius: torch.Tensor,
                    min_depth: float = 1e-3):
    """Where rays o + t d cross the sphere |x - center| = radius: near, far (..,) and hit (..,) bool."""
    oc = origins - center
    a = (dirs * dirs).sum(-1)
    b = (dirs * oc).sum(-1)
    c = (oc * oc).sum(-1) - radius**2
    disc = b * b - a * c
    root = disc.clamp(min=0).sqrt()
    near = ((-b - root) / a).clamp(min=min_depth)
    far = (-b + root) / a
    return near, far, (disc > 0) & (far > near)


def compositing_weights(sigma: torch.Tensor, depths: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. (7)'s weights T_i (1 - exp(-sigma_i delta_i)) of samples at `depths` (..., N), and the deltas (the last
    sample's delta is the interval before it)."""
    steps = depths[..., 1:] - depths[..., :-1]
    delta = torch.cat([steps, steps[..., -1:]], -1)
    alpha = 1.0 - torch.exp(-sigma * delta)
    transmittance = torch.cumprod(torch.cat([torch.ones_like(alpha[..., :1]), 1.0 - alpha + 1e-10], -1), -1)[..., :-1]
    return alpha * transmittance, delta


def volume_render_features(sigma: torch.Tensor, features: torch.Tensor, depths: torch.Tensor,
                           composited: tuple[torch.Tensor, torch.Tensor] | None = None):
    """Eq. (7): FeatureMap(r) = sum_i T_i (1 - exp(-sigma_i delta_i)) v_i, T_i = exp(-sum_{j<i} sigma_j delta_j),
    over the ray's interval [t_1, t_N] (the last sample's delta is the interval before it, not NeRF's "to
    infinity": a ray may stay transparent, and the background shows through - HeadNeRFModel).

    sigma (..., N), features (..., N, C), depths (..., N) along the ray (camera z, since dirs have z = 1);
    `composited`: `compositing_weights(sigma, depths)` when the caller has them already.
    Returns the feature values (..., C) and the accumulated opacity (...).
    """
    weights, _ = composited if composited is not None else compositing_weights(sigma, depths)
    return (weights[..., None] * features).sum(-2), weights.sum(-1)


def ray_distortion(sigma: torch.Tensor, depths: torch.Tensor, near: torch.Tensor, far: torch.Tensor,
                   composited: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """Mip-NeRF 360's distortion loss (Barron et al. 2022, eq. 15) per ray, on the ray's interval normalised to
    [0, 1] and on the ray's weights normalised to sum 1: sum_ij w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 (s_i+1 - s_i),
    w the compositing weights of eq. (7) over their sum, m the bins' midpoints; times the ray's opacity, held fixed.
    Small when a ray's weight sits in one thin layer (a surface); large when it is spread along the ray, which renders
    a feature at several depths - copies of it under a new view. Normalised, so that making a ray transparent does
    not lower it (the 2D renderer could still read a transparent ray's features).
    sigma, depths (R, N); near, far (R,) -> (R,); `composited` as in `volume_render_features`."""
    span = (far - near).clamp(min=1e-6)[:, None]
    s = (depths - near[:, None]) / span
    w, delta = composited if composited is not None else compositing_weights(sigma, depths)
    opacity = w.sum(-1)
    w = w / opacity.clamp(min=1e-6)[:, None]
    width = delta / span
    pairwise = (w[:, :, None] * w[:, None, :] * (s[:, :, None] - s[:, None, :]).abs()).sum((1, 2))
    return (pairwise + (w**2 * width).sum(-1) / 3) * opacity.detach()


def ray_samples(near: torch.Tensor, far: torch.Tensor, count: int, stratified: bool) -> torch.Tensor:
    """count depths per ray between near and far (R,): bin midpoints, or one uniform draw per bin when stratified."""
    offsets = torch.rand(near.shape[0], count, device=near.device) if stratified else torch.full(
        (near.shape[0], count), 0.5, device=near.device)
    u = (torch.arange(count, device=near.device) + offsets) / count
    return near[:, None] + (far - near)[:, None] * u


def render_feature_map(nerf: CNeRF, camera: Camera, size: tuple[int, int], geometry_code, appearance_code,
                       stratified: bool = True, with_distortion: bool = False):
    """-> feature map (B, C, h, w) and opacity (B, 1, h, w), and with `with_distortion` the mean `ray_distortion`
    of the rays that were sampled (a scalar). Only rays through the head's bounding sphere are sampled
    (`nerf.cfg.samples` points between where they enter and leave it)."""
    cfg = nerf.cfg
    origins, dirs = camera_rays(camera, size)
    near, far, hit = sphere_interval(origins, dirs, nerf.bound_center, nerf.bound_radius)
    b_idx, r_idx = hit.nonzero(as_tuple=True)
    depths = ray_samples(near[b_idx, r_idx], far[b_idx, r_idx], cfg.samples, stratified)  # (R', N)
    points = origins[b_idx, r_idx][:, None] + dirs[b_idx, r_idx][:, None] * depths[..., None]
    sigma, feat = nerf(points.reshape(-1, 3), b_idx.repeat_interleave(cfg.samples), geometry_code, appearance_code)
    sigma = sigma.reshape(-1, cfg.samples).float()
    composited = compositing_weights(sigma, depths)  # eq. (7)'s weights, once for the features and the distortion
    values, opacity = volume_render_features(sigma, feat.reshape(-1, cfg.samples, feat.shape[-1]), depths, composited)
    b, h, w = dirs.shape[0], *size
    fmap = values.new_zeros(b, h * w, values.shape[-1]).index_put((b_idx, r_idx), values)
    alpha = opacity.new_zeros(b, h * w).index_put((b_idx, r_idx), opacity)
    out = fmap.transpose(1, 2).reshape(b, -1, h, w), alpha.reshape(b, 1, h, w)
    if not with_distortion:
        return out
    distortion = ray_distortion(sigma, depths, near[b_idx, r_idx], far[b_idx, r_idx], composited)
    return *out, distortion.mean() if len(distortion) else sigma.sum() * 0


@torch.no_grad()
def head_bounds(head, neck_deg, jaw_max: float, margin: float = 0.01, samples: int = 64) -> tuple[tuple, float]:
    """The head model's bounding sphere in its own (world) frame over the poses the data has: random shapes and
    expressions in [-2, 2], neck rotations within `neck_deg` (x, y, z limits in degrees), the jaw up to `jaw_max`
    radians. -> (centre (x, y, z), radius) in metres, the radius grown by `margin`."""
    g = torch.Generator().manual_seed(0)  # draws on the CPU, the head evaluated where it is
    params = head.zeros(samples, device=torch.device("cpu"))
    params["shape"] = torch.rand(params["shape"].shape, generator=g) * 4 - 2
    params["expression"] = torch.rand(params["expression"].shape, generator=g) * 4 - 2
    limits = torch.tensor([float(d) for d in neck_deg]) * math.pi / 180
    params["pose"][:, 3:6] = (torch.rand(samples, 3, generator=g) * 2 - 1) * limits
    params["pose"][:, 3:6][: len(limits) * 2] = 0  # and the extremes of each axis alone
    for k in range(len(limits)):
        params["pose"][2 * k, 3 + k], params["pose"][2 * k + 1, 3 + k] = limits[k], -limits[k]
    params["pose"][:, 6] = torch.rand(samples, generator=g) * jaw_max
    device = head.buffers_.v_template.device
    params = {k: v.to(device) for k, v in params.items()}
    vertices = head(params["shape"], params["expression"], params["pose"]).vertices.reshape(-1, 3).cpu()
    center = (vertices.min(0).values + vertices.max(0).values) / 2
    radius = float((vertices - center).norm(dim=-1).max()) + margin
    return tuple(round(float(c), 4) for c in center), round(radius, 4)
