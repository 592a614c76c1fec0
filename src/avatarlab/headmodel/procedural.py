"""The embedded default head: a deterministic, openly generated FLAME-structured head model.

Geometry is a lofted surface (rows = heights, columns = azimuths) of head + neck with facial relief carved by
displacements along +z, so every facial point keeps its frontal (X, Y) coordinates. That makes the 68-landmark
embedding exact: a landmark given in (X, Y) maps to one grid quad and its barycentric coordinates.
Eyeballs are separate spheres behind an eyelid opening (moved by the eye joints), the mouth is a real slit
between two rows (opened by the jaw joint); an optional mouth-interior mesh (strategy alpha2) sits behind the lips.
Shape, expression and albedo bases are designed deformation fields plus seeded smooth random fields,
orthonormalised and scaled with decreasing standard deviation, like PCA components.
"""
from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from matplotlib.path import Path as PolygonPath
from scipy.interpolate import PchipInterpolator
from scipy.spatial import cKDTree

from avatarlab.headmodel.sources import HeadModelData, VertexAlbedo
from avatarlab.runtime.io import atomic_path

log = logging.getLogger(__name__)

GENERATOR_VERSION = 9  # bump when the geometry or bases change: invalidates caches


@dataclass(frozen=True)
class ProceduralSpec:
    n_shape: int = 100
    n_expression: int = 50
    n_texture: int = 50
    mouth_interior: bool = False
    seed: int = 0
    columns: int = 96
    face_row_step: float = 0.0028  # metres between rows over the face

    def digest(self) -> str:
        payload = json.dumps({**asdict(self), "version": GENERATOR_VERSION}, sort_keys=True)
        return hashlib.sha256(payload.encode()).hexdigest()[:12]


# ---------------------------------------------------------------- profiles (metres; y up, face towards +z)
Y_TOP, Y_CAP, Y_CHIN, Y_BOTTOM = 0.140, 0.085, -0.095, -0.200
MOUTH_Y, MOUTH_HALF_WIDTH, SLIT_HALF_GAP = -0.0365, 0.024, 0.00025
EYE_X, EYE_Y, EYE_RADIUS = 0.031, 0.030, 0.0118
EYE_OPEN_HALF = (0.0115, 0.0052)
SUPERELLIPSE = 2.5
_PROFILE_Y = [0.085, 0.06, 0.045, 0.03, 0.01, -0.01, -0.03, -0.05, -0.07, -0.085, -0.095, -0.105, -0.12, -0.2]
_FRONT = [0.080, 0.088, 0.092, 0.088, 0.088, 0.088, 0.088, 0.086, 0.080, 0.066, 0.045, 0.038, 0.040, 0.042]
_BACK = [0.100, 0.104, 0.105, 0.104, 0.100, 0.094, 0.086, 0.076, 0.064, 0.058, 0.056, 0.056, 0.058, 0.060]
_WIDTH = [0.072, 0.077, 0.078, 0.078, 0.076, 0.073, 0.068, 0.062, 0.055, 0.052, 0.050, 0.050, 0.052, 0.056]


def _profile(values):
    spline = PchipInterpolator(np.array(_PROFILE_Y[::-1]), np.array(values[::-1]))

    def at(y):
        y = np.asarray(y, dtype=np.float64)
        dome = np.sqrt(np.clip(1 - ((y - Y_CAP) / (Y_TOP - Y_CAP)) ** 2, 0, 1))
        return np.where(y > Y_CAP, values[0] * dome, spline(np.clip(y, Y_BOTTOM, Y_CAP)))

    return at


front_depth, back_depth, half_width = _profile(_FRONT), _profile(_BACK), _profile(_WIDTH)


def _gauss(x, y, cx, cy, sx, sy):
    return np.exp(-((x - cx) ** 2) / (2 * sx**2) - ((y - cy) ** 2) / (2 * sy**2))


