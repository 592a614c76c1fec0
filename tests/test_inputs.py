"""Bad input is judged where it enters and reported in one line naming the culprit; nothing is run from a file."""
import json
import os
import subprocess
import sys

import cv2
import numpy as np
import pytest
import torch
from helpers import compose_config

from avatarlab.preprocess.frames import read_video
from avatarlab.runtime.errors import ConfigError, InputError, InputFileError
from avatarlab.runtime.safe_load import load_arrays, load_tensors
from avatarlab.runtime.schema import problems, validate


class Payload:
    """Pickling this runs os.system on load: what a crafted model file would do."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_a_crafted_checkpoint_is_refused_in_one_line_and_its_payload_never_runs(tmp_path):
    from avatarlab.model.head_nerf import load_model_file

    marker = tmp_path / "PWNED"
    bad = tmp_path / "model.pt"
    torch.save({"format": "avatarlab.head_nerf/1", "spec": Payload(marker)}, bad)
    with pytest.raises(InputFileError) as err:
        load_model_file(bad)
    message = str(err.value)
    assert message.startswith(f"{bad}: cannot be read as a head model") and "\n" not in message
    assert "could run code" in message and not marker.exists()
    with pytest.raises(InputFileError, match="a training checkpoint"):
        load_tensors(bad, "a training checkpoint")
    assert not marker.exists()


def test_a_pickled_array_file_is_refused_with_its_name(tmp_path):
    bad = tmp_path / "landmarks.npz"
    np.savez(bad, points=np.array([{"a": 1}], dtype=object), found=np.ones(1, bool))
    with pytest.raises(InputFileError, match="landmarks.npz: cannot be read as landmarks.*pickled"):
        load_arrays(bad, ("points", "found"), "landmarks")
    with pytest.raises(InputFileError, match="missing found"):
        np.savez(bad, points=np.zeros((1, 68, 2)))
        load_arrays(bad, ("points", "found"), "landmarks")


def test_wrong_types_and_sizes_are_named_before_anything_runs():
    found = problems(compose_config(["pretrain.lr=abc", "scale.nerf_width=-3", "model.renderer=fancy"]))
    assert "pretrain.lr: expected a number, got 'abc'" in found
    assert "model.width (set by scale.nerf_width): must be at least 1, got -3" in found
    assert "model.renderer: expected one of proposed, baseline, got 'fancy'" in found
    for scale in ("smoke", "tiny", "paper"):
        for variant in ([], ["finetune=base"], ["strategy=beta6"], ["experiment=renderer"], ["speech_model=window"]):
            validate(compose_config([f"scale={scale}", *variant]))  # the shipped configs are valid
    with pytest.raises(ConfigError, match="invalid settings: finetune.test_frames: must be at least 1"):
        validate(compose_config(["finetune.test_frames=0"]))


def write_video(path, frames: int, size: int = 64):
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 25, (size, size))
    for i in range(frames):
        writer.write(np.full((size, size, 3), i * 5 % 255, np.uint8))
    writer.release()


def test_a_truncated_video_stops_with_the_counts(tmp_path):
    path = tmp_path / "clip.mp4"
    write_video(path, 40)
    data = path.read_bytes()
    frames, _ = read_video(path, None, None)
    assert len(frames) == 40
    moov_last = data.rfind(b"moov") > data.rfind(b"mdat")
    if not moov_last:
        pytest.skip("this OpenCV writes the index first; truncation would leave no readable header")
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(data[:len(data) // 3])
    with pytest.raises(InputError) as err:
        read_video(cut, None, None)
    assert str(err.value).startswith(f"{cut}: ") and "\n" not in str(err.value)


def run_step(module, *overrides, cwd=None):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    return subprocess.run([sys.executable, "-m", module, *overrides], capture_output=True, text=True, env=env,
                          cwd=cwd, timeout=600)


@pytest.mark.slow
def test_a_video_without_a_face_stops_in_the_landmark_step_in_one_line(tmp_path):
    subject = tmp_path / "results" / "smoke" / "subjects" / "plain"
    write_video(tmp_path / "plain.mp4", 20)
    common = ["scale=smoke", f"paths.results={tmp_path / 'results'}", f"preprocess.subject_dir={subject}",
              f"hydra.run.dir={tmp_path / 'hydra'}"]
    frames = run_step("avatarlab.preprocess.frames", *common, f"preprocess.inputs=[{tmp_path / 'plain.mp4'}]",
                      "preprocess.crop_margin=0")
    assert frames.returncode == 0, frames.stderr[-2000:]
    landmarks = run_step("avatarlab.preprocess.track_landmarks", *common)
    assert landmarks.returncode == 2
    line = landmarks.stderr.strip().splitlines()[-1]
    assert line.startswith("avatarlab error: subject plain: dlib finds a face in 0 of 12 frames (0%) of ")
    assert "plain.mp4" in line and "preprocess.min_face_share" in line and "Traceback" not in landmarks.stderr
    assert (subject / "frames.json").is_file(), "what was computed before stays"


@pytest.mark.slow
def test_a_setting_of_the_wrong_type_stops_a_step_in_one_line(tmp_path):
    proc = run_step("avatarlab.pretrain.train", "scale=smoke", "pretrain.lr=abc", f"hydra.run.dir={tmp_path}")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == "avatarlab error: invalid settings: pretrain.lr: expected a " \
                                                   "number, got 'abc'"
    json.dumps(proc.stderr)
