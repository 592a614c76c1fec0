"""Real GRID clips: their sentence, audio, frames and a derived phoneme alignment (the evaluation on real clips is
speech/real_eval.py).

GRID's samples here carry no phoneme alignment, so it is derived: the sentence (from the file name, GRID's grammar)
is spoken by espeak-ng, whose phoneme times are exact, and dynamic time warping of the two MFCC sequences maps them
onto the real recording. Where a GRID `.align` file exists the derived word boundaries are checked against it.
"""
from __future__ import annotations

import subprocess
from pathlib import Path

import cv2
import numpy as np

from avatarlab.speech.features import FeatureSpec, frame_features, resample
from avatarlab.speech.tts import Espeak

GRAMMAR = [{"b": "bin", "l": "lay", "p": "place", "s": "set"}, {"b": "blue", "g": "green", "r": "red", "w": "white"},
           {"a": "at", "b": "by", "i": "in", "w": "with"}, None,
           {"z": "zero", **{str(d): w for d, w in zip(range(1, 10), "one two three four five six seven eight nine"
                                                      .split())}},
           {"a": "again", "n": "now", "p": "please", "s": "soon"}]


def sentence(stem: str) -> str:
    """GRID file name -> its sentence (one letter per word; the fourth word is the letter itself)."""
    if len(stem) != 6:
        raise ValueError(f"{stem}: a GRID clip name has six letters, one per word")
    try:
        return " ".join(c if table is None else table[c] for c, table in zip(stem, GRAMMAR))
    except KeyError as err:
        raise ValueError(f"{stem}: {err.args[0]!r} is not a word of GRID's grammar at its position") from err


def read_audio(path: Path, rate: int) -> np.ndarray:
    import imageio_ffmpeg

    proc = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-loglevel", "error", "-i", str(path), "-f", "s16le",
                           "-ac", "1", "-ar", str(rate), "-"], capture_output=True)
    if proc.returncode != 0 or not proc.stdout:
        raise ValueError(f"{path}: no audio track ({proc.stderr.decode(errors='replace').strip()[-200:]})")
    return np.frombuffer(proc.stdout, np.int16).astype(np.float32) / 32768


def read_frames(path: Path) -> tuple[list[np.ndarray], float]:
    cap = cv2.VideoCapture(str(path))
    fps = cap.get(cv2.CAP_PROP_FPS) or 25.0
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
    cap.release()
    if not frames:
        raise ValueError(f"{path}: no video frames")
    return frames, fps


def dtw_path(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dynamic time warping of feature sequences a (N, D) and b (M, D): the (i, j) pairs of the cheapest path."""
    a = (a - a.mean(0)) / (a.std(0) + 1e-6)
    b = (b - b.mean(0)) / (b.std(0) + 1e-6)
    cost = np.linalg.norm(a[:, None] - b[None], axis=2)
    n, m = cost.shape
    acc = np.full((n + 1, m + 1), np.inf)
    acc[0, 0] = 0
    for i in range(1, n + 1):
        for j in range(1, m + 1):
            acc[i, j] = cost[i - 1, j - 1] + min(acc[i - 1, j], acc[i, j - 1], acc[i - 1, j - 1])
    i, j, path = n, m, []
    while i > 0 and j > 0:
        path.append((i - 1, j - 1))
        step = np.argmin([acc[i - 1, j - 1], acc[i - 1, j], acc[i, j - 1]])
        i, j = (i - 1, j - 1) if step == 0 else (i - 1, j) if step == 1 else (i, j - 1)
    return np.array(path[::-1])


def align_phonemes(audio: np.ndarray, text: str, tts: Espeak, spec: FeatureSpec):
    """Phoneme and word times of `text` in `audio` (spec.sample_rate), by DTW against espeak-ng's rendition."""
    utt = tts.synthesize(text)
    pad = 0.6  # seconds of quiet around the reference, so that the recording's own silences have a match
    quiet = 1e-4 * np.random.default_rng(0).standard_normal(int(pad * spec.sample_rate)).astype(np.float32)
    ref = np.concatenate([quiet, resample(utt.audio, utt.rate, spec.sample_rate), quiet])
    fa, fr = frame_features(audio, spec)[:, :13], frame_features(ref, spec)[:, :13]
    path = dtw_path(fr, fa)
    step = spec.step_ms / 1000

    def warp(t: float) -> float:
        i = min(int(round((t + pad) / step)), len(fr) - 1)
        return float(path[path[:, 0] == i, 1].mean()) * step

    phonemes = [(p, warp(s), warp(e)) for p, s, e in utt.phonemes]
    words = [(w, warp(s)) for w, s in utt.words]
    return phonemes, words
