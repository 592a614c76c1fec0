"""Visemes in the head model's space (seed 000 section 4: viseme blendshapes; groups after Bear & Harvey).

Each viseme is a mouth pose of the head model, described as the animator would - jaw opening, mouth width, upper-lip
raise and lip press/part - and turned into expression coefficients by least squares on the head model's own
landmarks (ridge-regularised, within [-2, 2]), so the same table works for the procedural head and for FLAME.
A phoneme maps to one viseme; the frontal projection of the 68 landmarks of each viseme gives the fixed linear layer
of seed 000, l = Pr(B0) + sum_j a_j (Pr(B_j) - Pr(B0)).
"""
from __future__ import annotations

import numpy as np
import torch

# name: (jaw rad, mouth width change mm, upper-lip raise mm, lip part (+) / press (-) beyond the jaw, mm)
VISEMES: dict[str, tuple[float, float, float, float]] = {
    "sil": (0.0, 0.0, 0.0, 0.0),        # B0, the neutral face
    "pbm": (0.0, 0.0, -1.0, -4.0),      # lips pressed
    "fv": (0.04, 2.0, 2.5, -2.0),       # lower lip to upper teeth
    "th": (0.08, 1.0, 1.0, 0.0),        # tongue between teeth
    "tdnl": (0.1, 2.0, 0.5, 0.0),       # alveolar: t d n l s z
    "kg": (0.14, 1.0, 0.0, 0.0),        # velar and h
    "ch": (0.08, -8.0, 2.0, 1.0),       # postalveolar, protruded: tS dZ S Z
    "r": (0.08, -6.0, 1.0, 0.0),
    "w": (0.05, -12.0, 0.0, -1.0),      # rounded close: w u: U
    "open": (0.3, 2.0, 1.0, 2.0),       # a A: aI aU V @
    "mid": (0.18, 4.0, 1.0, 0.0),       # E e eI 3:
    "spread": (0.1, 8.0, 1.0, 0.0),     # i: I j
    "round": (0.22, -9.0, 0.0, 1.0),    # O: o@ oU OI 0
}
NAMES = list(VISEMES)
MOUTH = list(range(48, 68))

_CONSONANTS = {"p": "pbm", "b": "pbm", "m": "pbm", "f": "fv", "v": "fv", "T": "th", "D": "th",
               "t": "tdnl", "d": "tdnl", "n": "tdnl", "l": "tdnl", "s": "tdnl", "z": "tdnl", "k": "kg", "g": "kg",
               "N": "kg", "h": "kg", "x": "kg", "tS": "ch", "dZ": "ch", "S": "ch", "Z": "ch", "r": "r", "w": "w",
               "j": "spread", "?": "kg"}
_VOWELS = {"u:": "w", "U": "w", "U@": "w", "a": "open", "A:": "open", "A@": "open", "aI": "open", "aU": "open",
           "V": "open", "@": "open", "@L": "tdnl", "3:": "mid", "E": "mid", "e@": "mid", "eI": "mid", "e": "mid",
           "i:": "spread", "I": "spread", "i": "spread", "i@": "spread", "I@": "spread", "O:": "round",
           "O@": "round", "oU": "round", "OI": "round", "0": "round", "o@": "round", "aa": "open"}
# the phoneme inventory the models predict: espeak-ng (en-us) mnemonics, plus silence
PHONEMES = ["_"] + sorted(set(_CONSONANTS) | set(_VOWELS))


def normalise_phoneme(name: str) -> str:
    """espeak's event names carry stress and variant marks ('t#', "'a", 'n-'): the base phoneme, '_' for pauses."""
    base = name.strip().strip("'\",%=#-;").replace("#", "")
    if not base or base.startswith("_"):
        return "_"
    if base in _CONSONANTS or base in _VOWELS:
        return base
    for size in (2, 1):  # a known prefix ('aI@' -> 'aI', 'r-' -> 'r')
        if base[:size] in _CONSONANTS or base[:size] in _VOWELS:
            return base[:size]
    return "@" if base[0] in "aeiouAEIOU@3V0" else "t"


