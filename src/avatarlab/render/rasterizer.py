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
def _visible_faces(screen: torch.Tensor, faces: torch.Tensor, image_size: tuple[int, int],
                   near: float) -> torch.Tensor:
    """screen (B, V, 3) [u, v, z] -> pixel_to_face (B, H*W) with -1 where empty.

    Every image of the batch in one pass: the (image, face) pairs are numbered b * F + f, and a pixel's slot in the
    z-buffer is b * H * W + y * W + x. Each candidate (face, pixel) pair reads its face's corners, area and box from
    one packed table row (one gather instead of one per quantity), and rejected candidates get the empty key instead
    of being compacted away, so no boolean indexing is needed."""
    h, w = image_size
    b, v, _ = screen.shape
    n_faces = faces.shape[0]
    corner_ids = faces[None] + v * torch.arange(b, device=screen.device)[:, None, None]  # (B, F, 3) into (B * V)
    tri = screen.reshape(b * v, 3).index_select(0, corner_ids.reshape(-1)).reshape(b * n_faces, 3, 3)
    x, y, z = tri[..., 0], tri[..., 1], tri[..., 2]
    x0 = torch.ceil(x.amin(1) - 0.5).clamp(min=0).long()
    x1 = torch.floor(x.amax(1) - 0.5).clamp(max=w - 1).long()
    y0 = torch.ceil(y.amin(1) - 0.5).clamp(min=0).long()
    y1 = torch.floor(y.amax(1) - 0.5).clamp(max=h - 1).long()
    area = _edge(x[:, 0], y[:, 0], x[:, 1], y[:, 1], x[:, 2], y[:, 2])
    valid = (z.amin(1) > near) & (x1 >= x0) & (y1 >= y0) & (area.abs() > 1e-9)
    ids = torch.nonzero(valid).squeeze(1)  # into the B * F (image, face) pairs
    # per valid face: the corners, the area and its box origin, gathered once per candidate pixel as one table row
    table = torch.cat([x, y, z, area[:, None]], 1).index_select(0, ids)  # (n, 10) float
    origin = torch.stack([x0, y0, x1 - x0 + 1, y1 - y0 + 1], 1).index_select(0, ids)  # (n, 4) long
    bw = origin[:, 2]
    counts = bw * origin[:, 3]
    best_key = torch.full((b * h * w,), _NO_FACE, dtype=torch.long, device=screen.device)
    ends = torch.cumsum(counts, 0)
    start = 0
    while start < len(ids):
        base = ends[start - 1] if start > 0 else 0
        stop = max(int(torch.searchsorted(ends, base + _PIXELS_PER_CHUNK, right=True)), start + 1)
        cnt = counts[start:stop]
        total = int(cnt.sum())
        rows = torch.repeat_interleave(torch.arange(start, stop, device=screen.device), cnt, output_size=total)
        first = (torch.cumsum(cnt, 0) - cnt).repeat_interleave(cnt, output_size=total)
        offsets = torch.arange(total, device=screen.device) - first  # candidate's place in its face's box
        t = table.index_select(0, rows)
        o = origin.index_select(0, rows)
        bwf = o[:, 2]
        px = o[:, 0] + offsets % bwf
        py = o[:, 1] + torch.div(offsets, bwf, rounding_mode="floor")
        cx, cy = px.float() + 0.5, py.float() + 0.5
        xf, yf, zf, a = t[:, 0:3], t[:, 3:6], t[:, 6:9], t[:, 9]
        w0 = _edge(xf[:, 1], yf[:, 1], xf[:, 2], yf[:, 2], cx, cy) / a
        w1 = _edge(xf[:, 2], yf[:, 2], xf[:, 0], yf[:, 0], cx, cy) / a
        w2 = 1.0 - w0 - w1
        depth = 1.0 / (w0 / zf[:, 0] + w1 / zf[:, 1] + w2 / zf[:, 2])
        keep = (w0 >= 0) & (w1 >= 0) & (w2 >= 0) & (depth > near)
        gid = ids.index_select(0, rows)
        key = (depth.float().view(torch.int32).long() << _FACE_BITS) | (gid % n_faces)
        key = torch.where(keep, key, _NO_FACE)
        pix = (gid // n_faces) * (h * w) + py * w + px
        best_key.scatter_reduce_(0, pix, key, reduce="amin")
        start = stop
    out = torch.where(best_key == _NO_FACE, -1, best_key & ((1 << _FACE_BITS) - 1))
    return out.reshape(b, h * w)


def rasterize(screen: torch.Tensor, faces: torch.Tensor, image_size: tuple[int, int], near: float = 1e-3,
              perspective_correct: bool = True) -> Fragments:
    """screen (B, V, 3): pixel u, pixel v (pixel centres at i + 0.5), camera depth z. faces (F, 3) long."""
    batch = screen.shape[0]
    h, w = image_size
    pix_to_face = _visible_faces(screen.detach(), faces, image_size, near)  # (B, H*W)
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
