"""Pure-PyTorch triangle rasterizer with a z-buffer and differentiable barycentric interpolation.

Visibility (which triangle a pixel sees) is decided without gradients, by enumerating the pixel centres in each
triangle's bounding box and keeping the nearest per pixel. The barycentric coordinates of the winning triangle
are then recomputed with autograd from the projected vertices, so colours, depths and any other per-vertex
attribute are differentiable w.r.t. vertex positions and attribute values (as in PyTorch3D's hard rasterizer).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

_PIXELS_PER_CHUNK = 8_000_000  # bound on candidate (triangle, pixel) pairs held at once
_FACE_BITS = 24  # up to 16.7M triangles
_NO_FACE = torch.iinfo(torch.int64).max


@dataclass
class Fragments:
    """Visible pixels in packed form (P = number of covered pixels over the batch)."""

    batch_idx: torch.Tensor  # (P,)
    pixel_y: torch.Tensor  # (P,)
    pixel_x: torch.Tensor  # (P,)
    face_idx: torch.Tensor  # (P,) index into faces
    bary: torch.Tensor  # (P, 3) perspective-correct barycentric coordinates, differentiable
    depth: torch.Tensor  # (P,) camera depth, differentiable
    image_size: tuple[int, int]
    batch: int

    def to_image(self, values: torch.Tensor, background: torch.Tensor | float = 0.0) -> torch.Tensor:
        """Scatter packed values (P, C) into images (B, C, H, W) over a background (C,) or scalar."""
        h, w = self.image_size
        channels = values.shape[-1]
        bg = torch.as_tensor(background, dtype=values.dtype, device=values.device)
        image = bg.expand(channels).reshape(1, 1, 1, channels).repeat(self.batch, h, w, 1) if bg.ndim else \
            torch.full((self.batch, h, w, channels), float(bg), dtype=values.dtype, device=values.device)
        image = image.index_put((self.batch_idx, self.pixel_y, self.pixel_x), values)
        return image.permute(0, 3, 1, 2)

    def mask(self) -> torch.Tensor:
        """(B, 1, H, W) coverage, 1 where a triangle is visible."""
        ones = torch.ones(self.batch_idx.shape[0], 1, device=self.bary.device)
        return self.to_image(ones, 0.0)

    def corners(self, attributes: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
        """attributes (B, V, C) per vertex -> (P, 3, C) at the corners of each visible pixel's triangle."""
        return gather_corners(attributes, faces, self.batch_idx, self.face_idx)

    def interpolate(self, attributes: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
        """attributes (B, V, C) per vertex -> (P, C) at the visible pixels."""
        return (self.bary[..., None] * self.corners(attributes, faces)).sum(1)


def gather_corners(values: torch.Tensor, faces: torch.Tensor, batch_idx: torch.Tensor,
                   face_idx: torch.Tensor) -> torch.Tensor:
    """values (B, V, C) -> (P, 3, C): values[batch_idx[p], faces[face_idx[p], k]], as one index_select over the
    flattened (B * V, C) values (much faster on the CPU than advanced indexing with 2-D index tensors)."""
    b, v, c = values.shape
    flat = (batch_idx[:, None] * v + faces.index_select(0, face_idx)).reshape(-1)
    return values.reshape(b * v, c).index_select(0, flat).reshape(-1, 3, c)


def _edge(ax, ay, bx, by, px, py):
    return (bx - ax) * (py - ay) - (by - ay) * (px - ax)


@torch.no_grad()
def _visible_faces(screen: torch.Tensor, faces: torch.Tensor, image_size: tuple[int, int], near: float):
    """screen (V, 3) [u, v, z] of one image -> pixel_to_face (H*W,) with -1 where empty."""
    h, w = image_size
    tri = screen[faces]  # (F, 3, 3)
    x, y, z = tri[..., 0], tri[..., 1], tri[..., 2]
    x0 = torch.ceil(x.min(1).values - 0.5).clamp(min=0).long()
    x1 = torch.floor(x.max(1).values - 0.5).clamp(max=w - 1).long()
    y0 = torch.ceil(y.min(1).values - 0.5).clamp(min=0).long()
    y1 = torch.floor(y.max(1).values - 0.5).clamp(max=h - 1).long()
    area = _edge(x[:, 0], y[:, 0], x[:, 1], y[:, 1], x[:, 2], y[:, 2])
    valid = (z.min(1).values > near) & (x1 >= x0) & (y1 >= y0) & (area.abs() > 1e-9)
    face_ids = torch.nonzero(valid).squeeze(1)
    bw = (x1 - x0 + 1)[face_ids]
    counts = bw * (y1 - y0 + 1)[face_ids]
    # One int64 key per candidate: the float32 depth bits (monotonic for positive floats) then the face id,
    # so a single scatter-amin picks the nearest face, ties broken by the lower id, across chunks.
    best_key = torch.full((h * w,), _NO_FACE, dtype=torch.long, device=screen.device)
    ends = torch.cumsum(counts, 0)
    start_face = 0
    while start_face < len(face_ids):
        base = ends[start_face - 1] if start_face > 0 else 0
        stop = max(int(torch.searchsorted(ends, base + _PIXELS_PER_CHUNK, right=True)), start_face + 1)
        sel = slice(start_face, stop)
        cnt = counts[sel]
        local_face = torch.repeat_interleave(torch.arange(stop - start_face, device=screen.device), cnt)
        offsets = torch.arange(int(cnt.sum()), device=screen.device) - torch.repeat_interleave(
            torch.cumsum(cnt, 0) - cnt, cnt)
        f = face_ids[sel][local_face]
        bwf = bw[sel][local_face]
        px = x0[f] + offsets % bwf
        py = y0[f] + torch.div(offsets, bwf, rounding_mode="floor")
        cx, cy = px.float() + 0.5, py.float() + 0.5
        xf, yf, zf = x[f], y[f], z[f]
        a = area[f]
        w0 = _edge(xf[:, 1], yf[:, 1], xf[:, 2], yf[:, 2], cx, cy) / a
        w1 = _edge(xf[:, 2], yf[:, 2], xf[:, 0], yf[:, 0], cx, cy) / a
        w2 = 1.0 - w0 - w1
        depth = 1.0 / (w0 / zf[:, 0] + w1 / zf[:, 1] + w2 / zf[:, 2])
        keep = (w0 >= 0) & (w1 >= 0) & (w2 >= 0) & (depth > near)
        key = (depth[keep].float().view(torch.int32).long() << _FACE_BITS) | f[keep]
        best_key.scatter_reduce_(0, (py * w + px)[keep], key, reduce="amin")
        start_face = stop
    return torch.where(best_key == _NO_FACE, -1, best_key & ((1 << _FACE_BITS) - 1))


def rasterize(screen: torch.Tensor, faces: torch.Tensor, image_size: tuple[int, int], near: float = 1e-3,
              perspective_correct: bool = True) -> Fragments:
    """screen (B, V, 3): pixel u, pixel v (pixel centres at i + 0.5), camera depth z. faces (F, 3) long."""
    batch = screen.shape[0]
    h, w = image_size
    pix_faces = []
    for b in range(batch):
        pix_faces.append(_visible_faces(screen[b].detach(), faces, image_size, near))
    pix_to_face = torch.stack(pix_faces)  # (B, H*W)
    b_idx, pix = torch.nonzero(pix_to_face >= 0, as_tuple=True)
    face_idx = pix_to_face[b_idx, pix]
    py, px = torch.div(pix, w, rounding_mode="floor"), pix % w
    tri = gather_corners(screen, faces, b_idx, face_idx)  # (P, 3, 3) with autograd
    cx, cy = px.to(screen.dtype) + 0.5, py.to(screen.dtype) + 0.5
    xs, ys, zs = tri[..., 0], tri[..., 1], tri[..., 2]
    area = _edge(xs[:, 0], ys[:, 0], xs[:, 1], ys[:, 1], xs[:, 2], ys[:, 2])
    l0 = _edge(xs[:, 1], ys[:, 1], xs[:, 2], ys[:, 2], cx, cy) / area
    l1 = _edge(xs[:, 2], ys[:, 2], xs[:, 0], ys[:, 0], cx, cy) / area
    lam = torch.stack([l0, l1, 1.0 - l0 - l1], -1)
    if perspective_correct:
        weighted = lam / zs
        depth = 1.0 / weighted.sum(-1)
        bary = weighted * depth[:, None]
    else:
        bary = lam
        depth = (lam * zs).sum(-1)
    return Fragments(batch_idx=b_idx, pixel_y=py, pixel_x=px, face_idx=face_idx, bary=bary, depth=depth,
                     image_size=(h, w), batch=batch)
