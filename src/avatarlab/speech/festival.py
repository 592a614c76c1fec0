"""Speech with phoneme timings from Festival (Debian's festival with its festvox voices): a second synthesis engine
beside espeak-ng for the synthetic corpus (issue 17, "several synthesis engines and voices"; seed 000 trains on GRID's
recorded speakers, which no package ships).

One `festival -b` process synthesises a batch of sentences with one voice: per sentence a RIFF wave and the segment
file (`utt.save.segs`: each phone's end time in the radio phone set), mapped here to espeak's phoneme mnemonics so
the corpus's viseme table and phoneme labels stay one. No shell: the Scheme script is a temporary file and the
sentence text is written into it as an escaped Scheme string.
"""
from __future__ import annotations

import shutil
import subprocess
import tempfile
import wave
from pathlib import Path

import numpy as np

from avatarlab.runtime.errors import ConfigError
from avatarlab.speech.tts import Utterance

PREFIX = "festival:"
# Debian package of each voice (the error names it); voice name -> package
PACKAGES = {"kal_diphone": "festvox-kallpc16k", "ked_diphone": "festvox-kdlpc16k",
            "cmu_us_slt_arctic_hts": "festvox-us-slt-hts"}
# Festival's radio phone set (US English voices) -> espeak-ng's mnemonics (speech/visemes.py PHONEMES)
RADIO_TO_ESPEAK = {
    "pau": "_", "h#": "_", "brth": "_",
    "aa": "A:", "ae": "a", "ah": "V", "ao": "O:", "aw": "aU", "ax": "@", "axr": "3:", "ay": "aI", "eh": "E",
    "er": "3:", "ey": "eI", "ih": "I", "ix": "I", "iy": "i:", "ow": "oU", "oy": "OI", "uh": "U", "uw": "u:",
    "b": "b", "ch": "tS", "d": "d", "dh": "D", "dx": "t", "el": "@L", "em": "m", "en": "n", "f": "f", "g": "g",
    "hh": "h", "hv": "h", "jh": "dZ", "k": "k", "l": "l", "m": "m", "n": "n", "nx": "n", "ng": "N", "p": "p",
    "r": "r", "s": "s", "sh": "S", "t": "t", "th": "T", "v": "v", "w": "w", "y": "j", "z": "z", "zh": "Z",
}


class FestivalError(ConfigError):
    """Festival or one of its voices is not installed, or it failed on a sentence (one line)."""


def is_festival_voice(voice: str) -> bool:
    return voice.startswith(PREFIX)


def scheme_string(text: str) -> str:
    """`text` as a Scheme string literal: backslashes and double quotes escaped, control characters dropped."""
    clean = "".join(c for c in text if c.isprintable())
    return '"' + clean.replace("\\", "\\\\").replace('"', '\\"') + '"'


def read_segments(path: Path) -> list[tuple[str, float, float]]:
    """An xlabel segment file (header, '#', then 'end_time colour phone' lines) -> [(espeak mnemonic, start, end)]."""
    lines = path.read_text().splitlines()
    body = lines[lines.index("#") + 1:] if "#" in lines else lines
    phones, start = [], 0.0
    for line in body:
        parts = line.split()
        if len(parts) < 3:
            continue
        end, name = float(parts[0]), parts[2]
        if name not in RADIO_TO_ESPEAK:
            raise FestivalError(f"{path}: phone {name!r} is not in the radio phone set this module maps")
        if end > start:
            phones.append((RADIO_TO_ESPEAK[name], start, end))
        start = max(start, end)
    return phones


def read_wave(path: Path) -> tuple[np.ndarray, int]:
    with wave.open(str(path), "rb") as w:
        if w.getsampwidth() != 2:
            raise FestivalError(f"{path}: expected 16-bit samples, got {8 * w.getsampwidth()}-bit")
        data = np.frombuffer(w.readframes(w.getnframes()), np.int16).reshape(-1, w.getnchannels())
        return data.mean(1).astype(np.float32) / 32768, w.getframerate()


class Festival:
    """Festival with one voice ('festival:kal_diphone' or 'kal_diphone'). `duration_stretch` > 1 speaks slower
    (diphone voices: Festival's Duration_Stretch; HTS voices: hts_engine's speed rate, its inverse); `pitch_factor`
    scales a diphone voice's target F0 mean (its intonation model's; Festival's HTS module takes no pitch shift, so
    an HTS voice keeps its own)."""

    def __init__(self, voice: str, duration_stretch: float = 1.0, pitch_factor: float = 1.0,
                 timeout_s: float = 120.0):
        self.voice = voice[len(PREFIX):] if is_festival_voice(voice) else voice
        if not self.voice.replace("_", "").isalnum():
            raise FestivalError(f"festival voice {voice!r}: a voice name is letters, digits and '_'")
        self.binary = shutil.which("festival")
        if self.binary is None:
            raise FestivalError(f"festival voice {voice!r}: festival is not installed (Debian: apt-get install "
                                f"festival {PACKAGES.get(self.voice, 'festvox-...')})")
        self.stretch, self.pitch, self.timeout = float(duration_stretch), float(pitch_factor), float(timeout_s)
        if not (0.25 <= self.stretch <= 4 and 0.25 <= self.pitch <= 4):
            raise FestivalError(f"festival voice {voice!r}: duration stretch {self.stretch} and pitch factor "
                                f"{self.pitch} must lie in [0.25, 4]")

    def voice_setup(self) -> list[str]:
        """The Scheme lines that select the voice and set its speed (and pitch)."""
        lines = [f"(voice_{self.voice})"]
        if self.voice.endswith("_hts"):
            return lines + [f'(set! hts_engine_params (append hts_engine_params (list (list "-r" '
                            f'{1 / self.stretch:.4f}))))']
        return lines + [f"(Parameter.set 'Duration_Stretch {self.stretch:.4f})",
                        "(if (assoc 'target_f0_mean int_lr_params) (set! int_lr_params (cons (list 'target_f0_mean "
                        f"(* {self.pitch:.4f} (cadr (assoc 'target_f0_mean int_lr_params)))) int_lr_params)))"]

    def synthesize_many(self, texts: list[str]) -> list[Utterance]:
        with tempfile.TemporaryDirectory(prefix="festival-") as tmp:
            folder = Path(tmp)
            lines = self.voice_setup()
            for i, text in enumerate(texts):
                lines += [f"(set! utt (SynthText {scheme_string(text)}))",
                          f"(utt.save.wave utt {scheme_string(str(folder / f'{i}.wav'))} 'riff)",
                          f"(utt.save.segs utt {scheme_string(str(folder / f'{i}.segs'))})"]
            script = folder / "synth.scm"
            script.write_text("\n".join(lines) + "\n")
            run = subprocess.run([self.binary, "-b", str(script)], capture_output=True, text=True,
                                 timeout=self.timeout, check=False)
            missing = [i for i in range(len(texts)) if not (folder / f"{i}.wav").exists()]
            if run.returncode != 0 or missing:
                detail = " ".join((run.stderr or run.stdout).split())[:200]
                if "voice_" in detail or "unbound variable" in detail:
                    detail = (f"no voice {self.voice!r} (Debian: apt-get install "
                              f"{PACKAGES.get(self.voice, 'its festvox package')})")
                raise FestivalError(f"festival voice {self.voice!r} failed: {detail}")
            out = []
            for i in range(len(texts)):
                audio, rate = read_wave(folder / f"{i}.wav")
                out.append(Utterance(audio, rate, read_segments(folder / f"{i}.segs"), []))
            return out

    def synthesize(self, text: str) -> Utterance:
        return self.synthesize_many([text])[0]
