"""Audio augmentation that moves the synthetic corpus's clean espeak-ng audio towards a real recording (issue 17,
"real voices"): a random channel (band-limited by a low-pass and a high-pass filter), room reverberation (an
exponentially decaying noise impulse response of a random RT60, mixed with the direct sound), additive noise (white
or low-frequency-weighted) at a random signal-to-noise ratio, and a random gain. The labels stay valid: nothing here
moves the audio in time.
"""
from __future__ import annotations

import numpy as np
from scipy.signal import butter, fftconvolve, lfilter

from avatarlab.runtime.errors import ConfigError

RANGES = ("lowpass_hz", "highpass_hz", "rt60_s", "drr_db", "snr_db", "gain")


def check_settings(settings) -> None:
    """One line naming what is wrong with conf `speech.augment` (copies, reverb_probability and [low, high] ranges)."""
    missing = [k for k in ("copies", "reverb_probability", *RANGES) if k not in settings]
    if missing:
        raise ConfigError(f"speech.augment: missing {', '.join(missing)}")
    bad = [k for k in RANGES if len(settings[k]) != 2 or float(settings[k][0]) > float(settings[k][1])]
    if bad or int(settings.copies) < 0 or not 0 <= float(settings.reverb_probability) <= 1:
        raise ConfigError(f"speech.augment: {', '.join(bad) or 'copies / reverb_probability'} out of range "
                          "(ranges are [low, high]; copies >= 0; reverb_probability in [0, 1])")


def reverberate(audio: np.ndarray, rate: int, rt60_s: float, drr_db: float, rng: np.random.Generator) -> np.ndarray:
    """`audio` through a room: the direct path plus a noise tail decaying by 60 dB in rt60_s, whose energy is
    `drr_db` below the direct sound's (the direct-to-reverberant ratio); the peak level is kept."""
    n = max(2, int(rt60_s * rate))
    tail = rng.standard_normal(n - 1) * np.exp(-6.9 * np.arange(1, n) / n)
    tail *= np.sqrt(10 ** (-drr_db / 10) / (np.sum(tail ** 2) + 1e-12))
    ir = np.concatenate([[1.0], tail])
    wet = fftconvolve(audio, ir)[:len(audio)]
    return wet * (np.abs(audio).max() / (np.abs(wet).max() + 1e-12))


def add_noise(audio: np.ndarray, snr_db: float, rng: np.random.Generator, coloured: bool) -> np.ndarray:
    """`audio` plus white (or, if coloured, first-order low-pass: rumble, hum-like) noise at `snr_db`."""
    noise = rng.standard_normal(len(audio))
    if coloured:
        noise = lfilter([1.0], [1.0, -0.95], noise)
    power = np.mean(audio.astype(np.float64) ** 2) + 1e-12
    noise *= np.sqrt(power / 10 ** (snr_db / 10) / (np.mean(noise ** 2) + 1e-12))
    return audio + noise


def augment(audio: np.ndarray, rate: int, rng: np.random.Generator, settings) -> np.ndarray:
    """One random real-recording-like version of `audio` (float samples at `rate`), drawn with `rng` from the ranges
    of `settings` (conf `speech.augment`: lowpass_hz, highpass_hz, reverb_probability, rt60_s, drr_db, snr_db,
    gain)."""
    nyquist = rate / 2
    x = audio.astype(np.float64)
    low = min(rng.uniform(*settings.lowpass_hz), 0.95 * nyquist)
    b, a = butter(2, low / nyquist, "low")
    x = lfilter(b, a, x)
    b, a = butter(1, rng.uniform(*settings.highpass_hz) / nyquist, "high")
    x = lfilter(b, a, x)
    if rng.random() < float(settings.reverb_probability):
        x = reverberate(x, rate, rng.uniform(*settings.rt60_s), rng.uniform(*settings.drr_db), rng)
    x = add_noise(x, rng.uniform(*settings.snr_db), rng, coloured=bool(rng.random() < 0.5))
    return (x * rng.uniform(*settings.gain)).astype(np.float32)
