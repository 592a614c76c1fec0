"""Faults and hostile input, round 3: each case of the probe as a user meets it (docs/troubleshooting.md lists them)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import fake_video_subject, step_cfg
from helpers.subjects import tiny_model_overrides

from avatarlab.data.subject_dir import SubjectDir
from avatarlab.runtime.errors import InputFileError, TrainingError
from avatarlab.runtime.safe_load import load_tensors


@pytest.mark.parametrize("key, index, value", [("expression", (0, 2), math.nan), ("shape", (0,), math.inf),
                                               ("pose", (1, 4), -math.inf)])
def test_a_nan_or_infinity_in_a_fit_stops_its_reader_naming_the_file_and_key(tmp_path, key, index, value):
    subject = fake_video_subject(tmp_path / "s", count=4)
    with np.load(subject / "fit_rgb.npz") as f:
        fit = {k: f[k].copy() for k in f.files}
    fit[key][index] = value
    np.savez(subject / "fit_rgb.npz", **fit)
    with pytest.raises(InputFileError) as err:
        SubjectDir(subject).fit()
    assert str(err.value) == (f"{subject / 'fit_rgb.npz'}: not an RGB fit: '{key}' holds 1 value(s) that are NaN or "
                              "infinite")


def test_a_loss_that_is_not_finite_stops_training_at_its_iteration_and_keeps_the_last_checkpoint(tmp_path, monkeypatch):
    from helpers import fake_real_set

    from avatarlab.pretrain import train as pretrain
    from avatarlab.training import loop

    fake_real_set(tmp_path / "real")
    cfg = step_cfg(pretrain, tiny_model_overrides() + ["strategy=alpha1", "pretrain.iterations=6",
                                                       "pretrain.checkpoint_every=2",
                                                       f"pretrain.real_subject_dir={tmp_path / 'real'}",
                                                       f"pretrain.out_dir={tmp_path / 'alpha1'}"])
    real_step, calls = loop.train_step, {"n": 0}

    def poisoned(*args, **kw):
        calls["n"] += 1
        entry = real_step(*args, **kw)
        return {**entry, "loss": math.nan} if calls["n"] == 5 else entry

    monkeypatch.setattr(loop, "train_step", poisoned)
    with pytest.raises(TrainingError) as err:
        pretrain.pretrain_model(cfg, torch.device("cpu"))
    checkpoint = tmp_path / "alpha1" / "checkpoint.pt"
    assert str(err.value).startswith(f"{tmp_path / 'alpha1'}: training stopped at iteration 5 of 6: the loss is nan")
    assert f"the last checkpoint, of iteration 4, is kept in {checkpoint}" in str(err.value)
    assert load_tensors(checkpoint)["step"] == 4 and not (tmp_path / "alpha1" / "model.pt").exists()


def test_a_half_written_checkpoint_says_how_to_start_over(tmp_path):
    bad = tmp_path / "checkpoint.pt"
    torch.save({"step": 3, "model": {"w": torch.zeros(1000)}}, bad)
    bad.write_bytes(bad.read_bytes()[:200])
    with pytest.raises(InputFileError) as err:
        load_tensors(bad, "a training checkpoint")
    assert str(err.value).startswith(f"{bad}: cannot be read as a training checkpoint: ")
    assert str(err.value).endswith("; delete it to start that step over") and "\n" not in str(err.value)


def test_a_report_shows_no_nan_as_a_number():
    from avatarlab.report.table import Table

    table = Table("t", "t", ["name", "psnr"])
    table.add(name="a", psnr=math.nan)
    table.add(name="b", psnr=None)
    table.add(name="c", psnr=-math.inf)
    assert "nan" not in table.markdown().lower().replace("name", "") and "inf" not in table.csv()
    assert table.markdown().count("not finite") == 2 and "| b | missing |" in table.markdown()
    assert table.csv().splitlines()[1:] == ["a,not finite", "b,", "c,not finite"]


def plan_config(**subjects) -> dict:
    import yaml
    from helpers import REPO

    config = yaml.safe_load((REPO / "workflow" / "config.yaml").read_text())
    config.update(scale="smoke", subjects={"synth_talk": {"source": "synthetic", "preset": "talking", "seed": 1},
                                           **subjects})
    return config


def test_a_subject_named_like_the_real_image_set_is_refused_before_any_job():
    from avatarlab.workflow.targets import Plan

    with pytest.raises(ValueError, match="'subjects': 'portraits' is the real image set's name"):
        Plan(plan_config(portraits={"source": "video", "path": "/tmp/me.mp4"}))


def test_subject_files_whose_names_snakemake_cannot_carry_are_named_at_planning(tmp_path):
    import os

    from avatarlab.workflow.targets import Plan

    (tmp_path / "odd").mkdir()
    with open(os.path.join(os.fsencode(tmp_path / "odd"), b"clip\xff.mp4"), "wb"):
        pass
    with pytest.raises(ValueError, match=r"subject 'me': the file name '.*clip\\\\xff.mp4' is not UTF-8; rename"):
        Plan(plan_config(me={"source": "video", "path": str(tmp_path / "odd" / "*.mp4")}))
    (tmp_path / "braces").mkdir()
    (tmp_path / "braces" / "take{1}.mp4").write_bytes(b"")
    with pytest.raises(ValueError, match=r"the file name '.*take\{1\}.mp4' holds a brace"):
        Plan(plan_config(me={"source": "video", "path": str(tmp_path / "braces" / "*.mp4")}))


def test_a_truncated_mpg_whose_container_declares_no_count_stops_naming_the_file(tmp_path):
    from helpers import SHARED_DATA

    from avatarlab.preprocess.frames import read_video
    from avatarlab.runtime.errors import InputError

    clips = sorted((SHARED_DATA / "grid").glob("*.mpg")) if SHARED_DATA else []
    if not clips:
        pytest.skip("no GRID clips in the shared data")
    frames, _ = read_video(clips[0], None, None)
    assert len(frames) == 75, "an intact clip passes the stream check"
    half = tmp_path / "half.mpg"
    half.write_bytes(clips[0].read_bytes()[: clips[0].stat().st_size // 2])
    with pytest.raises(InputError) as err:
        read_video(half, None, None)
    assert str(err.value).startswith(f"{half}: the video stream is damaged or cut off (ffmpeg: ")
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("size", [(1, 1), (15, 200)])
def test_an_image_too_small_to_hold_a_face_is_refused_by_name(tmp_path, size):
    import cv2

    from avatarlab.preprocess.frames import MIN_SIDE, load_frames
    from avatarlab.runtime.errors import InputError

    folder = tmp_path / "images"
    folder.mkdir()
    cv2.imwrite(str(folder / "a.png"), np.full((64, 64, 3), 128, np.uint8))
    cv2.imwrite(str(folder / "tiny.png"), np.full((size[1], size[0], 3), 128, np.uint8))
    with pytest.raises(InputError) as err:
        load_frames([folder], None, None)
    assert str(err.value) == (f"{folder / 'tiny.png'}: the image is {size[0]}x{size[1]} pixels; at least "
                              f"{MIN_SIDE}x{MIN_SIDE} are needed")


@pytest.mark.parametrize("override, expected", [
    ("scale.crop_size=100000", "preprocess.image_size (set by scale.crop_size): must be at most 4096, got 100000"),
    ("scale.pretrain_feature_size=100000", "model.feature_size (set by scale.pretrain_feature_size): must be at most "
                                           "512, got 100000"),
    ("scale.nerf_samples=5000", "model.samples (set by scale.nerf_samples): must be at most 1024, got 5000"),
    ("pretrain.batch=1000000", "pretrain.batch: must be at most 4096, got 1000000"),
])
def test_every_size_has_an_upper_bound_named_before_any_job(override, expected):
    from helpers import compose_config

    from avatarlab.runtime.schema import problems

    assert expected in problems(compose_config(["scale=smoke", override]))
    for scale in ("smoke", "tiny", "paper"):
        assert problems(compose_config([f"scale={scale}"])) == [], scale


@pytest.mark.parametrize("override", ["hydra.callbacks.pwn._target_=os.system",
                                      "+hydra.callbacks.pwn._target_=builtins.exec", "hydra.run.dir=/tmp/x",
                                      "hydra/launcher=basic"])
def test_a_hydra_setting_in_hydra_overrides_is_refused_aloud(override):
    from helpers import REPO

    from avatarlab.workflow.steps import Steps

    with pytest.raises(ValueError) as err:
        Steps(REPO / "conf", "smoke", "procedural", [override])
    assert str(err.value).startswith(f"workflow config 'hydra_overrides': {override!r} is refused")
    assert Steps(REPO / "conf", "smoke", "procedural", ["pretrain.lr=0.002"]).overrides == ("pretrain.lr=0.002",)


def test_local_cluster_down_removes_only_a_folder_it_made(tmp_path):
    import shutil
    import subprocess
    import tempfile

    from helpers import REPO

    repo = tmp_path / "repo"
    (repo / "cluster").mkdir(parents=True)
    shutil.copy(REPO / "cluster" / "local_cluster.sh", repo / "cluster")
    users = tmp_path / "my_thesis"
    users.mkdir()
    (users / "chapter1.tex").write_text("years of work")
    (repo / ".local_cluster").write_text(f"{users}\n")
    env = {k: v for k, v in __import__("os").environ.items() if k != "AVATARLAB_CLUSTER_DIR"}

    def down():
        return subprocess.run(["bash", str(repo / "cluster" / "local_cluster.sh"), "down"], capture_output=True,
                              text=True, env=env, timeout=60)

    refused = down()
    assert refused.returncode != 0 and (users / "chapter1.tex").read_text() == "years of work"
    assert f"names {users}, a folder this script did not make; nothing removed" in refused.stderr
    made = Path(tempfile.mkdtemp(prefix="avatarlab-cluster.", dir="/tmp"))
    assert len(made.name) == len("avatarlab-cluster.") + 8
    (made / ".made-by-local_cluster").write_text(f"{made}\n")
    (repo / ".local_cluster").write_text(f"{made}\n")
    removed = down()
    assert removed.returncode == 0, removed.stderr
    assert not made.exists() and not (repo / ".local_cluster").exists()


def test_an_interrupted_report_leaves_the_previous_one_whole(tmp_path, monkeypatch):
    from test_report import write_avatar

    from avatarlab.report import build as report

    results, final = tmp_path / "results", "beta6_from_alpha2"
    for k, psnr in enumerate((26.0, 26.4)):
        write_avatar(results, "synth_talk", "final", final + (f"_seed{k}" if k else ""), final, psnr)
    out = results / "report"
    report.build(results, out, final, "smoke")
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert Path("tables/final_avatars.csv") in before and Path("summary.json") in before
    write_avatar(results, "synth_talk", "final", final + "_seed2", final, 30.0)  # new results, then a kill
    real = report.speech_table

    def killed(*a, **k):
        raise KeyboardInterrupt("SIGTERM")

    monkeypatch.setattr(report, "speech_table", killed)
    with pytest.raises(KeyboardInterrupt):
        report.build(results, out, final, "smoke")
    after = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert after == before, "every file of the previous report, byte for byte, and nothing else"
    monkeypatch.setattr(report, "speech_table", real)
    report.build(results, out, final, "smoke")
    assert "| 3 |" in (out / "tables" / "final_avatars.md").read_text() and not (results / ".report.staging").exists()


@pytest.mark.slow
def test_the_venvs_snakemake_runs_steps_without_an_activated_venv(tmp_path):
    """`.venv/bin/snakemake` with a PATH that has no venv (a new shell): the steps still find avatarlab."""
    import os
    import subprocess
    import sys

    from helpers.workflow import snakemake_command

    env = {k: v for k, v in os.environ.items() if k not in ("MLFLOW_TRACKING_URI", "VIRTUAL_ENV")}
    env["PATH"] = "/usr/local/bin:/usr/bin:/bin"
    proc = subprocess.run(snakemake_command(tmp_path, "results/mlflow.ready", "--cores", "1", "--config",
                                            "scale=smoke"), env=env, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (tmp_path / "results" / "mlflow.ready").read_text().startswith("sqlite:///")
    assert str(Path(sys.executable).parent) not in env["PATH"]
