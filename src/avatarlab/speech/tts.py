"""Speech with phoneme timings from espeak-ng (Debian's espeak-ng / libespeak-ng1), through its C API by ctypes:
the synthesised audio and, from its phoneme events, when each phoneme starts. This makes a synthetic audio-visual
corpus with exact phoneme alignment on a machine with nothing downloaded.
"""
from __future__ import annotations

import ctypes
import ctypes.util
from dataclasses import dataclass

import numpy as np

EVENT_WORD, EVENT_END, EVENT_MSG_TERMINATED, EVENT_PHONEME = 1, 5, 6, 7
AUDIO_OUTPUT_SYNCHRONOUS = 2
INITIALIZE_PHONEME_EVENTS = 0x0001
CHARS_UTF8 = 1


class _EventId(ctypes.Union):
    _fields_ = [("number", ctypes.c_int), ("name", ctypes.c_char_p), ("string", ctypes.c_char * 8)]


class _Event(ctypes.Structure):
    _fields_ = [("type", ctypes.c_int), ("unique_identifier", ctypes.c_uint), ("text_position", ctypes.c_int),
                ("length", ctypes.c_int), ("audio_position", ctypes.c_int), ("sample", ctypes.c_int),
                ("user_data", ctypes.c_void_p), ("id", _EventId)]


_CALLBACK = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(ctypes.c_short), ctypes.c_int, ctypes.POINTER(_Event))


@dataclass
class Utterance:
    audio: np.ndarray        # float32 mono in [-1, 1]
    rate: int
    phonemes: list[tuple[str, float, float]]  # (espeak mnemonic, start s, end s)
    words: list[tuple[str, float]]            # (word, start s)


class EspeakError(RuntimeError):
    pass


class Espeak:
    """One espeak-ng engine (the library is a process-wide singleton)."""

    _lib = None
    _rate = None

    def __init__(self, voice: str = "en-us", words_per_minute: int = 160):
        if Espeak._lib is None:
            name = ctypes.util.find_library("espeak-ng") or "libespeak-ng.so.1"
            try:
                lib = ctypes.CDLL(name)
            except OSError as err:
                raise EspeakError("libespeak-ng is not installed (Debian: apt-get install espeak-ng)") from err
            rate = lib.espeak_Initialize(AUDIO_OUTPUT_SYNCHRONOUS, 0, None, INITIALIZE_PHONEME_EVENTS)
            if rate <= 0:
                raise EspeakError("espeak_Initialize failed")
            Espeak._lib, Espeak._rate = lib, rate
        self.lib, self.rate = Espeak._lib, Espeak._rate
        if self.lib.espeak_SetVoiceByName(voice.encode()) != 0:
            raise EspeakError(f"espeak-ng has no voice {voice!r}")
        self.lib.espeak_SetParameter(1, int(words_per_minute), 0)  # espeakRATE

    def synthesize(self, text: str) -> Utterance:
        chunks: list[np.ndarray] = []
        events: list[tuple[int, str, int]] = []

        def callback(wav, n, evs):
            if n > 0 and wav:
                chunks.append(np.ctypeslib.as_array(wav, shape=(n,)).copy())
            k = 0
            while evs[k].type != 0:
                ev = evs[k]
                if ev.type == EVENT_PHONEME:
                    events.append((EVENT_PHONEME, ev.id.string.decode("utf-8", "replace"), ev.audio_position))
                elif ev.type == EVENT_WORD:
                    events.append((EVENT_WORD, str(ev.text_position), ev.audio_position))
                k += 1
            return 0

        cb = _CALLBACK(callback)
        self.lib.espeak_SetSynthCallback(cb)
        data = text.encode("utf-8") + b"\0"
        err = self.lib.espeak_Synth(data, ctypes.c_size_t(len(data)), 0, 1, 0, CHARS_UTF8, None, None)
        if err != 0:
            raise EspeakError(f"espeak_Synth failed ({err}) on {text!r}")
        audio = (np.concatenate(chunks) if chunks else np.zeros(0, np.int16)).astype(np.float32) / 32768
        duration = len(audio) / self.rate
        starts = [(name, pos / 1000) for kind, name, pos in events if kind == EVENT_PHONEME and name.strip()]
        phonemes = []
        for k, (name, start) in enumerate(starts):
            end = starts[k + 1][1] if k + 1 < len(starts) else duration
            if end > start:
                phonemes.append((name, start, end))
        tokens = text.split()
        word_starts = [pos / 1000 for kind, _, pos in events if kind == EVENT_WORD]
        words = list(zip(tokens, word_starts))
        return Utterance(audio, self.rate, phonemes, words)
