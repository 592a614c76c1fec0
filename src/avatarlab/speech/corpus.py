"""The synthetic audio-visual speech corpus (GRID's grammar, espeak-ng and Festival voices, the head model's mouth).

Per utterance: a random six-word GRID command, spoken with the speaker's voice (speaker k gets
`speech.voices[k mod n]`: espeak-ng accents with male/female variants, Festival's diphone and HTS voices) at the
speaker's rate (and pitch, for espeak-ng); the engine's phoneme timings (espeak-ng's phoneme events, Festival's
segments mapped to espeak's phonemes) are exact. At 25 fps each frame gets the viseme of the phoneme sounding then,
smoothed over
neighbouring frames (coarticulation) and scaled by the speaker's articulation strength; the head model with the
speaker's face shape turns these into 68 frontal landmarks, with a little rigid head motion and landmark noise, as a
tracked video would give. Speakers are split into train / validation / test like GRID (24 / 6 / 4 of 34).
Writes one `corpus.npz` (audio at 25 kHz, per-frame phoneme ids, viseme weights, landmarks, splits).
`python -m avatarlab.speech.corpus speech.corpus=results/tiny/speech/corpus.npz`
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig
from scipy.ndimage import gaussian_filter1d

from avatarlab.headmodel import load_head_model
from avatarlab.runtime.entry import entry_point
from avatarlab.runtime.io import atomic_path, write_json
from avatarlab.speech.features import resample
from avatarlab.speech.festival import Festival, is_festival_voice
from avatarlab.speech.tts import Espeak
from avatarlab.speech.visemes import (
    NAMES,
    PHONEMES,
    frame_labels,
    frontal_landmarks,
    viseme_of,
    viseme_parameters,
)

log = logging.getLogger(__name__)
READS = ('seed', 'head_model', 'speech')  # the config sections this step reads (runtime/entry.py)

GRID_WORDS = [["bin", "lay", "place", "set"], ["blue", "green", "red", "white"], ["at", "by", "in", "with"],
              list("abcdefghijklmnopqrstuvxyz"),
              ["zero", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine"],
              ["again", "now", "please", "soon"]]
FPS = 25.0


def grid_sentence(rng: np.random.Generator) -> str:
    return " ".join(str(rng.choice(words)) for words in GRID_WORDS)





def viseme_weights(labels: np.ndarray, smoothing_frames: float) -> np.ndarray:
    """(T, n_visemes): one-hot visemes of the frames' phonemes, smoothed in time (coarticulation), on the simplex."""
    one_hot = np.zeros((len(labels), len(NAMES)), np.float32)
    one_hot[np.arange(len(labels)), [NAMES.index(viseme_of(PHONEMES[i])) for i in labels]] = 1
    if smoothing_frames > 0:
        one_hot = gaussian_filter1d(one_hot, smoothing_frames, axis=0, mode="nearest")
    return one_hot / one_hot.sum(1, keepdims=True)


def rigid_jitter(points: np.ndarray, rng: np.random.Generator, degrees: float, scale: float, shift: float):
    """A slow random in-plane rotation, scale and shift over the clip (head motion as a tracker sees it)."""
    t = np.linspace(0, 1, len(points))[:, None]
    a0, a1 = np.radians(rng.uniform(-degrees, degrees, 2))
    ang = a0 + (a1 - a0) * t
    s = 1 + rng.uniform(-scale, scale) * t
    off = rng.uniform(-shift, shift, 2) * t
    c, si = np.cos(ang), np.sin(ang)
    x, y = points[..., 0], points[..., 1]
    return np.stack([s * (c * x - si * y) + off[:, :1], s * (si * x + c * y) + off[:, 1:]], -1)


def speak(voice: str, texts: list[str], wpm: int, pitch: int) -> list:
    """The sentences spoken by one voice: espeak-ng's (name as `espeak-ng --voices` lists it) at `wpm` words per
    minute and `pitch` (0-100), or Festival's ('festival:<voice>', one process for all; its speed follows `wpm`,
    and a diphone voice's F0 `pitch` at 10 per semitone around 50)."""
    if is_festival_voice(voice):
        return Festival(voice, duration_stretch=165.0 / wpm,
                        pitch_factor=2 ** ((pitch - 50) / 120)).synthesize_many(texts)
    tts = Espeak(voice)
    tts.lib.espeak_SetParameter(1, wpm, 0)
    tts.lib.espeak_SetParameter(3, pitch, 0)  # espeakPITCH
    return [tts.synthesize(text) for text in texts]


