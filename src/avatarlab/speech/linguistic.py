"""Seed 001's linguistic input (Taylor et al. 2017, "A deep learning approach for generalized speech animation"):
binary indicators over a window of k_x video frames of phoneme labels, concatenated into one vector per window.

The paper's three kinds of indicator, built here over this project's phoneme inventory (espeak-ng en-us mnemonics
plus silence, `visemes.PHONEMES`):
- phoneme identity spanning positions: is phoneme p in frame j (every position) / anywhere in the centred spans of
  3, 5, 7 frames and the whole window ("is /s/ among frames j..k?");
- phoneme category at a position: is frame j's phoneme a nasal, a vowel, a bilabial, ... (`CATEGORIES`: manner,
  place, voicing, vowel height/backness/rounding, diphthong, and the viseme group it is seen as);
- transitions between adjacent frames: does the phoneme change between frames k and k + 1, and is the change one
  of silence / vowel / consonant to another of them ("a vowel-consonant transition between k and k + 1?").
The paper's 41 phonemes give 2379 indicators; the espeak inventory here gives `linguistic_size(k_x)` of them.
"""
from __future__ import annotations

import torch

from avatarlab.speech.visemes import _CONSONANTS, _VOWELS, NAMES, PHONEMES, viseme_of

_ROUNDED = {"u:", "U", "U@", "O:", "O@", "oU", "OI", "0", "o@", "w"}
_DIPHTHONGS = {"aI", "aU", "eI", "oU", "OI", "i@", "I@", "e@", "U@", "A@", "O@", "o@"}
# category -> the phonemes (espeak mnemonics) that belong to it
CATEGORIES: dict[str, set[str]] = {
    "silence": {"_"},
    "vowel": set(_VOWELS),
    "consonant": set(_CONSONANTS),
    "plosive": {"p", "b", "t", "d", "k", "g", "?"},
    "nasal": {"m", "n", "N"},
    "fricative": {"f", "v", "T", "D", "s", "z", "S", "Z", "h", "x"},
    "affricate": {"tS", "dZ"},
    "approximant": {"r", "l", "j", "w"},
    "voiced": {"b", "d", "g", "v", "D", "z", "Z", "dZ", "m", "n", "N", "l", "r", "w", "j"} | set(_VOWELS),
    "bilabial": {"p", "b", "m", "w"},
    "labiodental": {"f", "v"},
    "dental": {"T", "D"},
    "alveolar": {"t", "d", "n", "l", "s", "z", "r"},
    "postalveolar": {"tS", "dZ", "S", "Z"},
    "palatal": {"j"},
    "velar": {"k", "g", "N", "x", "w"},
    "glottal": {"h", "?"},
    "close_vowel": {"i:", "I", "i", "u:", "U", "i@", "I@", "U@"},
    "open_vowel": {"a", "A:", "A@", "aI", "aU", "V", "aa"},
    "front_vowel": {"i:", "I", "i", "i@", "I@", "E", "e", "e@", "eI", "a"},
    "back_vowel": {"u:", "U", "U@", "A:", "A@", "O:", "O@", "oU", "0", "o@", "aa"},
    "rounded": _ROUNDED,
    "diphthong": _DIPHTHONGS,
    **{f"viseme_{v}": {p for p in PHONEMES if viseme_of(p) == v} for v in NAMES},
}
CLASSES = ("silence", "vowel", "consonant")  # the coarse classes whose transitions are indicated
SPANS = (3, 5, 7)  # centred spans of the identity indicators (plus the whole window)


def category_matrix() -> torch.Tensor:
    """(n_phonemes, n_categories) 0/1: which categories each phoneme of PHONEMES belongs to."""
    return torch.tensor([[float(p in members) for members in CATEGORIES.values()] for p in PHONEMES])


def coarse_class() -> torch.Tensor:
    """(n_phonemes,) index into CLASSES of each phoneme of PHONEMES."""
    return torch.tensor([0 if p == "_" else 1 if p in _VOWELS else 2 for p in PHONEMES])


def linguistic_size(k_x: int) -> int:
    n_p, n_c = len(PHONEMES), len(CATEGORIES)
    spans = len([s for s in SPANS if s < k_x]) + 1
    transitions = 1 + len(CLASSES) * (len(CLASSES) - 1)
    return k_x * n_p + spans * n_p + k_x * n_c + (k_x - 1) * transitions


def linguistic_features(ids: torch.Tensor, categories: torch.Tensor, classes: torch.Tensor) -> torch.Tensor:
    """(T, k_x) phoneme ids of each window -> (T, linguistic_size(k_x)) 0/1 indicators; `categories` and
    `classes` from category_matrix() and coarse_class() (on the ids' device)."""
    t, k_x = ids.shape
    one_hot = torch.nn.functional.one_hot(ids, len(PHONEMES)).to(categories.dtype)  # (T, k_x, P)
    centre = k_x // 2
    spans = [one_hot[:, centre - s // 2:centre + s // 2 + 1].amax(1) for s in SPANS if s < k_x]
    spans.append(one_hot.amax(1))
    cats = one_hot @ categories  # (T, k_x, C)
    cls = classes[ids]  # (T, k_x)
    before, after = cls[:, :-1], cls[:, 1:]
    moves = [(ids[:, 1:] != ids[:, :-1])]
    moves += [(before == a) & (after == b) for a in range(len(CLASSES)) for b in range(len(CLASSES)) if a != b]
    transitions = torch.stack(moves, -1).to(categories.dtype)  # (T, k_x - 1, 1 + 6)
    return torch.cat([one_hot.flatten(1), *spans, cats.flatten(1), transitions.flatten(1)], 1)
