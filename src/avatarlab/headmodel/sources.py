"""Where a head model comes from: the real FLAME 2020 files (optional, licensed) or the procedural default.

Both give a `HeadModelData`: plain NumPy arrays in FLAME's layout, so everything downstream is source-agnostic.
The real model is read with a restricted unpickler: no chumpy is needed and no code from the pickle runs.
"""
from __future__ import annotations

import io
import logging
import pickle
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse

from avatarlab.headmodel.regions import derived_regions

log = logging.getLogger(__name__)


@dataclass
class VertexAlbedo:
    """Per-vertex albedo PCA: colour = mean + basis @ tau. mean (V,3), basis (V,3,T), values in [0,1]."""

    mean: np.ndarray
    basis: np.ndarray


@dataclass
class UVAlbedo:
    """UV-map albedo PCA (FLAME texture space). mean (H,W,3), basis (H,W,3,T); uv (VT,2) in [0,1]; uv_faces (F,3)."""

    mean: np.ndarray
    basis: np.ndarray
    uv: np.ndarray
    uv_faces: np.ndarray


@dataclass
class HeadModelData:
    v_template: np.ndarray  # (V, 3)
    faces: np.ndarray  # (F, 3)
    shapedirs: np.ndarray  # (V, 3, S)
    exprdirs: np.ndarray  # (V, 3, E)
    posedirs: np.ndarray  # (V, 3, 9 * (J - 1))
    J_regressor: np.ndarray  # (J, V) dense
    parents: np.ndarray  # (J,), -1 for the root
    lbs_weights: np.ndarray  # (V, J)
    lmk_faces_idx: np.ndarray  # (68,)
    lmk_bary_coords: np.ndarray  # (68, 3)
    albedo: VertexAlbedo | UVAlbedo
    source: str = "unknown"
    regions: dict[str, np.ndarray] = field(default_factory=dict)  # name -> vertex mask (V,) bool


class HeadModelFileError(ValueError):
    """A head model file is missing or not in the expected layout (message names the file)."""


class _ChumpyStub:
    """Stands in for chumpy.Ch: keeps the pickled state so the wrapped array can be taken out."""

    def __setstate__(self, state):
        self.state = state

    def to_array(self) -> np.ndarray:
        state = self.state if isinstance(self.state, dict) else {}
        if "x" in state:
            return np.asarray(state["x"])
        raise pickle.UnpicklingError("chumpy object without an 'x' array")


_NUMPY_ALLOWED = {
    ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
    ("numpy", "ndarray"), ("numpy", "dtype"), ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "scalar"),
}
_SPARSE_CLASSES = {"csc_matrix": scipy.sparse.csc_matrix, "csr_matrix": scipy.sparse.csr_matrix}


class RestrictedUnpickler(pickle.Unpickler):
    """Only NumPy arrays, SciPy sparse matrices, chumpy wrappers and plain containers; anything else is refused."""

    def find_class(self, module: str, name: str):
        if (module, name) in _NUMPY_ALLOWED:
            module = module.replace("numpy.core", "numpy._core") if module.startswith("numpy.core") else module
            return super().find_class(module, name)
        if module.startswith("scipy.sparse") and name in _SPARSE_CLASSES:
            return _SPARSE_CLASSES[name]
        if module.startswith("chumpy"):
            return _ChumpyStub
        if (module, name) in {("copy_reg", "_reconstructor"), ("copyreg", "_reconstructor")}:
            return _reconstructor
        if (module, name) in {("__builtin__", "object"), ("builtins", "object")}:
            return object
        if (module, name) == ("_codecs", "encode"):  # how bytes are pickled at protocols 0-2: a pure function
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"refusing to load {module}.{name}")


def _reconstructor(cls, base, state):
    if cls is _ChumpyStub:
        return _ChumpyStub()
    import copyreg

    return copyreg._reconstructor(cls, base, state)


def restricted_load(path: Path):
    with open(path, "rb") as fh:
        try:
            return RestrictedUnpickler(fh, encoding="latin1").load()
        except (pickle.UnpicklingError, EOFError, AttributeError, TypeError, ValueError) as err:
            raise HeadModelFileError(f"{path}: not a loadable FLAME pickle ({err})") from err


def _restricted_load_npy_object(path: Path):
    """np.load(..., allow_pickle=True) without letting the pickle run code."""
    with open(path, "rb") as fh:
        try:
            version = np.lib.format.read_magic(fh)
            np.lib.format._check_version(version) if hasattr(np.lib.format, "_check_version") else None
            reader = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                      else np.lib.format.read_array_header_2_0)
            _, _, dtype = reader(fh)
        except ValueError as err:
            raise HeadModelFileError(f"{path}: not a .npy file ({err})") from err
        if dtype != np.dtype(object):
            raise HeadModelFileError(f"{path}: expected a pickled dict inside the .npy, found dtype {dtype}")
        payload = fh.read()
    obj = RestrictedUnpickler(io.BytesIO(payload), encoding="latin1").load()
    return obj.item() if isinstance(obj, np.ndarray) else obj


def _as_array(value) -> np.ndarray:
    if isinstance(value, _ChumpyStub):
        return value.to_array()
    if scipy.sparse.issparse(value):
        return np.asarray(value.todense())
    return np.asarray(value)


