"""A preprocessed subject's folder: the one place that knows its file names and formats.

    results/<scale>/subjects/<subject>/
        frames/*.png, frames.json      the cropped frames (RGB PNGs) and their metadata (sources, clip of each frame)
        landmarks.npz                  points (N, 68, 2) pixels, found (N,) bool
        masks.npz                      masks (N, H, W) uint8 {0, 1}: head, hair, neck
        fit_rgb.npz                    eq. (1) per frame: expression, pose (root folded into R, t), K, R, t, fitted;
                                       shape, texture, lighting shared (video) or per image (image sets)
        interpolated.npz               frames re-created by the frame interpolator (indices, frames)
        input/truth.npz                ground truth of a synthetic subject

Every reader takes arrays only (no pickles) and names the file in its error.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from avatarlab.runtime.io import atomic_path, write_json
from avatarlab.runtime.safe_load import InputFileError, load_arrays

FIT_KEYS = ("shape", "texture", "lighting", "expression", "pose", "K", "R", "t", "fitted")
SHARED_FIT_KEYS = {"shape": 1, "texture": 1, "lighting": 2}  # dimensions of the shared (video) form


@dataclass
class SubjectDir:
    path: Path

    def __post_init__(self):
        self.path = Path(self.path)

    # --- frames -----------------------------------------------------------------------------------------------------
    @property
    def frames_json(self) -> Path:
        return self.path / "frames.json"

    def frames_meta(self) -> dict:
        if not self.frames_json.is_file():
            raise InputFileError(f"{self.frames_json}: no such file (run the frame extraction first)")
        return json.loads(self.frames_json.read_text())

    def frame_count(self) -> int:
        return int(self.frames_meta()["count"])

    def frames(self, indices=None) -> np.ndarray:
        """(N, H, W, 3) uint8 RGB, all frames or those at `indices`."""
        meta = self.frames_meta()
        files = meta["files"] if indices is None else [meta["files"][i] for i in indices]
        images = []
        for name in files:
            image = cv2.imread(str(self.path / "frames" / name))
            if image is None:
                raise InputFileError(f"{self.path / 'frames' / name}: cannot be read as an image")
            images.append(cv2.cvtColor(image, cv2.COLOR_BGR2RGB))
        return np.stack(images)

    def frame_clips(self) -> np.ndarray:
        """(N,) the index of the input file (clip) each frame came from (0 for a single input)."""
        meta = self.frames_meta()
        sources = meta.get("sources") or [0] * meta["count"]
        names = list(dict.fromkeys(sources))
        return np.array([names.index(s) for s in sources], dtype=int)

    # --- landmarks, masks ---------------------------------------------------------------------------------------------
    def landmarks(self) -> tuple[np.ndarray, np.ndarray]:
        """points (N, 68, 2) in pixels (NaN where not found), found (N,) bool."""
        data = load_arrays(self.path / "landmarks.npz", ("points", "found"), "landmarks (points, found)")
        return data["points"].astype(np.float64), data["found"].astype(bool)

    def masks(self) -> np.ndarray:
        return load_arrays(self.path / "masks.npz", ("masks",), "head masks")["masks"]

    # --- the RGB fit ----------------------------------------------------------------------------------------------------
    @property
    def fit_file(self) -> Path:
        return self.path / "fit_rgb.npz"

    def fit(self, per_frame: bool = True) -> dict[str, np.ndarray]:
        """The fitted parameters; with `per_frame`, shared vectors (a video's one shape, texture, lighting) are
        repeated for every frame so that every array has one row per frame."""
        fit = load_arrays(self.fit_file, FIT_KEYS + ("image_size",), "an RGB fit", finite=FIT_KEYS)
        if per_frame:
            n = len(fit["fitted"])
            for key, dims in SHARED_FIT_KEYS.items():
                if fit[key].ndim == dims:
                    fit[key] = np.broadcast_to(fit[key], (n, *fit[key].shape)).copy()
        return fit

    def write_fit(self, **arrays) -> None:
        missing = [k for k in FIT_KEYS + ("image_size",) if k not in arrays]
        if missing:
            raise ValueError(f"{self.fit_file}: fit without {', '.join(missing)}")
        with atomic_path(self.fit_file) as tmp:
            np.savez(tmp, **arrays)

    # --- interpolation, truth ---------------------------------------------------------------------------------------------
    @property
    def interpolated_file(self) -> Path:
        return self.path / "interpolated.npz"

    def interpolated(self, path: str | Path | None = None) -> tuple[np.ndarray, np.ndarray]:
        """indices (K,), frames (K, H, W, 3) uint8 made by the frame interpolator."""
        data = load_arrays(Path(path) if path else self.interpolated_file, ("indices", "frames"),
                           "interpolated frames")
        return data["indices"].astype(int), data["frames"]

    def truth(self, path: str | Path | None = None) -> dict[str, np.ndarray]:
        return load_arrays(Path(path) if path else self.path / "input" / "truth.npz", (), "a synthetic truth")

    def write_report(self, name: str, payload: dict) -> None:
        write_json(self.path / name, payload)
