"""68-point facial landmarks with dlib's HOG face detector and the face_recognition_models shape predictor."""
from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

#: Outer eye corners in the 68-point layout (0-based), the normaliser of the NME.
OUTER_EYE_CORNERS = (36, 45)


def predictor_path() -> Path:
    """Model file shipped by face_recognition_models (found without importing it: its import needs pkg_resources)."""
    spec = importlib.util.find_spec("face_recognition_models")
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError("face_recognition_models is not installed (pip install face_recognition_models)")
    path = Path(list(spec.submodule_search_locations)[0]) / "models" / "shape_predictor_68_face_landmarks.dat"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: dlib 68-point predictor missing from face_recognition_models")
    return path


@lru_cache(maxsize=1)
def _dlib_models():
    import dlib

    return dlib.get_frontal_face_detector(), dlib.shape_predictor(str(predictor_path()))


@dataclass
class Detection:
    landmarks: np.ndarray  # (68, 2) pixel (x, y)
    box: tuple[int, int, int, int]  # left, top, right, bottom
    score: float


def detect_faces(image_rgb: np.ndarray, upsample: int = 1) -> list[tuple[int, int, int, int]]:
    """Face boxes (left, top, right, bottom), largest first."""
    detector, _ = _dlib_models()
    boxes = detector(np.ascontiguousarray(image_rgb), upsample)
    boxes = sorted(boxes, key=lambda b: -b.width() * b.height())
    return [(b.left(), b.top(), b.right(), b.bottom()) for b in boxes]


def detect_landmarks(image_rgb: np.ndarray, upsample: int = 1) -> Detection | None:
    """Landmarks of the largest face in an RGB uint8 image, or None when no face is found."""
    import dlib

    detector, predictor = _dlib_models()
    image = np.ascontiguousarray(image_rgb)
    boxes, scores, _ = detector.run(image, upsample, 0.0)
    if len(boxes) == 0:
        return None
    k = int(np.argmax([b.width() * b.height() for b in boxes]))
    box = boxes[k]
    shape = predictor(image, dlib.rectangle(box.left(), box.top(), box.right(), box.bottom()))
    pts = np.array([[p.x, p.y] for p in shape.parts()], dtype=np.float32)
    return Detection(landmarks=pts, box=(box.left(), box.top(), box.right(), box.bottom()), score=float(scores[k]))


def normalised_mean_error(pred: np.ndarray, truth: np.ndarray) -> float:
    """Mean point-to-point distance over the outer-eye-corner distance of the truth (NME)."""
    iod = np.linalg.norm(truth[OUTER_EYE_CORNERS[0]] - truth[OUTER_EYE_CORNERS[1]])
    return float(np.linalg.norm(pred - truth, axis=-1).mean() / iod)
