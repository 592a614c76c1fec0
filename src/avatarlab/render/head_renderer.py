"""Head model + mesh renderer in one call: parameters and a camera in, images, masks, depth and landmarks out."""
from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from avatarlab.render.camera import Camera
from avatarlab.render.lighting import default_lighting
from avatarlab.render.mesh_renderer import MeshRenderer, RenderOutput

if TYPE_CHECKING:  # render/ is a leaf: any object with the head model's interface will do
    from avatarlab.headmodel.flame import HeadModel


class HeadRenderer:
    def __init__(self, model: "HeadModel", background=(0.5, 0.5, 0.5), backface_shade: float = 0.15):
        albedo = model.albedo_model
        self.model = model
        self.mesh_renderer = MeshRenderer(model.faces, background=background, backface_shade=backface_shade,
                                          uv=albedo.uv if albedo.is_uv else None,
                                          uv_faces=albedo.uv_faces if albedo.is_uv else None)

    def __call__(self, params: dict[str, torch.Tensor], camera: Camera,
                 lighting: torch.Tensor | None = None, geometry_images: bool = True) -> RenderOutput:
        """params: shape (B,S), expression (B,E), pose (B,15), texture (B,T); lighting (B,9,3) or the default.
        geometry_images=False: RGB, mask and landmarks only (no depth and normal images)."""
        out = self.model(params["shape"], params["expression"], params["pose"])
        if lighting is None:
            lighting = default_lighting(params["pose"].shape[0], device=params["pose"].device)
        return self.mesh_renderer(out.vertices, self.model.albedo(params["texture"]), camera, lighting,
                                  out.landmarks3d, geometry_images)
