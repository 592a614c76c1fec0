"""The parametric head model network: CNeRF + 2D neural renderer, the code assembly, and its model file.

geometry code = [beta (shape), theta (neck, jaw, eyes), psi (expression)] conditions the density; appearance code =
[tau (texture), lambda (27 SH lighting values)] conditions the features (seed 002, 3.1.1). A model file holds the
network's sizes, its weights and the resolved config it was trained with - tensors and plain values only, read with
`torch.load(weights_only=True)`, so a crafted file cannot run code.
"""
from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import torch
from torch import nn

from avatarlab.model.cnerf import CNeRF, CNeRFConfig, head_bounds, render_feature_map
from avatarlab.model.renderer2d import NeuralRenderer2D
from avatarlab.render.camera import Camera
from avatarlab.runtime.safe_load import load_tensors

MODEL_FORMAT = "avatarlab.head_nerf/1"


def assemble_codes(params: dict, lighting: torch.Tensor, offsets: dict | None = None):
    """The CNeRF conditioning of eq. (8): the fitted vectors plus their learnable offsets (real samples).
    params: shape (B,S), pose (B,15), expression (B,E), texture (B,T); lighting (B,9,3) or (B,27).
    -> geometry (B, S+12+E) = [shape, pose without the root, expression]; appearance (B, T+27)."""
    def get(k, v):
        return v + offsets[k] if offsets is not None and k in offsets else v

    geometry = torch.cat([get("shape", params["shape"]), get("pose", params["pose"][:, 3:]),
                          get("expression", params["expression"])], 1)
    appearance = torch.cat([get("texture", params["texture"]), get("lighting", lighting.reshape(-1, 27))], 1)
    return geometry, appearance


class HeadNeRFModel(nn.Module):
    def __init__(self, nerf_cfg: CNeRFConfig, renderer_kind: str, feature_size: int, min_channels: int = 32):
        super().__init__()
        self.nerf = CNeRF(nerf_cfg)
        self.renderer = NeuralRenderer2D(nerf_cfg.feature_channels, renderer_kind, min_channels=min_channels)
        self.feature_size = feature_size
        self.renderer_kind, self.min_channels = renderer_kind, min_channels
        # the feature a ray carries where nothing is dense: composited by the remaining transmittance (HeadNeRF's
        # background feature map; one learned vector here, the same at every pixel)
        self.background = nn.Parameter(torch.zeros(nerf_cfg.feature_channels))

    def forward(self, geometry, appearance, camera: Camera, stratified: bool = True, with_opacity: bool = False,
                with_distortion: bool = False):
        """-> image; (image, opacity) with `with_opacity`; (image, opacity, mean ray distortion) with
        `with_distortion` (cnerf.ray_distortion)."""
        fmap, opacity, *distortion = render_feature_map(self.nerf, camera, (self.feature_size, self.feature_size),
                                                        geometry, appearance, stratified, with_distortion)
        fmap = fmap + (1 - opacity) * self.background[None, :, None, None].to(fmap.dtype)
        image = self.renderer(fmap)
        if with_distortion:
            return image, opacity, distortion[0]
        return (image, opacity) if with_opacity else image

    def spec(self) -> dict:
        """What rebuilds this network: plain values only."""
        nerf = asdict(self.nerf.cfg)
        nerf["bound_center"] = list(nerf["bound_center"])
        return {"nerf": nerf, "renderer": self.renderer_kind, "min_channels": self.min_channels,
                "feature_size": self.feature_size}


def nerf_config(model_cfg, head, neck_deg, jaw_open) -> CNeRFConfig:
    """CNeRF sizes from the `model` config section and the head model (its coefficient counts and the bounding
    sphere of its poses within the synthetic neck and jaw ranges)."""
    center, radius = head_bounds(head, neck_deg, float(jaw_open[1]))
    m = model_cfg
    return CNeRFConfig(frequencies=int(m.frequencies), depth=int(m.depth), width=int(m.width),
                       skip_layer=int(m.skip_layer), feature_channels=int(m.feature_channels),
                       samples=int(m.samples), density_scale=float(m.density_scale), n_shape=head.n_shape,
                       n_expression=head.n_expression,
                       n_texture=head.n_texture, bound_center=center, bound_radius=radius)


def build_model(cfg, head, renderer: str | None = None) -> HeadNeRFModel:
    """The network a config describes: `cfg.model` sizes, the renderer kind (default `cfg.model.renderer`)."""
    m = cfg.model
    nerf = nerf_config(m, head, cfg.synthetic.neck_deg, cfg.synthetic.jaw_open)
    return HeadNeRFModel(nerf, renderer or str(m.renderer), int(m.feature_size), int(m.renderer_min_channels))


@torch.no_grad()
def render_in_chunks(net: HeadNeRFModel, geometry: torch.Tensor, appearance: torch.Tensor, camera: Camera,
                     chunk: int = 4) -> torch.Tensor:
    """Deterministic renders (bin midpoints, no jitter) of a batch, `chunk` images at a time on the net's device;
    returned float32 on the CPU."""
    device = next(net.parameters()).device
    geometry, appearance, camera = geometry.to(device), appearance.to(device), camera.to(device)
    return torch.cat([net(geometry[k:k + chunk], appearance[k:k + chunk], camera.index(slice(k, k + chunk)),
                          stratified=False).float().cpu() for k in range(0, len(geometry), chunk)])


def render_frames(net: HeadNeRFModel, frames) -> torch.Tensor:
    """Deterministic renders of a set of fitted frames (anything with per-frame `params`, the lighting among them,
    and `camera()`, e.g. a RealImageSet) from their own fits; float32 on the CPU."""
    return render_in_chunks(net, *assemble_codes(frames.params, frames.params["lighting"]), frames.camera())


def model_file(net: HeadNeRFModel, step: int, config: dict, **extra) -> dict:
    """The contents of a model.pt: format tag, network spec, weights, the iteration it stopped at, the resolved
    config, and any plain extras (e.g. the MLflow run id)."""
    return {"format": MODEL_FORMAT, "spec": net.spec(), "state": net.state_dict(), "step": int(step),
            "config": config, **extra}


def synthetic_mouth(content: dict) -> bool:
    """Whether a model file's synthetic samples came from the mouth-interior head when its training ended: alpha2's
    last 10 000 iterations (seed 002, 3.4, fig. 28) and every model continued from it, so a continuation (the beta
    runs from alpha2, their avatars) keeps drawing them from that head. Files written before the flag existed answer
    from their strategy's mouth phase."""
    if "synthetic_mouth" in content:
        return bool(content["synthetic_mouth"])
    return ((content.get("config") or {}).get("strategy") or {}).get("mouth_from") is not None


def load_model_file(path: str | Path, device: torch.device | str = "cpu") -> tuple[HeadNeRFModel, dict]:
    """A model.pt written by `model_file` -> (network in eval mode on `device`, the file's other contents).
    Anything else - a crafted pickle, another format - stops with one line naming the file."""
    path = Path(path)
    content = load_tensors(path, what="a head model (model.pt)")
    if not isinstance(content, dict) or content.get("format") != MODEL_FORMAT:
        raise ValueError(f"{path}: not an avatarlab head model file (expected format {MODEL_FORMAT})")
    spec = content["spec"]
    nerf = dict(spec["nerf"], bound_center=tuple(spec["nerf"]["bound_center"]))
    net = HeadNeRFModel(CNeRFConfig(**nerf), spec["renderer"], int(spec["feature_size"]), int(spec["min_channels"]))
    net.load_state_dict(content["state"])
    return net.eval().to(device), content
