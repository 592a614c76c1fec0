"""Strategy α2's mouth for a head model whose mesh leaves the mouth open (FLAME 2020; seed 002, 3.4, fig. 28).

FLAME's mesh and texture have no mouth interior: with the jaw open, the background shows through the lips. For α2
the dissertation adds, "without adding new vertices to the original mesh, new faces in the mouth area" (in Blender,
by hand), and makes "a rough modification of the original texture unwrap" so that those faces render as a mouth
interior. `close_mouth` does the same programmatically: it finds the boundary loop of the mesh at the inner lips,
zips its upper and lower halves together with new faces between existing vertices (so the new faces open with the
jaw, as the lips do), and, for a UV texture, gives those faces a free patch of the unwrap painted in a dark mouth
colour (mean albedo; no PCA variation there). The procedural default head builds its own mouth interior
instead (`ProceduralSpec.mouth_interior`), so this is used for FLAME 2020 given by path.
"""
from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
from scipy import ndimage
from skimage.draw import polygon as fill_polygon

from avatarlab.headmodel.regions import template_landmarks
from avatarlab.headmodel.sources import HeadModelData, HeadModelFileError, UVAlbedo

log = logging.getLogger(__name__)

#: the colour the mouth's new faces are painted in the UV texture (RGB in [0, 1]): the dark red of a mouth interior
MOUTH_COLOUR = (0.32, 0.10, 0.10)
INNER_LIPS = slice(60, 68)  # the 68-point scheme's inner-lip landmarks


