"""Real-time synthetic training samples (seed 002, section 3.2).

Per step: take the fitted parameters of random real images, add U[-0.3, 0.3] to shape, expression and texture, clip to
[-2, 2]; draw the neck rotation (x, z in [-80, 80] deg, y in [-60, 60] deg at paper settings), the jaw and the camera
uniformly; render with the head model. Lighting comes from the real image's fit.
"""
from __future__ import annotations

import math

import torch

from avatarlab.headmodel.flame import clip_coefficients
from avatarlab.render.camera import orbit_camera
from avatarlab.render.head_renderer import HeadRenderer


class SyntheticGenerator:
    def __init__(self, model, real_params: dict[str, torch.Tensor], cfg, image_size: int, background,
                 device: torch.device | None = None, fixed_identity: bool = False):
        """real_params: shape (R,S), expression (R,E), texture (R,T), lighting (R,9,3) of the real image set.
        The samples are drawn on the CPU (one generator: the same samples on every device) and rendered on
        `device` (default: where the model is), where the returned tensors are. `fixed_identity` (fine-tuning):
        no noise on the real image's shape and texture - the subject's own identity."""
        self.fixed_identity = fixed_identity
        self.device = device if device is not None else model.faces.device
        self.model = model.to(self.device)
        self.real = real_params
        self.cfg = cfg
        self.size = image_size
        self.renderer = HeadRenderer(model, background=background)

    def _uniform(self, n, low, high, g):
        return low + (high - low) * torch.rand(n, generator=g)

    @torch.no_grad()
    def sample(self, n: int, g: torch.Generator) -> dict:
        c = self.cfg
        pick = torch.randint(0, self.real["shape"].shape[0], (n,), generator=g)
        noise = lambda t: t + (torch.rand(t.shape, generator=g) * 2 - 1) * float(c.coefficient_noise)  # noqa: E731
        keep = (lambda t: t) if self.fixed_identity else noise  # fine-tuning: the subject's own shape/texture
        params = {"shape": clip_coefficients(keep(self.real["shape"][pick])),
                  "expression": clip_coefficients(noise(self.real["expression"][pick])),
                  "texture": clip_coefficients(keep(self.real["texture"][pick])),
                  "pose": torch.zeros(n, 15)}
        deg = math.pi / 180
        for axis, limit in enumerate(c.neck_deg):
            params["pose"][:, 3 + axis] = self._uniform(n, -limit * deg, limit * deg, g)
        params["pose"][:, 6] = self._uniform(n, c.jaw_open[0], c.jaw_open[1], g)
        distance = self._uniform(n, c.camera_distance[0], c.camera_distance[1], g)
        yaw = self._uniform(n, -c.camera_yaw_deg, c.camera_yaw_deg, g)
        pitch = self._uniform(n, -c.camera_pitch_deg, c.camera_pitch_deg, g)
        camera = orbit_camera(distance, yaw, pitch, image_size=(self.size, self.size), batch=n,
                              focal=float(c.focal_over_size) * self.size)
        lighting = self.real["lighting"][pick].to(self.device)
        params, camera = {k: v.to(self.device) for k, v in params.items()}, camera.to(self.device)
        out = self.renderer(params, camera, lighting, geometry_images=False)
        return {"images": out.rgb, "masks": out.mask, "params": params, "lighting": lighting, "camera": camera}
