"""Textured, SH-lit mesh rendering: RGB, mask, depth and projected landmarks from a posed head."""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from avatarlab.render.camera import Camera
from avatarlab.render.lighting import sh_basis
from avatarlab.render.rasterizer import Fragments, rasterize

#: camera (OpenCV) axes -> view axes used for lighting: x right, y up, z towards the camera.
_CAM_TO_VIEW = torch.tensor([1.0, -1.0, -1.0])


@dataclass
class RenderOutput:
    rgb: torch.Tensor  # (B, 3, H, W) in [0, 1], composited over the background
    mask: torch.Tensor  # (B, 1, H, W)
    depth: torch.Tensor | None  # (B, 1, H, W) camera z in metres, 0 on the background (None: not asked for)
    landmarks2d: torch.Tensor | None  # (B, L, 2) pixel coordinates (x, y)
    normals: torch.Tensor | None  # (B, 3, H, W) view-frame normals, 0 on the background (None: not asked for)
    fragments: Fragments


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted vertex normals. vertices (B, V, 3) -> (B, V, 3) unit."""
    b, v = vertices.shape[:2]
    v0, v1, v2 = (vertices.index_select(1, faces[:, k]) for k in range(3))
    face_n = torch.cross(v1 - v0, v2 - v0, dim=-1)  # (B, F, 3), |n| = 2 x area
    # every face adds its normal to its three corners: one scatter over the (V, B*3) layout
    per_corner = face_n.permute(1, 0, 2).reshape(-1, 1, b * 3).expand(-1, 3, -1).reshape(-1, b * 3)
    normals = vertices.new_zeros(v, b * 3).index_add_(0, faces.reshape(-1), per_corner)
    return F.normalize(normals.reshape(v, b, 3).transpose(0, 1), dim=-1, eps=1e-12)


class MeshRenderer:
    """Renders (vertices, albedo, camera, lighting). Albedo is per-vertex (B, V, 3) or a UV map (B, 3, Ht, Wt)."""

    def __init__(self, faces: torch.Tensor, background=(0.0, 0.0, 0.0), backface_shade: float = 0.15,
                 uv: torch.Tensor | None = None, uv_faces: torch.Tensor | None = None):
        self.faces = faces
        self.background = torch.as_tensor(background, dtype=torch.float32)
        self.backface_shade = backface_shade  # the inside of the closed head (seen through the open mouth) is unlit
        self.uv, self.uv_faces = uv, uv_faces

    def __call__(self, vertices: torch.Tensor, albedo: torch.Tensor, camera: Camera, lighting: torch.Tensor,
                 landmarks3d: torch.Tensor | None = None, geometry_images: bool = True) -> RenderOutput:
        """geometry_images=False skips the depth and normal images (training samples need RGB and mask only)."""
        faces = self.faces.to(vertices.device)
        cam_vertices = camera.world_to_camera(vertices)
        screen = camera.project(vertices)
        frags = rasterize(screen, faces, camera.image_size)
        normals_view = vertex_normals(cam_vertices, faces) * _CAM_TO_VIEW.to(vertices)
        n_pix = F.normalize(frags.interpolate(normals_view, faces), dim=-1, eps=1e-12)
        if albedo.dim() == 4:  # UV texture map
            uv = frags.interpolate(self.uv[None].to(vertices).expand(frags.batch, -1, -1), self.uv_faces.to(vertices.device))
            grid = frags.to_image(uv * 2 - 1, 0.0).permute(0, 2, 3, 1) * torch.tensor([1.0, -1.0]).to(vertices)
            colour = F.grid_sample(albedo, grid, align_corners=False)
            colour = colour.permute(0, 2, 3, 1)[frags.batch_idx, frags.pixel_y, frags.pixel_x]
        else:
            colour = frags.interpolate(albedo, faces)
        shading = torch.einsum("pk,pkc->pc", sh_basis(n_pix), lighting.index_select(0, frags.batch_idx))
        tri = frags.corners(cam_vertices, faces)
        face_n = torch.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)
        facing = ((face_n * tri.mean(1)).sum(-1) < 0).to(vertices)
        shading = shading * (facing + (1 - facing) * self.backface_shade)[:, None]
        rgb_px = (colour * shading).clamp(0.0, 1.0)
        bg = self.background.to(vertices)
        landmarks2d = camera.project(landmarks3d)[..., :2] if landmarks3d is not None else None
        return RenderOutput(rgb=frags.to_image(rgb_px, bg), mask=frags.mask(),
                            depth=frags.to_image(frags.depth[:, None], 0.0) if geometry_images else None,
                            landmarks2d=landmarks2d, normals=frags.to_image(n_pix, 0.0) if geometry_images else None,
                            fragments=frags)

