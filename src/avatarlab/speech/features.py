"""Audio features of seed 000: 13 MFCC + 26 log mel filterbank energies + 26 spectral subband centroids = 65 per
analysis frame (python_speech_features, 25 ms frames every 10 ms, 26 filters, at 25 kHz), stacked into one input
window per video frame: 250 ms of frames ending 130 ms after the frame's time (the look-ahead), every 40 ms (25 fps).
"""
from __future__ import annotations

import wave
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.signal import resample_poly

N_FEATURES = 65


@dataclass(frozen=True)
class FeatureSpec:
    sample_rate: int = 25_000
    frame_ms: float = 25.0
    step_ms: float = 10.0
    n_mfcc: int = 13
    n_filters: int = 26
    window_ms: float = 250.0
    hop_ms: float = 40.0
    lookahead_ms: float = 130.0

    @property
    def window_frames(self) -> int:
        return int(round(self.window_ms / self.step_ms))


def read_wav(path: str | Path) -> tuple[np.ndarray, int]:
    """Mono float32 samples in [-1, 1] and the sample rate of a PCM WAV file."""
    path = Path(path)
    try:
        with wave.open(str(path), "rb") as w:
            rate, width, channels, n = w.getframerate(), w.getsampwidth(), w.getnchannels(), w.getnframes()
            raw = w.readframes(n)
    except (wave.Error, EOFError) as err:
        raise ValueError(f"{path}: not a PCM WAV file ({err})") from err
    if width not in (1, 2, 4):
        raise ValueError(f"{path}: {8 * width}-bit samples are not supported (8, 16 or 32-bit PCM)")
    dtype = {1: np.uint8, 2: np.int16, 4: np.int32}[width]
    audio = np.frombuffer(raw, dtype=dtype).astype(np.float32)
    audio = (audio - 128) / 128 if width == 1 else audio / float(2 ** (8 * width - 1))
    audio = audio.reshape(-1, channels).mean(1)
    if len(audio) == 0:
        raise ValueError(f"{path}: no audio samples")
    return audio, rate


def write_wav(path: str | Path, audio: np.ndarray, rate: int) -> None:
    from avatarlab.runtime.io import atomic_path

    pcm = (np.clip(audio, -1, 1) * 32767).round().astype(np.int16)
    with atomic_path(path) as tmp:
        with wave.open(str(tmp), "wb") as w:
            w.setnchannels(1)
            w.setsampwidth(2)
            w.setframerate(rate)
            w.writeframes(pcm.tobytes())


def resample(audio: np.ndarray, rate: int, target: int) -> np.ndarray:
    if rate == target:
        return audio.astype(np.float32)
    g = np.gcd(rate, target)
    return resample_poly(audio, target // g, rate // g).astype(np.float32)


def frame_features(audio: np.ndarray, spec: FeatureSpec = FeatureSpec()) -> np.ndarray:
    """(n_frames, 65) per 10 ms analysis frame: MFCC (13), log filterbank (26), spectral subband centroids (26)."""
    from python_speech_features import logfbank, mfcc, ssc

    kw = {"samplerate": spec.sample_rate, "winlen": spec.frame_ms / 1000, "winstep": spec.step_ms / 1000,
          "nfilt": spec.n_filters, "nfft": 1024}
    signal = audio.astype(np.float64) + 1e-6 * np.random.default_rng(0).standard_normal(len(audio))  # no log(0)
    feats = np.concatenate([mfcc(signal, numcep=spec.n_mfcc, **kw), logfbank(signal, **kw), ssc(signal, **kw)], 1)
    feats[:, -spec.n_filters:] /= spec.sample_rate / 2  # centroids in Hz -> [0, 1] of the Nyquist band
    return feats.astype(np.float32)


def windows(audio: np.ndarray, rate: int, n_video_frames: int | None = None,
            spec: FeatureSpec = FeatureSpec()) -> np.ndarray:
    """(T, window_frames, 65): for video frame t (time t * hop), the analysis frames in
    [t*hop + lookahead - window, t*hop + lookahead); audio before the start or after the end is padded by edge frames."""
    audio = resample(audio, rate, spec.sample_rate)
    feats = frame_features(audio, spec)
    if n_video_frames is None:
        n_video_frames = int(np.ceil(len(audio) / spec.sample_rate * 1000 / spec.hop_ms))
    w = spec.window_frames
    out = np.empty((n_video_frames, w, feats.shape[1]), np.float32)
    for t in range(n_video_frames):
        end = int(round((t * spec.hop_ms + spec.lookahead_ms) / spec.step_ms))
        idx = np.clip(np.arange(end - w, end), 0, len(feats) - 1)
        out[t] = feats[idx]
    return out
