"""Vertex regions for a head model whose files name none (FLAME 2020), derived from its skinning and landmarks.

The procedural head builds its own regions. Downstream code needs two of them from any model: `head` (the skin
surface, eyeballs excluded: the portraits' hair is drawn on it) and `face` (the front of the face: the fits' errors
against the truth are measured there).
"""
from __future__ import annotations

import numpy as np
from matplotlib.path import Path as PolygonPath

from avatarlab.headmodel.joints import POSE_JOINTS

EYES = [POSE_JOINTS.index("eye_left"), POSE_JOINTS.index("eye_right")]
OUTLINE = list(range(0, 17)) + list(range(26, 16, -1))  # the jaw contour, then the brows right to left


def template_landmarks(v_template: np.ndarray, faces: np.ndarray, lmk_faces_idx: np.ndarray,
                       lmk_bary: np.ndarray) -> np.ndarray:
    """The 68 landmarks on the template mesh (68, 3): NumPy's `flame.vertices_to_landmarks` for one mesh."""
    return (v_template[faces[lmk_faces_idx]] * lmk_bary[:, :, None]).sum(1)


def derived_regions(v_template: np.ndarray, faces: np.ndarray, lbs_weights: np.ndarray, lmk_faces_idx: np.ndarray,
                    lmk_bary: np.ndarray, margin: float = 0.1) -> dict[str, np.ndarray]:
    """`head`: vertices skinned mostly to neither eye joint. `face`: head vertices inside the outline of the 68
    landmarks (jaw contour and brows, widened by `margin` of its size about its centre) on the front of the head
    (no further behind the landmarks than the outline is tall)."""
    head = lbs_weights[:, EYES].sum(1) < 0.5
    landmarks = template_landmarks(v_template, faces, lmk_faces_idx, lmk_bary)
    outline = landmarks[OUTLINE, :2]
    centre = outline.mean(0)
    path = PolygonPath(centre + (outline - centre) * (1 + margin))
    inside = path.contains_points(v_template[:, :2])
    height = np.ptp(outline[:, 1])
    front = v_template[:, 2] > landmarks[:, 2].min() - 0.5 * height
    return {"head": head, "face": head & inside & front}
