"""Audio -> avatar video: a WAV drives a subject's avatar through the seed-000 model.

The audio's 65 features per 40 ms step give viseme weights; the weights mix the visemes' expression and jaw
parameters (the head model's space, speech/visemes.py); the avatar renders them on the subject's identity, pose and
camera of its first test frame. Writes an MP4 at 25 fps with the audio muxed in (ffmpeg from imageio-ffmpeg; without
it the video is silent and the log says so), plus a PNG strip and a JSON.
`python -m avatarlab.speech.animate speech.wav=in.wav speech.animate_model=.../lstm_reg/model.pt apps.avatar=... apps.out=out.mp4`
Also `python -m avatarlab.speech.animate speech.say="bin blue at f two now" ...` to speak text with espeak-ng first.
"""
from __future__ import annotations

import logging
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import torch

from avatarlab.headmodel import load_head_model
from avatarlab.model.avatar import load_avatar, load_fit, select, to_uint8
from avatarlab.runtime.entry import entry_point
from avatarlab.runtime.io import atomic_path, write_json, write_png, write_video
from avatarlab.speech.features import FeatureSpec, read_wav, windows, write_wav
from avatarlab.speech.models import load_speech_model
from avatarlab.speech.visemes import NAMES, viseme_parameters

log = logging.getLogger(__name__)
READS = ('seed', 'head_model', 'speech', 'apps')  # the config sections this step reads (runtime/entry.py)





def mux_audio(video: Path, wav: Path, out: Path) -> bool:
    try:
        import imageio_ffmpeg

        ffmpeg = imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError):
        ffmpeg = shutil.which("ffmpeg")
    if not ffmpeg:
        return False
    with atomic_path(out) as tmp:
        proc = subprocess.run([ffmpeg, "-y", "-loglevel", "error", "-i", str(video), "-i", str(wav), "-c:v", "copy",
                               "-c:a", "aac", "-shortest", "-f", "mp4", str(tmp)], capture_output=True, text=True)
        if proc.returncode != 0:
            raise RuntimeError(f"{out}: ffmpeg could not mux the audio: {proc.stderr.strip()[-300:]}")
    return True


@entry_point(READS)
def main(cfg, device) -> None:
    sp, apps = cfg.speech, cfg.apps
    out = Path(apps.out)
    wav = Path(sp.wav) if sp.get("wav") else out.with_suffix(".wav")
    if sp.get("say"):
        from avatarlab.speech.tts import Espeak

        utt = Espeak(sp.voice).synthesize(str(sp.say))
        write_wav(wav, utt.audio, utt.rate)
    audio, rate = read_wav(wav)
    head = load_head_model(cfg.head_model)
    model = load_speech_model(sp.animate_model, head, device)
    spec = FeatureSpec(sample_rate=int(sp.sample_rate))
    x = torch.from_numpy(windows(audio, rate, None, spec))[None].to(device)
    with torch.no_grad():
        weights = model(x)[0].cpu()
    expr_table, jaw_table = viseme_parameters(head)
    weights = weights[0]
    avatar = load_avatar(apps.avatar, device)
    fit = load_fit(apps.subject_dir, avatar.image_size)
    frame = int(torch.nonzero(fit["fitted"]).flatten()[-1])
    params, camera = select(fit, [frame] * len(weights))
    params["expression"] = params["expression"] + weights @ expr_table
    params["pose"][:, 6] = weights @ jaw_table
    start = time.perf_counter()
    frames = to_uint8(avatar.render(params, camera))
    seconds = (time.perf_counter() - start) / len(frames)
    silent = out.with_name(out.stem + ".silent.mp4")
    write_video(silent, frames, 1000.0 / spec.hop_ms)
    with_audio = mux_audio(silent, wav, out)
    if with_audio:
        silent.unlink()
    else:
        silent.replace(out)
        log.warning("no ffmpeg: %s has no sound track", out)
    show = np.linspace(0, len(frames) - 1, min(8, len(frames))).round().astype(int)
    write_png(out.with_suffix(".png"), np.concatenate(list(frames[show]), 1))
    jaw = (weights @ jaw_table).numpy()
    write_json(out.with_suffix(".json"), {
        "wav": str(wav), "audio_seconds": len(audio) / rate, "frames": len(frames), "fps": 1000.0 / spec.hop_ms,
        "with_audio": with_audio, "render_seconds_per_frame": seconds, "jaw_rad_mean": float(jaw.mean()),
        "jaw_rad_max": float(jaw.max()), "dominant_visemes": [NAMES[i] for i in weights.argmax(-1).tolist()]})
    log.info("%s: %d frames from %.1f s of audio (jaw opening up to %.2f rad)%s", out, len(frames),
             len(audio) / rate, jaw.max(), "" if with_audio else " - silent")


if __name__ == "__main__":
    main()