def build(cfg: DictConfig) -> dict:
    sp = cfg.speech
    rng = np.random.default_rng(int(cfg.seed))
    head = load_head_model(cfg.head_model)
    expr_table, jaw_table = viseme_parameters(head)
    voices = list(sp.voices) or [str(sp.voice)]
    n_speakers, per_speaker = int(cfg.speech.speakers), int(cfg.speech.utterances)
    split_sizes = np.array(sp.split_fractions) * n_speakers
    n_val, n_test = max(1, int(round(split_sizes[1]))), max(1, int(round(split_sizes[2])))
    splits = ["train"] * (n_speakers - n_val - n_test) + ["val"] * n_val + ["test"] * n_test
    audio, frames = [], []
    items = []
    for speaker in range(n_speakers):
        shape = torch.zeros(1, head.n_shape)
        shape[0, :20] = torch.from_numpy(rng.normal(0, 0.7, 20)).float()
        strength = rng.uniform(0.75, 1.25, len(NAMES)).astype(np.float32)
        wpm, pitch = int(rng.integers(140, 190)), int(rng.integers(25, 75))
        voice = voices[speaker % len(voices)]
        texts = [grid_sentence(rng) for _ in range(per_speaker)]
        for text, utt in zip(texts, speak(voice, texts, wpm, pitch)):
            wav = resample(utt.audio, utt.rate, int(sp.sample_rate))
            n = int(np.ceil(len(wav) / sp.sample_rate * FPS))
            labels = frame_labels(utt.phonemes, n)
            weights = viseme_weights(labels, float(sp.coarticulation_frames))
            w = torch.from_numpy(weights * strength[None]).float()
            with torch.no_grad():
                lms = frontal_landmarks(head, shape, w @ expr_table, w @ jaw_table).numpy()
            lms = rigid_jitter(lms, rng, 4.0, 0.05, 0.004) + rng.normal(0, float(sp.landmark_noise_m), lms.shape)
            items.append({"speaker": speaker, "voice": voice, "split": splits[speaker], "text": text,
                          "audio_start": sum(map(len, audio)), "audio_len": len(wav), "frame_start": sum(len(f[0]) for f in frames), "frames": n})
            audio.append(wav)
            frames.append((labels, weights, lms.astype(np.float32)))
    return {"audio": np.concatenate(audio).astype(np.float32), "labels": np.concatenate([f[0] for f in frames]),
            "weights": np.concatenate([f[1] for f in frames]), "landmarks": np.concatenate([f[2] for f in frames]),
            "items": items, "sample_rate": int(sp.sample_rate)}


@entry_point(READS)
def main(cfg, device) -> None:
    corpus = build(cfg)
    items = corpus.pop("items")
    out = Path(cfg.speech.corpus)
    with atomic_path(out) as tmp:
        np.savez_compressed(tmp, **corpus, item_speaker=[i["speaker"] for i in items],
                            item_split=[i["split"] for i in items], item_voice=[i["voice"] for i in items],
                            item_text=[i["text"] for i in items],
                            item_audio_start=[i["audio_start"] for i in items],
                            item_audio_len=[i["audio_len"] for i in items],
                            item_frame_start=[i["frame_start"] for i in items], item_frames=[i["frames"] for i in items],
                            phonemes=PHONEMES, visemes=NAMES)
    seconds = len(corpus["audio"]) / corpus["sample_rate"]
    write_json(out.with_suffix(".json"), {"utterances": len(items), "speakers": len({i["speaker"] for i in items}),
                                          "voices": sorted({i["voice"] for i in items}),
                                          "seconds": seconds, "frames": int(len(corpus["labels"])),
                                          "splits": {s: sum(i["split"] == s for i in items) for s in
                                                     ("train", "val", "test")}})
    log.info("speech corpus: %d utterances, %.0f s of audio, %d frames -> %s", len(items), seconds,
             len(corpus["labels"]), out)


if __name__ == "__main__":
    main()