def _smoothstep(edge0, edge1, x):
    t = np.clip((np.asarray(x, dtype=np.float64) - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def _soft_sign(x, width=0.008):
    """A smooth sign(x): odd fields must vanish continuously at the midline or the mesh folds there."""
    return np.tanh(np.asarray(x) / width)


def _signed_pow(v, p):
    return np.sign(v) * np.abs(v) ** p


def _row_heights(step: float) -> np.ndarray:
    cap = Y_TOP - (Y_TOP - Y_CAP) * (np.arange(1, 11) / 10.0) ** 2
    n_face = int(round((Y_CAP - Y_CHIN) / step))
    face = np.linspace(Y_CAP, Y_CHIN, n_face + 1)[1:]
    face = face[np.abs(face - MOUTH_Y) > 1.5 * SLIT_HALF_GAP + step / 2]
    face = np.sort(np.concatenate([face, [MOUTH_Y + SLIT_HALF_GAP, MOUTH_Y - SLIT_HALF_GAP]]))[::-1]
    neck = np.linspace(Y_CHIN, Y_BOTTOM, 11)[1:]
    return np.concatenate([cap, face, neck])


def _azimuths(n: int, gamma: float = 1.4) -> np.ndarray:
    u = -1.0 + 2.0 * np.arange(n) / n
    return np.pi * _signed_pow(u, gamma)


def _cross_section(y, azimuth):
    s, c = np.sin(azimuth), np.cos(azimuth)
    x = half_width(y) * _signed_pow(s, 2 / SUPERELLIPSE)
    depth = np.where(c >= 0, front_depth(y), back_depth(y))
    z = depth * _signed_pow(c, 2 / SUPERELLIPSE)
    return x, z


def _nose_height(y):
    ys = [0.045, 0.035, 0.02, 0.005, -0.003, -0.009, -0.014, -0.018]
    hs = [0.0, 0.004, 0.009, 0.016, 0.022, 0.017, 0.006, 0.0]
    spline = PchipInterpolator(ys[::-1], hs[::-1])
    return np.where((y < ys[0]) & (y > ys[-1]), spline(np.clip(y, ys[-1], ys[0])), 0.0)


def facial_relief(x, y):
    """Displacement along +z (metres) that carves the face into the base loft, before the eye override."""
    dz = 0.004 * (_gauss(x, y, EYE_X, 0.047, 0.016, 0.006) + _gauss(x, y, -EYE_X, 0.047, 0.016, 0.006))
    dz -= 0.011 * (_gauss(x, y, EYE_X, EYE_Y, 0.017, 0.012) + _gauss(x, y, -EYE_X, EYE_Y, 0.017, 0.012))
    width = 0.005 + 0.004 * _smoothstep(0.04, -0.003, y)
    dz += _nose_height(y) * np.exp(-(x**2) / (2 * width**2))
    dz += 0.008 * (_gauss(x, y, 0.0125, -0.009, 0.005, 0.005) + _gauss(x, y, -0.0125, -0.009, 0.005, 0.005))
    dz += 0.006 * (_gauss(x, y, 0.042, 0.0, 0.014, 0.015) + _gauss(x, y, -0.042, 0.0, 0.014, 0.015))
    dz += 0.005 * _gauss(x, y, 0.0, -0.0305, 0.018, 0.0045)
    dz += 0.0055 * _gauss(x, y, 0.0, -0.0435, 0.016, 0.005)
    dz -= 0.003 * _gauss(x, y, 0.0, -0.053, 0.014, 0.004)
    dz += 0.007 * _gauss(x, y, 0.0, -0.072, 0.015, 0.010)
    return dz


def eye_opening(x, y, side: float):
    """Soft indicator (0..1) of the eyelid opening of the eye at x = side * EYE_X."""
    rho = np.sqrt(((x - side * EYE_X) / EYE_OPEN_HALF[0]) ** 2 + ((y - EYE_Y) / EYE_OPEN_HALF[1]) ** 2)
    return 1.0 / (1.0 + np.exp(-(1.0 - rho) / 0.08))


# ---------------------------------------------------------------- 68 landmarks in frontal (X, Y), dlib order
# Image-left (subject's right, -X) first, as in the iBUG 300-W / dlib convention. The table was designed from the
# feature positions above, then calibrated once to the median response of dlib's 68-point predictor on frontal
# renders of random heads (seed 1, 60 renders), symmetrised, and frozen; the check in avatarlab.pretrain.dlib_check
# measures it on other renders. Mouth points stay on their side of the slit (the embedding needs a triangle there).
_LANDMARK_XY = np.array([
    [-0.0741, 0.0340], [-0.0727, 0.0143], [-0.0702, -0.0052], [-0.0662, -0.0240],
    [-0.0613, -0.0418], [-0.0522, -0.0581], [-0.0381, -0.0724], [-0.0207, -0.0832],
    [0.0000, -0.0863], [0.0207, -0.0832], [0.0381, -0.0724], [0.0522, -0.0581],
    [0.0613, -0.0418], [0.0662, -0.0240], [0.0702, -0.0052], [0.0727, 0.0143],
    [0.0741, 0.0340], [-0.0566, 0.0442], [-0.0468, 0.0532], [-0.0338, 0.0574],
    [-0.0203, 0.0564], [-0.0082, 0.0504], [0.0082, 0.0504], [0.0203, 0.0564],
    [0.0338, 0.0574], [0.0468, 0.0532], [0.0566, 0.0442], [0.0000, 0.0325],
    [0.0000, 0.0211], [0.0000, 0.0097], [0.0000, -0.0014], [-0.0099, -0.0138],
    [-0.0051, -0.0151], [0.0000, -0.0162], [0.0051, -0.0151], [0.0099, -0.0138],
    [-0.0430, 0.0308], [-0.0355, 0.0366], [-0.0251, 0.0361], [-0.0176, 0.0285],
    [-0.0263, 0.0251], [-0.0364, 0.0254], [0.0176, 0.0285], [0.0251, 0.0361],
    [0.0355, 0.0366], [0.0430, 0.0308], [0.0364, 0.0254], [0.0263, 0.0251],
    [-0.0227, -0.0357], [-0.0154, -0.0295], [-0.0064, -0.0251], [0.0000, -0.0265],
    [0.0064, -0.0251], [0.0154, -0.0295], [0.0227, -0.0357], [0.0157, -0.0452],
    [0.0073, -0.0483], [0.0000, -0.0491], [-0.0073, -0.0483], [-0.0157, -0.0452],
    [-0.0184, -0.0357], [-0.0064, -0.0352], [0.0000, -0.0355], [0.0064, -0.0352],
    [0.0184, -0.0357], [0.0065, -0.0373], [0.0000, -0.0381], [-0.0065, -0.0373],
])


def landmark_xy() -> np.ndarray:
    return _LANDMARK_XY.astype(np.float64).copy()


# ---------------------------------------------------------------- mesh construction
def grid_faces(rows: int, cols: int, offset: int, top: int | None, bottom: int | None, skip=None) -> np.ndarray:
    """Triangles of a closed-in-azimuth grid (rows x cols vertices from `offset`) with optional pole fans."""
    idx = offset + np.arange(rows * cols).reshape(rows, cols)
    right = np.roll(idx, -1, axis=1)
    a, b, c, d = idx[:-1], idx[1:], right[1:], right[:-1]
    keep = np.ones(a.shape, bool) if skip is None else ~skip
    tris = [np.stack([a[keep], b[keep], c[keep]], -1), np.stack([a[keep], c[keep], d[keep]], -1)]
    if top is not None:
        tris.append(np.stack([np.full(cols, top), idx[0], right[0]], -1))
    if bottom is not None:
        tris.append(np.stack([np.full(cols, bottom), right[-1], idx[-1]], -1))
    return np.concatenate(tris)


def orient_outward(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Flip a closed component's triangles if its signed volume is negative (normals must point out)."""
    v0, v1, v2 = (vertices[faces[:, k]] for k in range(3))
    volume = np.einsum("ij,ij->i", v0, np.cross(v1, v2)).sum() / 6.0
    return faces if volume > 0 else faces[:, [0, 2, 1]]


def sphere_grid(center, radius, n_lat=12, n_lon=20, power=1.5, radii=None):
    """Lat-long sphere with its pole on +z, rings denser near the front pole. Returns (front, rings, back)."""
    radii = np.asarray(radii if radii is not None else (radius, radius, radius))
    theta = np.pi * (np.arange(1, n_lat) / n_lat) ** power
    phi = 2 * np.pi * np.arange(n_lon) / n_lon
    t, p = np.meshgrid(theta, phi, indexing="ij")
    ring = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1) * radii + center
    return center + radii * [0, 0, 1], ring, center - radii * [0, 0, 1], theta


def _triangle_bary(p, a, b, c):
    v0, v1, v2 = b - a, c - a, p - a
    d00, d01, d11 = v0 @ v0, v0 @ v1, v1 @ v1
    d20, d21 = v2 @ v0, v2 @ v1
    den = d00 * d11 - d01 * d01
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    return np.array([1 - v - w, v, w])


class _Builder:
    """Accumulates vertex groups and faces; keeps per-vertex frontal coordinates and region masks."""

    def __init__(self, spec: ProceduralSpec):
        self.spec = spec
        self.rng = np.random.default_rng(spec.seed)
        self.heights = _row_heights(spec.face_row_step)
        self.azimuths = _azimuths(spec.columns)

    def head(self):
        rows, cols = len(self.heights), len(self.azimuths)
        y = np.repeat(self.heights[:, None], cols, 1)
        az = np.repeat(self.azimuths[None, :], rows, 0)
        x, z = _cross_section(y, az)
        front = _smoothstep(0.25, 0.65, np.cos(az))
        z_face = z + front * facial_relief(x, y)
        self.eye_z = {}
        openings = np.zeros_like(z)
        for side in (1.0, -1.0):
            ex = side * EYE_X
            socket = z_face[np.argmin(np.abs(self.heights - EYE_Y)), np.argmin(np.abs(self.azimuths - np.arcsin(
                (abs(ex) / half_width(EYE_Y)) ** (SUPERELLIPSE / 2)) * side))]
            ze = socket - EYE_RADIUS + 0.0045
            self.eye_z[side] = ze
            d2 = (x - ex) ** 2 + (y - EYE_Y) ** 2
            lid = np.where(d2 < (EYE_RADIUS + 0.0015) ** 2, ze + np.sqrt(np.clip((EYE_RADIUS + 0.0015) ** 2 - d2, 0, None)),
                           -np.inf)
            covered = np.where(front > 0.5, np.maximum(z_face, lid), z_face)
            hidden = ze + np.sqrt(np.clip(EYE_RADIUS**2 - d2, 0, None)) - 0.004
            o = eye_opening(x, y, side) * (front > 0.5)
            self.blink_dz = getattr(self, "blink_dz", np.zeros_like(z)) + o * (covered - hidden)
            z_face = (1 - o) * covered + o * hidden
            openings = np.maximum(openings, o)
        self.grid_shape = (rows, cols)
        self.grid_x, self.grid_y, self.grid_az = x, y, az
        verts = np.concatenate([[[0.0, Y_TOP, 0.0]], np.stack([x, y, z_face], -1).reshape(-1, 3),
                                [[0.0, Y_BOTTOM, 0.0]]])
        slit_row = int(np.argmin(np.abs(self.heights - (MOUTH_Y + SLIT_HALF_GAP))))
        skip = np.zeros((rows - 1, cols), bool)
        xr = x[slit_row]
        skip[slit_row] = (np.abs(xr) < MOUTH_HALF_WIDTH) & (np.abs(np.roll(xr, -1)) < MOUTH_HALF_WIDTH) & (
            np.cos(self.azimuths) > 0)
        faces = grid_faces(rows, cols, 1, 0, rows * cols + 1, skip)
        self.quad_faces = self._quad_face_index(rows, cols, skip)
        self.slit_row = slit_row
        self.openings = np.concatenate([[0.0], openings.reshape(-1), [0.0]])
        return verts, orient_outward(verts, faces)

    @staticmethod
    def _quad_face_index(rows, cols, skip):
        """(rows-1, cols, 2) face indices of the two triangles of each quad (-1 where skipped)."""
        keep = ~skip
        n = keep.sum()
        table = -np.ones((rows - 1, cols, 2), np.int64)
        table[keep, 0] = np.arange(n)
        table[keep, 1] = n + np.arange(n)
        return table

    def eyeball(self, side: float, offset: int):
        center = np.array([side * EYE_X, EYE_Y, self.eye_z[side]])
        front, ring, back, theta = sphere_grid(center, EYE_RADIUS)
        verts = np.concatenate([[front], ring.reshape(-1, 3), [back]])
        n_lat, n_lon = ring.shape[:2]
        faces = grid_faces(n_lat, n_lon, offset + 1, offset, offset + 1 + n_lat * n_lon)
        angle = np.concatenate([[0.0], np.repeat(theta, n_lon), [np.pi]])
        return verts, orient_outward(verts - 0, faces - offset) + offset, angle, center

    def mouth_bag(self, offset: int):
        center = np.array([0.0, MOUTH_Y - 0.003, front_depth(MOUTH_Y) + 0.006 - 0.008 - 0.016])
        front, ring, back, _ = sphere_grid(center, None, n_lat=10, n_lon=16, power=1.2, radii=(0.021, 0.013, 0.016))
        verts = np.concatenate([[front], ring.reshape(-1, 3), [back]])
        n_lat, n_lon = ring.shape[:2]
        faces = grid_faces(n_lat, n_lon, offset + 1, offset, offset + 1 + n_lat * n_lon)
        return verts, orient_outward(verts, faces - offset) + offset, center

    def landmark_embedding(self, verts, faces):
        rows, cols = self.grid_shape
        heights = self.heights
        front_cols = np.where(np.cos(self.azimuths) > 0)[0]
        idx, bary = [], []
        for X, Y in landmark_xy():
            i = int(np.searchsorted(-heights, -Y) - 1)
            fr = (heights[i] - Y) / (heights[i] - heights[i + 1])
            q0 = np.interp(X, self.grid_x[i, front_cols], front_cols)
            q1 = np.interp(X, self.grid_x[i + 1, front_cols], front_cols)
            q = (1 - fr) * q0 + fr * q1
            j = int(np.floor(q))
            u = q - j
            pick = 0 if fr >= u else 1
            f = self.quad_faces[i, j, pick]
            if f < 0:
                raise RuntimeError(f"landmark at ({X:.4f}, {Y:.4f}) falls into the mouth slit")
            corner = lambda r, c: verts[1 + r * cols + (c % cols)]  # noqa: E731
            a, b, c, d = corner(i, j), corner(i + 1, j), corner(i + 1, j + 1), corner(i, j + 1)
            p = (1 - fr) * a + (fr - u) * b + u * c if pick == 0 else (1 - u) * a + fr * c + (u - fr) * d
            idx.append(f)
            bary.append(_triangle_bary(p, *verts[faces[f]]))
        return np.array(idx), np.array(bary, dtype=np.float32)


def _normalise_fields(fields: list[np.ndarray], amplitudes: np.ndarray) -> np.ndarray:
    """Orthonormalise displacement fields (each (V,3)) into (V, 3, K) components ordered by decreasing std.

    Field k gets the standard deviation that makes its largest vertex displacement `amplitudes[k]` at coefficient 1;
    components are then sorted by standard deviation, as a PCA orders them.
    """
    mat = np.stack([f.reshape(-1) for f in fields], 1)
    q, r = np.linalg.qr(mat)
    q = q * np.sign(np.diag(r))[None, :]
    sigma = amplitudes[: q.shape[1]] / np.abs(q).max(0)
    order = np.argsort(-sigma, kind="stable")
    sigma = sigma[order] * (1 - 1e-6 * np.arange(len(order)))  # strictly decreasing even for equal amplitudes
    return (q[:, order] * sigma[None, :]).reshape(-1, 3, q.shape[1]).astype(np.float32)


def _smooth_random_fields(rng, points, centers_from, count, n_rbf, width, weight):
    fields = []
    for _ in range(count):
        field = np.zeros_like(points)
        for c in centers_from[rng.integers(0, len(centers_from), n_rbf)]:
            falloff = np.exp(-np.sum((points - c) ** 2, 1) / (2 * width**2))
            field += falloff[:, None] * rng.normal(size=3)
        fields.append(field * weight[:, None])
    return fields


def build_procedural_head(spec: ProceduralSpec = ProceduralSpec()) -> HeadModelData:
    b = _Builder(spec)
    head_v, head_f = b.head()
    n_head = len(head_v)
    eye_parts = {}
    groups_v, groups_f = [head_v], [head_f]
    offset = n_head
    for side, name in ((1.0, "eyeball_left"), (-1.0, "eyeball_right")):
        v, f, angle, center = b.eyeball(side, offset)
        eye_parts[name] = (offset, len(v), angle, center)
        groups_v.append(v)
        groups_f.append(f)
        offset += len(v)
    bag = None
    if spec.mouth_interior:
        v, f, center = b.mouth_bag(offset)
        bag = (offset, len(v), center)
        groups_v.append(v)
        groups_f.append(f)
        offset += len(v)
    verts = np.concatenate(groups_v)
    faces = np.concatenate(groups_f)
    n = len(verts)

    regions = {name: np.zeros(n, bool) for name in ("head", "face", "lips", "neck", "lower_face", "eyeball_left",
                                                     "eyeball_right", "mouth_interior")}
    regions["head"][:n_head] = True
    for name, (start, count, _, _) in eye_parts.items():
        regions[name][start:start + count] = True
    if bag:
        regions["mouth_interior"][bag[0]:bag[0] + bag[1]] = True
    x, y, z = verts.T
    head_cos = np.concatenate([[0.0], np.cos(b.grid_az).reshape(-1), [0.0]])
    front = np.zeros(n)
    front[:n_head] = _smoothstep(0.25, 0.65, head_cos)
    front[n_head:] = 1.0
    in_face = (front > 0.5) & (y < 0.075) & (y > -0.1)
    regions["face"] = in_face & regions["head"]
    outer_lip = PolygonPath(landmark_xy()[48:60])
    regions["lips"] = regions["face"] & outer_lip.contains_points(np.stack([x, y], 1), radius=-1e-3)
    regions["neck"] = regions["head"] & (y < -0.095)
    head_cos_full = np.concatenate([head_cos, np.zeros(n - n_head)])
    regions["lower_face"] = regions["head"] & (y < MOUTH_Y) & (head_cos_full > 0.05) & (y > -0.12)

    # --- skinning: root 0, neck 1, jaw 2, eye_left 3, eye_right 4
    weights = np.zeros((n, 5))
    head_side = _smoothstep(-0.13, -0.07, y)
    below_slit = y < MOUTH_Y
    cheek = np.abs(x) >= MOUTH_HALF_WIDTH + 0.004
    vertical = np.where(below_slit, 1.0, np.where(cheek, _smoothstep(MOUTH_Y + 0.012, MOUTH_Y, y), 0.0))
    lateral = _smoothstep(0.1, 0.45, head_cos_full)
    under = _smoothstep(-0.115, -0.09, y)
    jaw = (lateral * vertical * under)[:n_head]
    weights[:n_head, 0] = 1 - head_side[:n_head]
    weights[:n_head, 1] = head_side[:n_head] * (1 - jaw)
    weights[:n_head, 2] = head_side[:n_head] * jaw
    for j, name in ((3, "eyeball_left"), (4, "eyeball_right")):
        weights[regions[name], j] = 1.0
    if bag:
        s = slice(bag[0], bag[0] + bag[1])
        t = _smoothstep(bag[2][1] + 0.003, bag[2][1] - 0.003, y[s])
        weights[s, 1], weights[s, 2] = 1 - t, t
    rows, cols = b.grid_shape

    def grid_vertex(height, az):
        r = int(np.argmin(np.abs(b.heights - height)))
        c = int(np.argmin(np.abs(np.angle(np.exp(1j * (b.azimuths - az))))))
        return 1 + r * cols + c

    j_reg = np.zeros((5, n))
    for joint, height in ((0, -0.17), (1, -0.04), (2, -0.005)):
        j_reg[joint, [grid_vertex(height, np.pi / 2), grid_vertex(height, -np.pi / 2)]] = 0.5
    for joint, name in ((3, "eyeball_left"), (4, "eyeball_right")):
        j_reg[joint, regions[name]] = 1.0 / regions[name].sum()

    # --- bases
    rng = b.rng
    face_pts = verts[regions["face"]]
    head_w = regions["head"].astype(float)
    shape_fields = [
        verts * [1, 0, 0], verts * [0, 1, 0], verts * [0, 0, 1],
        np.stack([0 * x, -_smoothstep(0.0, -0.06, y), 0 * x], 1),
        np.stack([0 * x, 0 * x, np.exp(-(x**2) / (2 * 0.008**2)) * _nose_height(y) / 0.022], 1) * front[:, None],
        np.stack([_soft_sign(x) * _smoothstep(-0.02, -0.08, y), 0 * x, 0 * x], 1) * head_w[:, None],
        np.stack([_soft_sign(x) * (_gauss(x, y, EYE_X, EYE_Y, 0.015, 0.012) + _gauss(x, y, -EYE_X, EYE_Y, 0.015, 0.012)),
                  0 * x, 0 * x], 1) * front[:, None],
        np.stack([0 * x, 0 * x, _gauss(x, y, 0, -0.072, 0.02, 0.015)], 1) * front[:, None],
        np.stack([_soft_sign(x), 0 * x, 0.5 + 0 * x], 1) * (_gauss(np.abs(x), y, 0.045, 0.005, 0.015, 0.015))[:, None],
        np.stack([0 * x, 0 * x, _smoothstep(0.05, 0.1, y)], 1) * front[:, None],
        np.stack([x, 0 * x, 0 * x], 1) * _gauss(x, y, 0, MOUTH_Y, 0.03, 0.012)[:, None] * front[:, None],
        np.stack([0 * x, 0 * x, 0 * x + 1], 1) * regions["lips"][:, None],
    ]
    shape_fields += _smooth_random_fields(rng, verts, verts[:n_head], max(0, spec.n_shape - len(shape_fields)),
                                          4, 0.03, head_w)
    shape_fields = shape_fields[: spec.n_shape]
    smile = (_gauss(x, y, MOUTH_HALF_WIDTH, MOUTH_Y, 0.012, 0.012) + _gauss(x, y, -MOUTH_HALF_WIDTH, MOUTH_Y, 0.012,
                                                                              0.012)) * front
    brows = (_gauss(x, y, 0.03, 0.05, 0.02, 0.01) + _gauss(x, y, -0.03, 0.05, 0.02, 0.01)) * front
    inner_brows = (_gauss(x, y, 0.012, 0.048, 0.01, 0.008) + _gauss(x, y, -0.012, 0.048, 0.01, 0.008)) * front
    lips_w = _gauss(x, y, 0, MOUTH_Y, 0.022, 0.01) * front
    cheeks = (_gauss(x, y, 0.045, -0.015, 0.015, 0.015) + _gauss(x, y, -0.045, -0.015, 0.015, 0.015)) * front
    blink = np.zeros((n, 3))
    blink[1:1 + rows * cols, 2] = b.blink_dz.reshape(-1)
    upper = (y >= MOUTH_Y).astype(float)
    zero = 0 * x
    expr_fields = [
        np.stack([0.6 * _soft_sign(x), zero + 1, zero - 0.4], 1) * smile[:, None],
        np.stack([zero, zero + 1, zero], 1) * brows[:, None],
        blink,
        np.stack([zero, zero - 1, zero], 1) * smile[:, None],
        np.stack([-_soft_sign(x), zero - 0.6, zero], 1) * inner_brows[:, None],
        np.stack([-x / 0.02, zero, zero + 1], 1) * lips_w[:, None],
        np.stack([_soft_sign(x), zero, zero], 1) * smile[:, None],
        np.stack([zero, 1 - 2 * upper, zero], 1) * lips_w[:, None],
        np.stack([_soft_sign(x), zero, zero + 0.5], 1) * cheeks[:, None],
        np.stack([zero, zero + 1, zero + 0.3], 1) * (lips_w * upper)[:, None],
        np.stack([0.6 * _soft_sign(x), zero + 1, zero - 0.4], 1) * (smile * (x > 0))[:, None],
    ]
    face_w = regions["face"].astype(float)
    expr_fields += _smooth_random_fields(rng, verts, face_pts, max(0, spec.n_expression - len(expr_fields)), 3,
                                         0.015, face_w)
    expr_fields = expr_fields[: spec.n_expression]
    # Rigid parts follow the surface around them: eyeballs translate with their socket, the mouth bag with the lips.
    socket = {name: regions["head"] & ((x - c[0]) ** 2 + (y - c[1]) ** 2 < 0.015**2) & (front > 0.5)
              for name, (_, _, _, c) in eye_parts.items()}
    bag_src = None
    if bag:
        lip_idx = np.where(regions["face"] & (np.abs(y - MOUTH_Y) < 0.015))[0]
        _, nearest = cKDTree(verts[lip_idx]).query(verts[bag[0]:bag[0] + bag[1]])
        bag_src = lip_idx[nearest]

    def attach_rigid(field, keep_blink=False):
        field = field.copy()
        for name in eye_parts:
            field[regions[name]] = field[socket[name]].mean(0) if not keep_blink else 0.0
        if bag:
            field[bag[0]:bag[0] + bag[1]] = field[bag_src]
        return field

    shape_fields = [attach_rigid(f) for f in shape_fields]
    expr_fields = [attach_rigid(f, keep_blink=(k == 2)) for k, f in enumerate(expr_fields)]
    shapedirs = _normalise_fields(shape_fields, 0.005 * 0.97 ** np.arange(len(shape_fields)))
    exprdirs = _normalise_fields(expr_fields, 0.0045 * 0.97 ** np.arange(len(expr_fields)))

    posedirs = np.zeros((n, 3, 36), np.float32)
    neck_w = _gauss(0 * x, y, 0, -0.09, 1, 0.025) * head_w
    for k in range(9):
        posedirs[:, :, k] = (_smooth_random_fields(rng, verts, verts[regions["neck"] | (np.abs(y + 0.08) < 0.01)],
                                                   1, 3, 0.03, neck_w)[0] * 0.004)
    lower_lip = (regions["lips"] & (y < MOUTH_Y)).astype(float)
    posedirs[:, 2, 9 + 7] = 0.004 * lower_lip  # sin(jaw angle): lower lip rolls out
    jaw_cheeks = _soft_sign(x) * cheeks * weights[:, 2]  # only where the jaw carries the skin
    posedirs[:, 0, 9 + 4] = -0.004 * jaw_cheeks  # cos(jaw angle) - 1: cheeks thin as the mouth opens
    posedirs[:, 0, 9 + 8] = -0.004 * jaw_cheeks

    lmk_idx, lmk_bary = b.landmark_embedding(verts, faces)
    albedo = _albedo(spec, rng, verts, regions, front, b.openings, eye_parts, bag, n_head, faces)
    data = HeadModelData(
        v_template=verts.astype(np.float32), faces=faces.astype(np.int64), shapedirs=shapedirs, exprdirs=exprdirs,
        posedirs=posedirs, J_regressor=j_reg.astype(np.float32), parents=np.array([-1, 0, 1, 1, 1]),
        lbs_weights=weights.astype(np.float32), lmk_faces_idx=lmk_idx, lmk_bary_coords=lmk_bary, albedo=albedo,
        source=f"procedural:v{GENERATOR_VERSION}:seed{spec.seed}" + (":mouth" if spec.mouth_interior else ""),
        regions=regions)
    return data


SKIN = np.array([0.80, 0.60, 0.50])


def _albedo(spec, rng, verts, regions, front, openings, eye_parts, bag, n_head, faces) -> VertexAlbedo:
    n = len(verts)
    x, y, z = verts.T
    colour = np.tile(SKIN, (n, 1))
    colour += np.outer(_gauss(np.abs(x), y, 0.045, -0.005, 0.015, 0.015) * front, [0.04, -0.03, -0.03])
    lm = landmark_xy()
    xy = np.stack([x, y], 1)
    lips = regions["lips"]
    colour[lips] = [0.72, 0.36, 0.36]
    slit = regions["head"] & (np.abs(y - MOUTH_Y) < 0.001) & (np.abs(x) < MOUTH_HALF_WIDTH) & (front > 0.5)
    colour[slit] = [0.35, 0.14, 0.14]
    brow = np.zeros(n, bool)
    for start in (17, 22):
        for a, c in zip(lm[start:start + 4], lm[start + 1:start + 5]):
            t = np.clip(((xy - a) @ (c - a)) / ((c - a) @ (c - a)), 0, 1)
            brow |= np.linalg.norm(xy - (a + t[:, None] * (c - a)), axis=1) < 0.0042
    brow &= regions["head"] & (front > 0.5)
    colour[brow] = [0.27, 0.19, 0.14]
    openings = np.concatenate([openings, np.zeros(n - len(openings))])
    lash = regions["head"] & (openings > 0.15) & (openings < 0.9)
    colour[lash] = [0.22, 0.15, 0.12]
    for sx in (-0.0065, 0.0065):
        colour[regions["head"] & ((x - sx) ** 2 + (y + 0.0125) ** 2 < 0.0032**2) & (front > 0.5)] = [0.3, 0.18, 0.15]
    iris_mask = np.zeros(n, bool)
    for name, (start, count, angle, _) in eye_parts.items():
        s = slice(start, start + count)
        colour[s] = np.where(angle[:, None] < 0.12, [0.04, 0.04, 0.04],
                             np.where(angle[:, None] < 0.42, [0.33, 0.21, 0.12], [0.90, 0.88, 0.85]))
        iris_mask[s] = angle < 0.42
    if bag:
        s = slice(bag[0], bag[0] + bag[1])
        yb = y[s] - bag[2][1]
        teeth = (np.abs(yb - 0.003) < 0.0045) & (z[s] > bag[2][2])
        colour[s] = np.where(teeth[:, None], [0.92, 0.90, 0.85], np.where(yb[:, None] < -0.004, [0.70, 0.30, 0.30],
                                                                          [0.45, 0.15, 0.15]))
    skin = regions["head"] & ~lips & ~brow & ~slit
    fields = [
        skin[:, None] * SKIN, skin[:, None] * np.array([1.0, -0.5, -0.5]), skin[:, None] * np.array([0.5, 0.5, -1.0]),
        lips[:, None] * np.array([1.0, 0.3, 0.3]), brow[:, None] * np.array([1.0, 0.8, 0.7]),
        iris_mask[:, None] * np.array([-0.5, 0.2, 1.0]),
        (_gauss(np.abs(x), y, 0.045, -0.005, 0.015, 0.015) * front)[:, None] * np.array([1.0, -0.4, -0.4]),
    ]
    head_w = regions["head"].astype(float)
    tints = np.stack([SKIN, [1.0, -0.5, -0.5], [0.5, 0.5, -1.0]])
    for field in _smooth_random_fields(rng, verts, verts[:n_head], max(0, spec.n_texture - len(fields)), 3, 0.03,
                                       head_w):
        # colour changes stay in skin-like directions: brightness, redness, yellowness
        fields.append(np.linalg.norm(field, axis=1, keepdims=True) * (rng.normal(size=3) @ tints))
    # peak colour change per unit coefficient: brightness, redness, yellowness, lips, brows, iris, blush, then
    # small random skin-tone fields
    designed = np.array([0.07, 0.025, 0.02, 0.05, 0.05, 0.06, 0.03])
    amplitudes = np.concatenate([designed, 0.02 * 0.95 ** np.arange(max(0, spec.n_texture - len(designed)))])
    basis = _normalise_fields(fields[: spec.n_texture], amplitudes)
    return VertexAlbedo(mean=colour.astype(np.float32), basis=basis)


# ---------------------------------------------------------------- cache
def load_procedural_head(spec: ProceduralSpec, cache_dir: str | Path | None = None) -> HeadModelData:
    """Build the procedural head, or read it from `cache_dir` (written atomically) if an identical spec was built."""
    if cache_dir is None:
        return build_procedural_head(spec)
    if "${" in str(cache_dir):  # a head_model group read without the root config: its ${paths.cache} is unresolved
        raise ValueError(f"head model cache_dir {str(cache_dir)!r} holds an unresolved interpolation; compose the "
                         "whole config (avatarlab.runtime.config.compose_config) or pass a real folder")
    path = Path(cache_dir) / f"procedural_{spec.digest()}.npz"
    if path.is_file():
        try:
            return _from_npz(path)
        except (OSError, KeyError, ValueError) as err:
            log.warning("head model cache %s unreadable (%s); rebuilding", path, err)
    data = build_procedural_head(spec)
    arrays = {k: getattr(data, k) for k in ("v_template", "faces", "shapedirs", "exprdirs", "posedirs", "J_regressor",
                                            "parents", "lbs_weights", "lmk_faces_idx", "lmk_bary_coords")}
    arrays.update({"albedo_mean": data.albedo.mean, "albedo_basis": data.albedo.basis,
                   "source": np.array(data.source)})
    arrays.update({f"region_{k}": v for k, v in data.regions.items()})
    with atomic_path(path) as tmp:  # a unique temporary name: parallel steps may build the same head at once
        np.savez_compressed(tmp, **arrays)
    return data


def _from_npz(path: Path) -> HeadModelData:
    with np.load(path) as npz:
        keys = set(npz.files)
        arrays = {k: npz[k] for k in keys if not k.startswith(("albedo_", "region_")) and k != "source"}
        return HeadModelData(**arrays, albedo=VertexAlbedo(npz["albedo_mean"], npz["albedo_basis"]),
                             source=str(npz["source"]),
                             regions={k[len("region_"):]: npz[k] for k in keys if k.startswith("region_")})
