"""The seed-000 audio models (trained on the synthetic corpus) on real recordings: GRID clips and the Obama clips.

Truth: each video frame's 68 dlib landmarks, similarity-aligned to the head model's neutral face on the stable points
(as the corpus), resampled to the models' 25 fps (linear in time; the Obama clips are 29.97 fps). As the models'
neutral face is the head model's, every prediction and every baseline is scored on the mouth's *motion*: each clip's
mean shape is the truth's (the identity offset removed), so a still mouth at the clip's mean shape is the trivial
predictor to beat. Rows per speaker (the clip's folder: grid, obama):
- `synthetic`: the model as trained on the synthetic corpus (espeak-ng voices, augmented audio);
- `adapted_other_clips`: fine-tuned on the real clips' own audio and lips, leave one clip out (the held-out clip's
  speaker is heard in the other clips: two real speakers only here);
- `adapted_other_speakers`: fine-tuned on the other speakers' clips only (the held-out speaker never heard).
Each beside the still mouth, with the per-clip paired gain (mean +- 95 % CI over clips, wins) so that a gain is
called one only when the CI excludes zero. A second view, on timing alone: the correlation over each clip's frames
of the predicted and the true mouth opening (the inner lips' gap), beside what the audio's loudness alone gives
(log RMS over the video frame's own 40 ms, and over the model's own window), again with the per-clip paired gain
over the better of the two. The still mouth follows nothing (r = 0); loudness is the trivial predictor of when a
mouth opens. GRID clips also get the phoneme accuracy of models with a phoneme module
against an alignment derived by DTW with espeak-ng (speech/grid.py) and, where GRID's `.align` exists, its word-start
error. Clips without an audio track are listed as skipped.
`python -m avatarlab.speech.real_eval speech.real_clips='[../shared/data/grid/*.mpg]' \
speech.real_models='[results/tiny/speech/lstm_noreg/model.pt]' speech.real_eval_out=real_eval.json`
"""
from __future__ import annotations

import copy
import glob
import logging
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from avatarlab.headmodel import load_head_model
from avatarlab.metrics.seeds import gain_verdict, mean_ci, signed_range
from avatarlab.preprocess.landmarks import detect_landmarks
from avatarlab.runtime.entry import entry_point
from avatarlab.runtime.io import write_json
from avatarlab.speech.features import FeatureSpec, windows
from avatarlab.speech.grid import align_phonemes, read_audio, read_frames, sentence
from avatarlab.speech.lip_metrics import align_to, correlation, lip_error_percent, motion_only, mouth_opening
from avatarlab.speech.models import AudioToVisemes, load_speech_model
from avatarlab.speech.tts import Espeak
from avatarlab.speech.visemes import frame_labels, viseme_basis

log = logging.getLogger(__name__)
READS = ('seed', 'head_model', 'speech')  # the config sections this step reads (runtime/entry.py)
FPS = 25.0
DETECT_WIDTH = 640  # frames wider than this are detected at this width (landmarks scaled back): dlib's speed


@dataclass
class RealClip:
    name: str
    speaker: str
    audio: np.ndarray           # at the feature rate
    windows: np.ndarray         # (T, W, 65) model inputs at 25 fps
    truth: np.ndarray           # (T, 68, 2) aligned landmarks at 25 fps
    frames: int                 # video frames
    faces_found: int
    text: str | None = None
    labels: np.ndarray | None = None   # derived phoneme ids per 25-fps frame (GRID clips)
    word_start_error_ms: float | None = None
    loudness: dict[str, np.ndarray] | None = None  # loudness_predictors(): trivial predictors of the opening


def loudness(audio: np.ndarray, rate: int, frames: int, start_ms: float, end_ms: float) -> np.ndarray:
    """Log RMS of `audio` in [k * 40 ms + start_ms, k * 40 ms + end_ms) for each 25-fps frame k (the part inside
    the clip; -9.2, log 1e-4, where it is silent or outside)."""
    out = np.empty(frames, np.float32)
    for k in range(frames):
        lo = max(0, int(round((k / FPS + start_ms / 1000) * rate)))
        hi = min(len(audio), int(round((k / FPS + end_ms / 1000) * rate)))
        part = audio[lo:hi]
        out[k] = np.log(np.sqrt(np.mean(part.astype(np.float64) ** 2)) + 1e-4) if len(part) else np.log(1e-4)
    return out