FLAME_KEYS = ("f", "v_template", "shapedirs", "posedirs", "J_regressor", "kintree_table", "weights")


def load_flame_pickle(path: str | Path, n_shape_total: int = 300) -> dict[str, np.ndarray]:
    """Read generic_model.pkl into plain arrays; shapedirs is split into shape (first 300) and expression."""
    path = Path(path)
    if not path.is_file():
        raise HeadModelFileError(f"{path}: FLAME model file not found")
    raw = restricted_load(path)
    if not isinstance(raw, dict):
        raise HeadModelFileError(f"{path}: expected a dict of arrays, found {type(raw).__name__}")
    missing = [k for k in FLAME_KEYS if k not in raw]
    if missing:
        raise HeadModelFileError(f"{path}: missing FLAME keys {missing}")
    arrays = {k: _as_array(raw[k]) for k in FLAME_KEYS}
    v = arrays["v_template"]
    dirs = arrays["shapedirs"]
    if dirs.ndim != 3 or dirs.shape[:2] != v.shape:
        raise HeadModelFileError(f"{path}: shapedirs has shape {dirs.shape}, expected ({v.shape[0]}, 3, K)")
    posedirs = arrays["posedirs"]
    if posedirs.shape[:2] != v.shape:
        raise HeadModelFileError(f"{path}: posedirs has shape {posedirs.shape}, expected ({v.shape[0]}, 3, P)")
    parents = arrays["kintree_table"][0].astype(np.int64)
    parents[0] = -1
    return {
        "faces": arrays["f"].astype(np.int64), "v_template": v.astype(np.float32),
        "shapedirs": dirs[..., :n_shape_total].astype(np.float32),
        "exprdirs": dirs[..., n_shape_total:].astype(np.float32),
        "posedirs": posedirs.astype(np.float32), "J_regressor": arrays["J_regressor"].astype(np.float32),
        "parents": parents, "lbs_weights": arrays["weights"].astype(np.float32),
    }


def load_landmark_embedding(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """68-point embedding (face index + barycentric coordinates) from FLAME's landmark_embedding.npy/.npz."""
    path = Path(path)
    if not path.is_file():
        raise HeadModelFileError(f"{path}: landmark embedding file not found")
    if path.suffix == ".npz":
        with np.load(path) as npz:
            emb = dict(npz)
    else:
        emb = _restricted_load_npy_object(path)
    if "full_lmk_faces_idx" not in emb or "full_lmk_bary_coords" not in emb:
        raise HeadModelFileError(f"{path}: needs keys full_lmk_faces_idx and full_lmk_bary_coords (68 points)")
    idx = np.asarray(emb["full_lmk_faces_idx"]).reshape(-1).astype(np.int64)
    bary = np.asarray(emb["full_lmk_bary_coords"]).reshape(-1, 3).astype(np.float32)
    if idx.shape[0] != 68:
        raise HeadModelFileError(f"{path}: expected 68 landmarks, found {idx.shape[0]}")
    return idx, bary


def load_uv_texture_space(path: str | Path, n_faces: int) -> UVAlbedo:
    """FLAME texture space npz (keys mean, tex_dir, vt, ft; values 0-255 or 0-1)."""
    path = Path(path)
    if not path.is_file():
        raise HeadModelFileError(f"{path}: texture space file not found")
    with np.load(path) as npz:
        missing = [k for k in ("mean", "tex_dir", "vt", "ft") if k not in npz]
        if missing:
            raise HeadModelFileError(f"{path}: missing texture keys {missing}")
        mean, basis = npz["mean"].astype(np.float32), npz["tex_dir"].astype(np.float32)
        uv, uv_faces = npz["vt"].astype(np.float32), npz["ft"].astype(np.int64)
    if uv_faces.shape[0] != n_faces:
        raise HeadModelFileError(f"{path}: ft has {uv_faces.shape[0]} faces, the model has {n_faces}")
    scale = 255.0 if mean.max() > 1.5 else 1.0
    basis = basis.reshape(*mean.shape, -1)
    return UVAlbedo(mean=mean / scale, basis=basis / scale, uv=uv, uv_faces=uv_faces)


def flat_grey_albedo(n_vertices: int) -> VertexAlbedo:
    return VertexAlbedo(mean=np.full((n_vertices, 3), 0.6, np.float32), basis=np.zeros((n_vertices, 3, 1), np.float32))


def load_flame2020(model_path, landmark_path, texture_path=None, n_shape_total: int = 300) -> HeadModelData:
    arrays = load_flame_pickle(model_path, n_shape_total)
    idx, bary = load_landmark_embedding(landmark_path)
    if texture_path:
        albedo = load_uv_texture_space(texture_path, arrays["faces"].shape[0])
    else:
        log.warning("head model: no FLAME texture space given; using a flat grey albedo")
        albedo = flat_grey_albedo(arrays["v_template"].shape[0])
    regions = derived_regions(arrays["v_template"], arrays["faces"], arrays["lbs_weights"], idx, bary)
    return HeadModelData(**arrays, lmk_faces_idx=idx, lmk_bary_coords=bary, albedo=albedo,
                         source=f"flame2020:{Path(model_path).name}", regions=regions)