def viseme_of(phoneme: str) -> str:
    p = normalise_phoneme(phoneme)
    return "sil" if p == "_" else _CONSONANTS.get(p) or _VOWELS[p]


def phoneme_to_viseme_matrix() -> torch.Tensor:
    """(n_phonemes, n_visemes) 0/1: which viseme each phoneme of PHONEMES belongs to."""
    m = torch.zeros(len(PHONEMES), len(NAMES))
    for i, p in enumerate(PHONEMES):
        m[i, NAMES.index(viseme_of(p))] = 1
    return m


def mouth_features(landmarks: torch.Tensor) -> torch.Tensor:
    """(..., 68, 2) -> (..., 3) in mm: mouth width, upper-lip height, outer lip opening."""
    width = landmarks[..., 54, 0] - landmarks[..., 48, 0]
    upper = landmarks[..., 51, 1]
    opening = landmarks[..., 51, 1] - landmarks[..., 57, 1]
    return 1000 * torch.stack([width, upper, opening], -1)


def viseme_parameters(head, components: int = 16, ridge: float = 0.05) -> tuple[torch.Tensor, torch.Tensor]:
    """(n_visemes, n_expression) expression and (n_visemes,) jaw rotation of every viseme of VISEMES."""
    n = min(components, head.n_expression)
    table = torch.tensor([VISEMES[k] for k in NAMES], dtype=torch.float32)
    jaw = table[:, 0]
    zero_shape = torch.zeros(1, head.n_shape)
    with torch.no_grad():
        base = mouth_features(frontal_landmarks(head, zero_shape, torch.zeros(1, head.n_expression),
                                                torch.zeros(1)))[0]
        jaw_only = mouth_features(frontal_landmarks(head, zero_shape, torch.zeros(len(NAMES), head.n_expression),
                                                    jaw))
        unit = torch.zeros(n + 1, head.n_expression)
        unit[1:, :n] = torch.eye(n)
        feats = mouth_features(frontal_landmarks(head, zero_shape, unit, torch.zeros(n + 1)))
    J = (feats[1:] - feats[:1]).T  # (3, n): feature change per unit coefficient (the model is linear in them)
    target = torch.stack([base[0] + table[:, 1], base[1] + table[:, 2], jaw_only[:, 2] + table[:, 3]], 1)
    residual = (target - jaw_only).T  # (3, n_visemes)
    coef = torch.linalg.solve(J.T @ J + ridge * torch.eye(n), J.T @ residual).T.clamp(-2, 2)
    expression = torch.zeros(len(NAMES), head.n_expression)
    expression[:, :n] = coef
    expression[0] = 0  # B0 is the neutral face
    return expression, jaw


def frontal_landmarks(head, shape: torch.Tensor, expression: torch.Tensor, jaw: torch.Tensor) -> torch.Tensor:
    """(B, 68, 2) landmarks of the head model seen from the front (orthographic x, y up; metres)."""
    pose = torch.zeros(expression.shape[0], 15)
    pose[:, 6] = jaw
    out = head(shape.expand(expression.shape[0], -1), expression, pose)
    return out.landmarks3d[..., :2]


def viseme_basis(head) -> torch.Tensor:
    """(n_visemes, 68, 2): Pr(B_j), the frontal landmarks of every viseme on the mean head; row 0 is B0 (neutral)."""
    expression, jaw = viseme_parameters(head)
    with torch.no_grad():
        return frontal_landmarks(head, torch.zeros(1, head.n_shape), expression, jaw)


def frame_labels(phonemes: list[tuple[str, float, float]], n_frames: int, fps: float = 25.0) -> np.ndarray:
    """The phoneme id (index in PHONEMES) sounding at each frame's time; '_' (silence) outside speech."""
    labels = np.zeros(n_frames, np.int64)
    for name, start, end in phonemes:
        first, last = int(np.ceil(start * fps)), int(np.ceil(end * fps))
        labels[first:min(last, n_frames)] = PHONEMES.index(normalise_phoneme(name))
    return labels
