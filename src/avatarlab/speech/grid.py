"""Real GRID clips as a test set for the seed-000 model (trained on the synthetic corpus).

GRID's samples here carry no phoneme alignment, so it is derived: the sentence (from the file name, GRID's grammar)
is spoken by espeak-ng, whose phoneme times are exact, and dynamic time warping of the two MFCC sequences maps them
onto the real recording. Where a GRID `.align` file exists the derived word boundaries are checked against it.
The video's 68 dlib landmarks, aligned to the neutral shape like the corpus, are the truth for the lip error; as the
model's neutral face is the head model's, the error is also reported with each clip's mean offset removed
("identity-normalised"). Writes a JSON with per-clip and mean numbers.
`python -m avatarlab.speech.grid speech.grid_clips='../shared/data/grid/*.mpg' apps.out=grid_eval.json`
"""
from __future__ import annotations

import glob
import logging
import subprocess
from pathlib import Path

import cv2
import numpy as np
import torch

from avatarlab.entry import entry_point
from avatarlab.headmodel import load_head_model
from avatarlab.io import write_json
from avatarlab.preprocess.landmarks import detect_landmarks
from avatarlab.speech.features import FeatureSpec, frame_features, resample, windows
from avatarlab.speech.lip_metrics import LIPS, align_to, lip_error_percent
from avatarlab.speech.models import load_speech_model
from avatarlab.speech.tts import Espeak
from avatarlab.speech.visemes import PHONEMES, frame_labels, viseme_basis

log = logging.getLogger(__name__)
READS = ('seed', 'head_model', 'speech', 'apps')  # the config sections this step reads (avatarlab/entry.py)

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


@entry_point(READS)
def main(cfg, device) -> None:
    sp = cfg.speech
    given = sp.grid_clips  # a glob, or the list of clip paths the workflow passes
    patterns = [str(given)] if isinstance(given, str) else [str(g) for g in given]
    clips = sorted({Path(c) for p in patterns for c in glob.glob(p)})
    if not clips:
        raise FileNotFoundError(f"{sp.grid_clips}: no GRID clips")
    spec = FeatureSpec(sample_rate=int(sp.sample_rate))
    head = load_head_model(cfg.head_model)
    basis = viseme_basis(head).numpy()
    model = load_speech_model(sp.animate_model, head, device)
    tts = Espeak(sp.voice)
    per_clip, preds, truths, normed_preds = [], [], [], []
    for clip in map(Path, clips):
        text = sentence(clip.stem)
        audio = read_audio(clip, spec.sample_rate)
        frames, fps = read_frames(clip)
        phonemes, words = align_phonemes(audio, text, tts, spec)
        labels = frame_labels(phonemes, len(frames), fps)
        dets = [detect_landmarks(f) for f in frames]
        found = np.array([d is not None for d in dets])
        lms = np.stack([d.landmarks if d is not None else np.zeros((68, 2), np.float32) for d in dets])
        lms[..., 1] *= -1  # image y down -> y up, as the head model's frontal landmarks
        x = torch.from_numpy(windows(audio, spec.sample_rate, len(frames), spec))[None].to(device)
        with torch.no_grad():
            _, logits, pred, _ = model(x)
        pred = pred.cpu()
        pred = pred[0].numpy()[found]
        truth = align_to(lms[found], basis[0])
        offset = (truth - pred).mean(0, keepdims=True)  # the clip's identity vs the head model's neutral face
        row = {"clip": clip.name, "text": text, "frames": len(frames), "faces_found": int(found.sum()),
               "lip_error_percent": lip_error_percent(pred, truth),
               "lip_error_identity_normalised_percent": lip_error_percent(pred + offset, truth),
               "phoneme_accuracy_vs_alignment": None if logits is None else
               float((logits[0].cpu().argmax(-1).numpy() == labels).mean())}
        align_file = clip.with_suffix(".align")
        if align_file.is_file():
            ref = [line.split() for line in align_file.read_text().split("\n") if line.strip()]
            truth_words = [(w, int(s) / 25000) for s, _, w in ref if w != "sil"]
            row["word_start_error_ms"] = float(1000 * np.mean([abs(a[1] - b[1]) for a, b in zip(words, truth_words)]))
        per_clip.append(row)
        preds.append(pred)
        truths.append(truth)
        normed_preds.append(pred + offset)
        log.info("%s '%s': lip error %.2f %% IOD (%.2f identity-normalised), %d/%d faces", clip.name, text,
                 row["lip_error_percent"], row["lip_error_identity_normalised_percent"], found.sum(), len(frames))
    mouth_motion = float(np.mean([lip_error_percent(np.repeat(t.mean(0, keepdims=True), len(t), 0), t)
                                  for t in truths]))
    report = {"clips": per_clip, "model": str(sp.animate_model), "phonemes": len(PHONEMES),
              "lip_error_percent": lip_error_percent(np.concatenate(preds), np.concatenate(truths)),
              "lip_error_identity_normalised_percent": lip_error_percent(np.concatenate(normed_preds),
                                                                         np.concatenate(truths)),
              "static_mouth_baseline_percent": mouth_motion,
              "lips": LIPS[0], "alignment": "DTW of MFCCs against espeak-ng's rendition of the sentence"}
    write_json(cfg.apps.out, report)
    log.info("GRID (%d clips): lip error %.2f %% IOD, identity-normalised %.2f %% (a still mouth at each clip's mean: "
             "%.2f %%)", len(clips), report["lip_error_percent"], report["lip_error_identity_normalised_percent"],
             mouth_motion)


if __name__ == "__main__":
    main()