def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """The mesh's boundary loops (edges used by one face only), each an ordered array of vertex indices."""
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = np.sort(directed, 1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    edges = directed[counts[inverse.reshape(-1)] == 1]
    nxt = {}
    for a, b in edges:
        if int(b) in nxt:
            raise HeadModelFileError(f"the mesh's boundary is not a set of simple loops (vertex {int(b)})")
        nxt[int(b)] = int(a)  # walked against the faces' own edge direction
    loops, seen = [], set()
    for start in nxt:
        if start in seen:
            continue
        loop, v = [], start
        while v not in seen:
            seen.add(v)
            loop.append(v)
            v = nxt[v]
        loops.append(np.array(loop))
    return loops


def mouth_loop(data: HeadModelData) -> np.ndarray:
    """The boundary loop nearest the inner-lip landmarks, ordered. Raises if the mesh has no boundary there."""
    loops = boundary_loops(data.faces)
    if not loops:
        raise HeadModelFileError(f"{data.source}: the mesh has no boundary loop, so no open mouth to close")
    inner = template_landmarks(data.v_template, data.faces, data.lmk_faces_idx, data.lmk_bary_coords)[INNER_LIPS]
    centre, size = inner.mean(0), np.linalg.norm(np.ptp(inner, 0))
    dist = [np.linalg.norm(data.v_template[loop].mean(0) - centre) for loop in loops]
    best = int(np.argmin(dist))
    width = np.ptp(data.v_template[loops[best], 0])
    if dist[best] > max(size, width):
        raise HeadModelFileError(f"{data.source}: no boundary loop near the inner lips (nearest "
                                 f"{dist[best] * 1000:.1f} mm from them)")
    return loops[best]


def split_loop(loop: np.ndarray, verts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The loop's upper and lower halves, each from its leftmost to its rightmost vertex (the mouth corners)."""
    x = verts[loop, 0]
    i0, i1 = int(np.argmin(x)), int(np.argmax(x))
    rolled = np.roll(loop, -i0)
    k = (i1 - i0) % len(loop)
    first, second = rolled[:k + 1], np.concatenate([rolled[k:], rolled[:1]])[::-1]
    return (first, second) if verts[first, 1].mean() >= verts[second, 1].mean() else (second, first)


def zip_faces(upper: np.ndarray, lower: np.ndarray, verts: np.ndarray) -> np.ndarray:
    """Faces between the upper and lower halves of the mouth's loop, made by advancing along whichever half is
    behind in arc length: a strip with no new vertex, oriented to the front (+z), where the mouth opens."""
    def fraction(chain):
        step = np.linalg.norm(np.diff(verts[chain], axis=0), axis=1)
        s = np.concatenate([[0.0], np.cumsum(step)])
        return s / max(s[-1], 1e-12)

    fu, fl = fraction(upper), fraction(lower)
    faces, i, j = [], 0, 0
    while i < len(upper) - 1 or j < len(lower) - 1:
        if j == len(lower) - 1 or (i < len(upper) - 1 and fu[i + 1] <= fl[j + 1]):
            tri = (upper[i], lower[j], upper[i + 1])
            i += 1
        else:
            tri = (upper[i], lower[j], lower[j + 1])
            j += 1
        if len(set(tri)) == 3:
            faces.append(tri)
    faces = np.array(faces, dtype=np.int64)
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    back = np.cross(b - a, c - a)[:, 2] < 0
    faces[back] = faces[back][:, [0, 2, 1]]
    return faces


def uv_coverage(uv: np.ndarray, uv_faces: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Texels (H, W) inside any of the UV triangles, in the renderer's sampling convention (grid_sample,
    align_corners=False, v up)."""
    h, w = shape
    mask = np.zeros((h, w), bool)
    for tri in uv[uv_faces]:
        rr, cc = fill_polygon((1 - tri[:, 1]) * h - 0.5, tri[:, 0] * w - 0.5, shape=(h, w))
        mask[rr, cc] = True
    return mask


def mouth_patch(albedo: UVAlbedo) -> tuple[UVAlbedo, tuple[int, int, int]]:
    """A square of texels no existing face samples, for the mouth's new faces: (row, col, half size). Where the
    unwrap has no free square of at least 5 texels, the texture is widened by a free block on the right (the
    existing coordinates rescaled so that every face samples the texels it did)."""
    h, w = albedo.mean.shape[:2]
    free = ~uv_coverage(albedo.uv, albedo.uv_faces, (h, w))
    free[[0, -1], :] = free[:, [0, -1]] = False  # keep clear of the border, where sampling clamps
    room = ndimage.distance_transform_cdt(free, metric="chessboard")
    if room.max() < 3:
        extra = max(8, w // 8)
        pad = ((0, 0), (0, extra)) + ((0, 0),) * (albedo.mean.ndim - 2)
        uv = albedo.uv.copy()
        uv[:, 0] *= w / (w + extra)
        albedo = UVAlbedo(mean=np.pad(albedo.mean, pad, mode="edge"),
                          basis=np.pad(albedo.basis, pad + ((0, 0),), mode="constant"), uv=uv,
                          uv_faces=albedo.uv_faces)
        return mouth_patch(albedo)
    r, c = np.unravel_index(int(np.argmax(room)), room.shape)
    return albedo, (int(r), int(c), int(room[r, c]) - 1)


def paint_mouth_uv(albedo: UVAlbedo, upper: np.ndarray, lower: np.ndarray, new_faces: np.ndarray, verts: np.ndarray,
                   colour=MOUTH_COLOUR) -> tuple[UVAlbedo, int]:
    """The texture edit: the loop's vertices get texture coordinates in a free patch of the unwrap (laid out as
    the mouth is: left to right, upper lip above the lower), the new faces use them, and the patch is painted
    `colour` in the mean and zero in the PCA basis. -> the edited albedo and the number of texels painted."""
    albedo, (r, c, half) = mouth_patch(albedo)
    h, w = albedo.mean.shape[:2]
    loop = np.unique(np.concatenate([upper, lower]))
    x = verts[loop, 0]
    t = (x - x.min()) / max(np.ptp(x), 1e-12)
    side = np.where(np.isin(loop, upper[1:-1]), 1.0, np.where(np.isin(loop, lower[1:-1]), -1.0, 0.0))
    cols, rows = c - 0.5 * half + t * half, r - 0.5 * side * half  # inside the square, a margin on every side
    new_vt = np.stack([(cols + 0.5) / w, 1 - (rows + 0.5) / h], 1).astype(albedo.uv.dtype)
    index = {int(v): len(albedo.uv) + i for i, v in enumerate(loop)}
    new_uv_faces = np.vectorize(index.__getitem__)(new_faces).astype(np.int64)
    mean, basis = albedo.mean.copy(), albedo.basis.copy()
    square = (slice(r - half, r + half + 1), slice(c - half, c + half + 1))
    mean[square] = np.asarray(colour, mean.dtype)
    basis[square] = 0
    painted = (2 * half + 1) ** 2
    return UVAlbedo(mean=mean, basis=basis, uv=np.concatenate([albedo.uv, new_vt]),
                    uv_faces=np.concatenate([albedo.uv_faces, new_uv_faces])), painted


def close_mouth(data: HeadModelData) -> HeadModelData:
    """α2's head model: `data` with new faces closing the mouth opening and, for a UV texture, the unwrap painted
    for them. Vertices, blend shapes, skinning and the landmark embedding are unchanged."""
    loop = mouth_loop(data)
    upper, lower = split_loop(loop, data.v_template)
    new_faces = zip_faces(upper, lower, data.v_template)
    albedo, painted = data.albedo, None
    if isinstance(albedo, UVAlbedo):
        albedo, painted = paint_mouth_uv(albedo, upper, lower, new_faces, data.v_template)
    log.info("head model: mouth closed for alpha2 with %d new faces on its %d-vertex inner-lip loop (no new "
             "vertices)%s", len(new_faces), len(loop),
             f", {painted} texels of the unwrap painted as mouth interior" if painted is not None else
             "; a per-vertex albedo, so the new faces take the lips' colours")
    return replace(data, faces=np.concatenate([data.faces, new_faces]), albedo=albedo, source=data.source + ":mouth")
