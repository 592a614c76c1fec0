"""Pinhole camera: intrinsics K, extrinsics (R, t) world -> camera (OpenCV axes: x right, y down, z forward)."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from kornia.geometry.camera.perspective import project_points
from kornia.geometry.conversions import axis_angle_to_rotation_matrix


@dataclass
class Camera:
    K: torch.Tensor  # (B, 3, 3) intrinsics in pixels of an image of `image_size`
    R: torch.Tensor  # (B, 3, 3) world -> camera rotation
    t: torch.Tensor  # (B, 3) world -> camera translation
    image_size: tuple[int, int]  # (H, W)

    @property
    def batch(self) -> int:
        return self.K.shape[0]

    def world_to_camera(self, points: torch.Tensor) -> torch.Tensor:
        """points (B, N, 3) -> camera coordinates (B, N, 3)."""
        return torch.einsum("bij,bnj->bni", self.R, points) + self.t[:, None]

    def project(self, points: torch.Tensor) -> torch.Tensor:
        """points (B, N, 3) world -> (B, N, 3): pixel u, pixel v, depth z (camera z, metres)."""
        cam = self.world_to_camera(points)
        uv = project_points(cam, self.K[:, None].expand(-1, cam.shape[1], -1, -1))
        return torch.cat([uv, cam[..., 2:]], dim=-1)

    def scaled(self, image_size: tuple[int, int]) -> "Camera":
        """The same camera for another resolution (e.g. a CNeRF feature map): K scaled by h'/h, w'/w."""
        sy, sx = image_size[0] / self.image_size[0], image_size[1] / self.image_size[1]
        return replace(self, K=scale_intrinsics(self.K, sx, sy), image_size=tuple(image_size))

    def to(self, device) -> "Camera":
        return replace(self, K=self.K.to(device), R=self.R.to(device), t=self.t.to(device))

    def index(self, idx) -> "Camera":
        """The cameras of batch entries `idx` (a slice, indices or a mask)."""
        return replace(self, K=self.K[idx], R=self.R[idx], t=self.t[idx])

    @staticmethod
    def cat(cameras: list["Camera"]) -> "Camera":
        """One batch of cameras of the same image size."""
        cameras = [c for c in cameras if c is not None]
        if len(cameras) == 1:
            return cameras[0]
        return Camera(K=torch.cat([c.K for c in cameras]), R=torch.cat([c.R for c in cameras]),
                      t=torch.cat([c.t for c in cameras]), image_size=cameras[0].image_size)


def intrinsics(focal: torch.Tensor | float, image_size: tuple[int, int], batch: int = 1,
               principal: tuple[float, float] | None = None) -> torch.Tensor:
    """(B, 3, 3) with focal length in pixels and the principal point at the image centre by default."""
    h, w = image_size
    cx, cy = principal if principal is not None else (w / 2.0, h / 2.0)
    focal = torch.as_tensor(focal, dtype=torch.float32).reshape(-1).expand(batch)
    K = torch.zeros(batch, 3, 3)
    K[:, 0, 0] = focal
    K[:, 1, 1] = focal
    K[:, 0, 2] = cx
    K[:, 1, 2] = cy
    K[:, 2, 2] = 1.0
    return K


def scale_intrinsics(K: torch.Tensor, sx: float, sy: float) -> torch.Tensor:
    """Intrinsics for an image resized by (sx, sy); pixel centres stay aligned (half-pixel convention)."""
    S = torch.tensor([[sx, 0.0, 0.0], [0.0, sy, 0.0], [0.0, 0.0, 1.0]], dtype=K.dtype, device=K.device)
    return S @ K


def extrinsics_from_axis_angle(axis_angle: torch.Tensor, translation: torch.Tensor):
    """axis_angle (B, 3), translation (B, 3) -> R (B, 3, 3), t (B, 3)."""
    return axis_angle_to_rotation_matrix(axis_angle), translation


#: A camera on the +z axis of the head looking back at it: world (y up, z to viewer) -> OpenCV axes.
FLIP_YZ = torch.diag(torch.tensor([1.0, -1.0, -1.0]))


def orbit_camera(distance, yaw_deg=0.0, pitch_deg=0.0, target=(0.0, 0.0, 0.0), focal=None, image_size=(256, 256),
                 fov_height: float = 0.32, batch: int | None = None) -> Camera:
    """Camera on a sphere around `target` looking at it. yaw turns around the vertical axis, pitch raises it.

    Focal length defaults to the one that makes `fov_height` metres at the target span the image height.
    Scalars or (B,) tensors for distance, yaw and pitch.
    """
    as_t = lambda v: torch.as_tensor(v, dtype=torch.float32).reshape(-1)  # noqa: E731
    d, yaw, pitch = as_t(distance), as_t(yaw_deg) * math.pi / 180, as_t(pitch_deg) * math.pi / 180
    n = batch or max(len(d), len(yaw), len(pitch))
    d, yaw, pitch = d.expand(n), yaw.expand(n), pitch.expand(n)
    # world -> camera: first turn the world by -yaw about y and by pitch about x, then flip into OpenCV axes.
    zeros = torch.zeros(n)
    r_yaw = axis_angle_to_rotation_matrix(torch.stack([zeros, -yaw, zeros], -1))
    r_pitch = axis_angle_to_rotation_matrix(torch.stack([pitch, zeros, zeros], -1))
    R = FLIP_YZ @ r_pitch @ r_yaw
    target_t = torch.as_tensor(target, dtype=torch.float32)
    t = -torch.einsum("bij,j->bi", R, target_t) + torch.stack([zeros, zeros, d], -1)
    if focal is None:
        focal = d * image_size[0] / fov_height
    return Camera(K=intrinsics(focal, image_size, n), R=R, t=t, image_size=tuple(image_size))