def loudness_predictors(audio: np.ndarray, frames: int, spec: FeatureSpec) -> dict[str, np.ndarray]:
    """The trivial predictors of the mouth's opening from the audio alone: its loudness in the video frame's own
    40 ms, and in the window the models hear (spec.window_ms ending spec.lookahead_ms after the frame)."""
    return {"loudness_frame": loudness(audio, spec.sample_rate, frames, 0.0, 1000 / FPS),
            "loudness_window": loudness(audio, spec.sample_rate, frames, spec.lookahead_ms - spec.window_ms,
                                        spec.lookahead_ms)}


def video_landmarks(path: Path) -> tuple[np.ndarray, np.ndarray, float]:
    """dlib's 68 landmarks of every frame (y up), which frames had a face, and the video's frame rate."""
    frames, fps = read_frames(path)
    points, found = [], []
    for frame in frames:
        scale = min(1.0, DETECT_WIDTH / frame.shape[1])
        if scale < 1:
            frame = cv2.resize(frame, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        det = detect_landmarks(frame)
        found.append(det is not None)
        points.append(det.landmarks / scale if det is not None else np.zeros((68, 2), np.float32))
    points = np.stack(points).astype(np.float32)
    points[..., 1] *= -1  # image y down -> y up, as the head model's frontal landmarks
    return points, np.array(found), float(fps)


def resample_truth(aligned: np.ndarray, found: np.ndarray, fps: float) -> np.ndarray:
    """Aligned landmarks of the frames with a face (times k / fps) at 25 fps, linear in time, over the video's span."""
    times = np.arange(len(aligned)) / fps
    out_times = np.arange(int(np.floor(times[-1] * FPS)) + 1) / FPS
    flat = aligned[found].reshape(int(found.sum()), -1)
    return np.stack([np.interp(out_times, times[found], flat[:, j]) for j in range(flat.shape[1])],
                    1).reshape(len(out_times), 68, 2).astype(np.float32)


def load_clip(path: Path, neutral: np.ndarray, spec: FeatureSpec, tts: Espeak) -> RealClip | None:
    """A real clip as model inputs and truth, or None (logged) when it has no audio or too few faces."""
    try:
        audio = read_audio(path, spec.sample_rate)
    except ValueError as err:
        log.warning("skipped: %s", err)
        return None
    points, found, fps = video_landmarks(path)
    if found.sum() < max(2, len(found) // 2):
        log.warning("skipped: %s: dlib found a face in %d of %d frames", path, found.sum(), len(found))
        return None
    truth = resample_truth(align_to(points, neutral), found, fps)
    clip = RealClip(path.stem, path.parent.name, audio, windows(audio, spec.sample_rate, len(truth), spec), truth,
                    len(found), int(found.sum()), loudness=loudness_predictors(audio, len(truth), spec))
    try:
        clip.text = sentence(path.stem)
    except ValueError:
        return clip  # not a GRID clip: no sentence to align
    phonemes, words = align_phonemes(audio, clip.text, tts, spec)
    clip.labels = frame_labels(phonemes, len(truth), FPS)
    align_file = path.with_suffix(".align")
    if align_file.is_file():
        ref = [line.split() for line in align_file.read_text().split("\n") if line.strip()]
        truth_words = [(w, int(s) / 25000) for s, _, w in ref if w != "sil"]
        clip.word_start_error_ms = float(1000 * np.mean([abs(a[1] - b[1]) for a, b in zip(words, truth_words)]))
    return clip


@torch.no_grad()
def predict(model: AudioToVisemes, clip: RealClip) -> tuple[np.ndarray, np.ndarray | None]:
    """The model's landmarks on the clip moved to the truth's mean shape (motion only), and its phoneme ids."""
    model.eval()
    _, logits, landmarks, _ = model(torch.from_numpy(clip.windows)[None])
    moved = motion_only([landmarks[0].numpy()], [clip.truth])
    return moved, None if logits is None else logits[0].argmax(-1).numpy()


def adapt(model: AudioToVisemes, clips: list[RealClip], sp, seed: int) -> AudioToVisemes:
    """A copy of `model` fine-tuned on `clips`' own audio and lips: the landmark loss on each clip's motion applied to
    the model's neutral face (as the corpus targets), random 32-frame chunks, Adam at speech.adapt_lr."""
    tuned = copy.deepcopy(model)
    if not clips or int(sp.adapt_epochs) == 0:
        return tuned
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    neutral = tuned.basis[0].reshape(68, 2).numpy()
    targets = [c.truth - c.truth.mean(0, keepdims=True) + neutral for c in clips]
    optim = torch.optim.Adam(tuned.parameters(), lr=float(sp.adapt_lr))
    chunk, batch = int(sp.chunk_frames), int(sp.batch)
    steps = int(np.ceil(len(clips) * int(sp.adapt_repeats) / batch))
    tuned.train()
    for _ in range(int(sp.adapt_epochs)):
        for _ in range(steps):
            picks = rng.integers(0, len(clips), batch)
            length = min(chunk, *(len(clips[k].truth) for k in picks))
            xs, ys = [], []
            for k in picks:
                start = int(rng.integers(0, len(clips[k].truth) - length + 1))
                xs.append(clips[k].windows[start:start + length])
                ys.append(targets[k][start:start + length])
            landmarks = tuned(torch.from_numpy(np.stack(xs)))[2]
            loss = ((landmarks - torch.from_numpy(np.stack(ys))) ** 2).sum(-1).mean()
            optim.zero_grad()
            loss.backward()
            optim.step()
    return tuned.eval()


def still_mouth(clip: RealClip) -> np.ndarray:
    return np.repeat(clip.truth.mean(0, keepdims=True), len(clip.truth), 0)


def opening_timing(preds: list[np.ndarray], clips: list[RealClip]) -> dict | None:
    """How well each clip's predicted mouth opening follows the true one over time (Pearson's r per clip), beside the
    loudness predictors' r on the same frames, and the per-clip paired gain over the better of them (by mean)."""
    if any(c.loudness is None for c in clips):
        return None
    truths = [mouth_opening(c.truth) for c in clips]
    model = np.array([correlation(mouth_opening(p), t) for p, t in zip(preds, truths)])
    baselines = {name: np.array([correlation(c.loudness[name], t) for c, t in zip(clips, truths)])
                 for name in clips[0].loudness}
    best = max(baselines, key=lambda name: baselines[name].mean())
    gains = model - baselines[best]
    mean, half, _ = mean_ci(gains)
    return {"model_r": float(model.mean()), "model_r_ci95": mean_ci(model)[1],
            "baselines_r": {name: float(r.mean()) for name, r in baselines.items()}, "best_baseline": best,
            "gain_mean_per_clip": mean, "gain_ci95": half, "wins": int((gains > 0).sum()),
            "beats_best_baseline": gain_verdict(mean, half, "clips'") == "better",
            "per_clip": {c.name: {"model_r": float(m), **{name: float(r[k]) for name, r in baselines.items()}}
                         for k, (c, m) in enumerate(zip(clips, model))}}


def compare(preds: list[np.ndarray], clips: list[RealClip]) -> dict:
    """Lip errors of `preds` over the clips' frames beside the still mouth's, and the per-clip paired gain; the
    opening's timing beside the loudness predictors' (`opening_timing`)."""
    truth = np.concatenate([c.truth for c in clips])
    stills = [still_mouth(c) for c in clips]
    model = [lip_error_percent(p, c.truth) for p, c in zip(preds, clips)]
    still = [lip_error_percent(s, c.truth) for s, c in zip(stills, clips)]
    gains = np.array(still) - np.array(model)
    mean, half, _ = mean_ci(gains)
    return {"lip_error_percent": lip_error_percent(np.concatenate(preds), truth),
            "opening_timing": opening_timing(preds, clips),
            "still_mouth_percent": lip_error_percent(np.concatenate(stills), truth),
            "gain_mean_per_clip": mean, "gain_ci95": half,
            "wins": int((gains > 0).sum()), "clips": len(clips),
            "beats_still_mouth": gain_verdict(mean, half, "clips'") == "better",
            "per_clip": {c.name: {"lip_error_percent": m, "still_mouth_percent": s}
                         for c, m, s in zip(clips, model, still)}}


SEED_STRIDE = 10_000  # fine-tuning seed m of clip k: seed + k + m * SEED_STRIDE (m = 0: the headline's)


def seed_spread(rows: list[dict]) -> dict:
    """One adapted row's compare() per fine-tuning seed -> the spread of its gain over the still mouth and of its
    opening r, and in how many seeds the gain is beyond its CI."""
    timing = [r["opening_timing"] for r in rows]
    return {"seeds": len(rows), "gain_mean_per_clip": [r["gain_mean_per_clip"] for r in rows],
            "gain_ci95": [r["gain_ci95"] for r in rows],
            "lip_error_percent": [r["lip_error_percent"] for r in rows],
            "beats_still_mouth": sum(bool(r["beats_still_mouth"]) for r in rows),
            "opening_r": None if any(t is None for t in timing) else [t["model_r"] for t in timing]}


def evaluate_model(model: AudioToVisemes, clips: list[RealClip], sp, seed: int) -> dict:
    """The three rows (synthetic, adapted on the other clips, adapted on the other speakers) per speaker. The adapted
    rows are fine-tuned `speech.adapt_seeds` times; the first seed's predictions are the row, and with more than one
    the row's `fine_tuning_seeds` gives every seed's gain (`seed_spread`): a fine-tune's luck is not a model's gain."""
    speakers = sorted({c.speaker for c in clips})
    synthetic = {c.name: predict(model, c) for c in clips}
    adapting = int(sp.adapt_epochs) > 0 and len(clips) > 1
    seeds = range(int(sp.adapt_seeds) if adapting else 0)
    other_clips = [{c.name: predict(adapt(model, [o for o in clips if o is not c], sp, seed + k + m * SEED_STRIDE),
                                    c)[0] for k, c in enumerate(clips)} for m in seeds]
    other_speakers = []
    for m in seeds if len(speakers) > 1 else []:
        preds = {}
        for k, speaker in enumerate(speakers):
            tuned = adapt(model, [o for o in clips if o.speaker != speaker], sp, seed + 1000 + k + m * SEED_STRIDE)
            preds.update({c.name: predict(tuned, c)[0] for c in clips if c.speaker == speaker})
        other_speakers.append(preds)
    out = {}
    for speaker in speakers:
        mine = [c for c in clips if c.speaker == speaker]
        rows = {"synthetic": compare([synthetic[c.name][0] for c in mine], mine)}
        for key, runs in (("adapted_other_clips", other_clips), ("adapted_other_speakers", other_speakers)):
            if runs:
                per_seed = [compare([run[c.name] for c in mine], mine) for run in runs]
                rows[key] = per_seed[0]
                if len(per_seed) > 1:
                    rows[key]["fine_tuning_seeds"] = seed_spread(per_seed)
        labelled = [(synthetic[c.name][1], c.labels) for c in mine if c.labels is not None]
        if labelled and labelled[0][0] is not None:
            rows["synthetic"]["phoneme_accuracy_vs_alignment"] = float(
                np.concatenate([p == t for p, t in labelled]).mean())
        out[speaker] = rows
    return out


def clip_paths(patterns, per_speaker: int | None = None) -> list[Path]:
    """The clips the patterns match, sorted; with `per_speaker`, the first that many of each speaker (folder)."""
    patterns = [str(patterns)] if isinstance(patterns, str) else [str(p) for p in patterns]
    paths = sorted({Path(c) for p in patterns for c in glob.glob(p)})
    if not per_speaker:
        return paths
    seen = Counter()  # clips kept per speaker: the folder's name, as load_clip reads it
    kept = []
    for path in paths:
        seen[path.parent.name] += 1
        if seen[path.parent.name] <= int(per_speaker):
            kept.append(path)
    return kept


def run(cfg) -> dict:
    """The report of speech.real_models on speech.real_clips (what main writes to speech.real_eval_out)."""
    sp = cfg.speech
    paths = clip_paths(sp.real_clips, sp.real_clips_per_speaker)
    if not paths:
        raise FileNotFoundError(f"speech.real_clips={list(sp.real_clips)}: no clips")
    spec = FeatureSpec(sample_rate=int(sp.sample_rate))
    head = load_head_model(cfg.head_model)
    neutral = viseme_basis(head)[0].numpy()
    tts = Espeak(sp.voice)
    clips, skipped = [], []
    for path in paths:
        clip = load_clip(path, neutral, spec, tts)
        (clips.append(clip) if clip is not None else skipped.append(str(path)))
    if not clips:
        raise ValueError(f"speech.real_clips: none of {len(paths)} clips has audio and faces")
    report = {"clips": [{"clip": c.name, "speaker": c.speaker, "text": c.text, "video_frames": c.frames,
                         "faces_found": c.faces_found, "frames_25fps": len(c.truth), "seconds": len(c.truth) / FPS,
                         "word_start_error_ms": c.word_start_error_ms} for c in clips],
              "skipped": skipped, "models": {},
              "adaptation": {"epochs": int(sp.adapt_epochs), "lr": float(sp.adapt_lr),
                             "repeats": int(sp.adapt_repeats), "seeds": int(sp.adapt_seeds)},
              "truth": "dlib 68 landmarks aligned to the neutral face on brows, nose and eyes, 25 fps; motion only "
                       "(each clip's mean shape is the truth's)",
              "published_seed_000_grid_percent": 1.9}
    for model_path in map(Path, sp.real_models):
        name = model_path.parent.name
        model = load_speech_model(model_path, head, "cpu")
        rows = evaluate_model(model, clips, sp, int(cfg.seed))
        report["models"][name] = {"path": str(model_path), "speakers": rows}
        for speaker, by_row in rows.items():
            for row, r in by_row.items():
                ci = "" if r["gain_ci95"] is None else f" +- {r['gain_ci95']:.2f}"
                log.info("%s on %s (%d clips), %s: lip motion error %.2f %% IOD vs still mouth %.2f %% (gain per "
                         "clip %+.2f%s, %d/%d wins)", name, speaker, r["clips"], row, r["lip_error_percent"],
                         r["still_mouth_percent"], r["gain_mean_per_clip"], ci, r["wins"], r["clips"])
                if "fine_tuning_seeds" in r:
                    spread = r["fine_tuning_seeds"]
                    log.info("%s on %s, %s over %d fine-tuning seeds: gain per clip %s, beyond its CI in %d",
                             name, speaker, row, spread["seeds"], signed_range(spread["gain_mean_per_clip"]),
                             spread["beats_still_mouth"])
                timing = r["opening_timing"]
                if timing is not None:
                    ci = "" if timing["gain_ci95"] is None else f" +- {timing['gain_ci95']:.2f}"
                    log.info("%s on %s, %s: mouth-opening r %.2f vs %s %.2f (gain per clip %+.2f%s, %d/%d wins)",
                             name, speaker, row, timing["model_r"], timing["best_baseline"],
                             timing["baselines_r"][timing["best_baseline"]], timing["gain_mean_per_clip"], ci,
                             timing["wins"], r["clips"])
    return report


@entry_point(READS)
def main(cfg, device) -> None:
    write_json(cfg.speech.real_eval_out, run(cfg))


if __name__ == "__main__":
    main()
