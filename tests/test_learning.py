"""Each trained model kind must *learn*: at a test-size budget it beats its trivial baselines on held-out data by a
margin several times the seed-to-seed spread measured for it (docs/experiment-log.md, "Learning tests").

These tests fail when learning stops. To see them fail, run them with every learning rate at zero:
    AVATARLAB_TEST_LR_SCALE=0 .venv/bin/python -m pytest tests/test_learning.py
(each then scores at or below its baseline: the untrained interpolator is a cross-fade, the untrained speech model a
still mouth, the untrained head model and avatar a noise-initialised render).
"""
from __future__ import annotations

import inspect
import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import fake_real_set, interp_config, step_cfg

pytestmark = pytest.mark.slow

#: multiplies every learning rate below; 0 must make every test here fail
LR_SCALE = float(os.environ.get("AVATARLAB_TEST_LR_SCALE", "1"))


def drifting_texture(frames: int, size: int, px_per_frame: float, seed: int) -> torch.Tensor:
    """(frames, 3, size, size) in [0, 1]: a smooth random texture panning `px_per_frame` to the left."""
    rng = np.random.default_rng(seed)
    coarse = torch.from_numpy(rng.random((1, 3, 8, 8 + frames // 3))).float()
    wide = torch.nn.functional.interpolate(coarse, size=(size, size + int(frames * px_per_frame) + 4),
                                           mode="bicubic").clamp(0, 1)
    return torch.stack([wide[0, :, :, round(i * px_per_frame):round(i * px_per_frame) + size] for i in range(frames)])


def test_the_interpolator_learns_to_beat_the_cross_fade_on_frames_it_never_saw(tmp_path):
    """XVFI-style network with flows learnt from zero (so the untrained network *is* the cross-fade), 600 steps on
    one panning video, scored on another video's middle frames. Seeds 0-2 (this machine, 2026-12-06): +3.5, +3.9,
    +3.0 dB over the cross-fade (SD 0.4 dB); the margin asked is 1.5 dB."""
    from avatarlab.preprocess.interp.training import train, validation_psnr

    seen, unseen = drifting_texture(40, 32, 2.0, seed=100), drifting_texture(21, 32, 2.0, seed=200)
    triplets = np.stack([np.arange(0, 38), np.arange(1, 39), np.arange(2, 40)], 1)
    cfg = interp_config()
    cfg.interp.update({"flow_init": "zero", "keep_unwarped": False, "width": 16, "scales": 2, "batch": 4,
                       "lr": 1e-3 * LR_SCALE, "iterations": 600, "checkpoint_every": 10**6})
    model, _, _ = train(seen, triplets, cfg, tmp_path / "checkpoint.pt")
    held = np.stack([np.arange(0, 19, 2), np.arange(1, 20, 2), np.arange(2, 21, 2)], 1)
    left, middle, right = (unseen[held[:, k]] for k in range(3))

    def pooled_psnr(prediction: torch.Tensor) -> float:
        return float(10 * torch.log10(1 / (prediction - middle).square().mean()))

    baselines = {"cross_fade": pooled_psnr((left + right) / 2), "copy_left": pooled_psnr(left)}
    score = validation_psnr(model, unseen, held, torch.device("cpu"))
    assert score - max(baselines.values()) > 1.5, (score, baselines)


def test_the_speech_model_learns_to_beat_a_still_mouth_for_speakers_it_never_heard(tmp_path):
    """Seed 000's audio model (its landmark loss alone: lstm_noreg) on a small espeak-ng corpus of 8 speakers, 80
    epochs; the test speaker's mouth motion (lip error, % IOD) against a still mouth. Seeds 0-2: +0.70, +0.71, +0.72
    % IOD (SD 0.01); the margin asked is 0.35. (The regularised model, lstm_reg, collapsed to a still mouth in 2 of 3
    seeds at this budget: docs/experiment-log.md.)"""
    from avatarlab.speech import corpus, train

    overrides = ["scale=smoke", "tracking.enabled=false", "seed=0", f"speech.corpus={tmp_path / 'corpus.npz'}",
                 "speech.speakers=8", "speech.utterances=12", "speech.epochs=80", "speech.augment.copies=0",
                 "speech_model=lstm_noreg", "speech.channels=32", "speech.hidden=64", f"speech.lr={3e-3 * LR_SCALE}",
                 f"speech.out_dir={tmp_path / 'lstm'}",
                 "speech.voices=[en-us,en-us+f3,en-gb-scotland,en-us+m3,en-029+f2,en-us-nyc+f4,en-gb-x-rp+m5]"]
    inspect.unwrap(corpus.main)(step_cfg(corpus, overrides), torch.device("cpu"))
    inspect.unwrap(train.main)(step_cfg(train, overrides), torch.device("cpu"))
    test = json.loads((tmp_path / "lstm" / "metrics.json").read_text())["test"]
    assert test["best_baseline"] == "still_mouth"
    assert test["gain_over_best_baseline"] > 0.35, test


def pretrained_head_model(folder: Path, seed: int = 0):
    """alpha1's recipe (synthetic samples only), 300 iterations at 32x32 of a narrow pose range, the MSE term alone."""
    from avatarlab.pretrain import train as pretrain

    if not (folder / "real").is_dir():
        fake_real_set(folder / "real")
    overrides = NARROW + [f"seed={seed}", "strategy=alpha1", "pretrain.iterations=300",
                          f"pretrain.real_subject_dir={folder / 'real'}", f"pretrain.out_dir={folder / 'alpha1'}",
                          f"pretrain.lr={1e-3 * LR_SCALE}", f"pretrain.renderer_lr={1e-2 * LR_SCALE}",
                          "pretrain.checkpoint_every=1000000"]
    net, _, _ = pretrain.pretrain_model(step_cfg(pretrain, overrides), torch.device("cpu"))
    return net


#: smoke's network at 32x32, poses and cameras in a narrow range (what 300 iterations can learn), the MSE term alone
NARROW = ["scale=smoke", "tracking.enabled=false", "model.image_size=32", "model.feature_size=4",
          "model.w_perceptual=0", "synthetic.neck_deg=[5,5,5]", "synthetic.camera_yaw_deg=2",
          "synthetic.camera_pitch_deg=2"]


@pytest.fixture(scope="module")
def pretrained(tmp_path_factory):
    """(folder holding alpha1/model.pt and the stand-in real set, the network)"""
    folder = tmp_path_factory.mktemp("pretrained")
    return folder, pretrained_head_model(folder)


def test_head_model_pretraining_learns_to_beat_the_mean_colour_and_the_nearest_sample(pretrained):
    """Scored by the evaluation step's own code on 16 held-out head-model renders, beside the mean colour of training
    draws and the training draw nearest in conditioning (64 of them). Training seeds 0-2 (evaluation seed 0):
    +1.59, +1.40, +1.54 dB head-region PSNR over the best baseline (SD 0.10 dB); the margin asked is 0.5 dB."""
    from avatarlab.pretrain import evaluate as evaluation

    folder, net = pretrained
    net.eval()
    cfg = step_cfg(evaluation, NARROW + ["seed=0", f"evaluate.real_subject_dir={folder / 'real'}",
                                         "evaluate.samples=16", "evaluate.baseline_pool=64", "evaluate.st_lpips=false"])
    report, _ = evaluation.score_pretrained(net, 32, cfg, torch.device("cpu"), real_pool=False)
    gain = report["gain"]["psnr_head"]
    assert gain["gain"] > 0.5, (report["model"]["psnr_head"], gain, report["baselines"])


def test_avatar_fine_tuning_learns_to_beat_every_copied_training_frame(pretrained, tmp_path):
    """The base recipe, 300 iterations from that pretrained model, on a 40-frame head-turn video of the head model
    (32x32, its truth as the fit); scored by the evaluation step on the last 8 frames it never saw, beside the mean,
    the last and the nearest training frame. Seeds 0-2: +0.30, +0.38, +0.33 dB PSNR over the best baseline (SD
    0.04 dB); the margin asked is 0.15 dB. (At 500 iterations one seed of three fell below the mean frame: this
    budget is chosen on those runs, not on a validation split, and the test only asks that learning happens.)"""
    from helpers.subjects import rendered_video_subject

    from avatarlab.avatar import evaluate as evaluation
    from avatarlab.avatar import finetune

    folder, _ = pretrained
    subject = rendered_video_subject(tmp_path / "subject", frames=40, size=32, preset="head_turns")
    common = NARROW + ["seed=0", "finetune=base", f"finetune.subject_dir={subject}", "finetune.test_frames=8",
                       f"finetune.out_dir={tmp_path / 'avatar'}"]
    finetune.finetune_avatar(step_cfg(finetune, common + [
        f"finetune.init_model={folder / 'alpha1' / 'model.pt'}", "finetune.iterations=300",
        f"finetune.lr={float(step_cfg(finetune, common).finetune.lr) * LR_SCALE}",
        f"finetune.renderer_lr={float(step_cfg(finetune, common).finetune.renderer_lr) * LR_SCALE}",
        f"finetune.offset_lr={1e-3 * LR_SCALE}"]), torch.device("cpu"))
    cfg = step_cfg(evaluation, common + [f"evaluate.model={tmp_path / 'avatar' / 'model.pt'}",
                                         f"evaluate.out={tmp_path / 'avatar' / 'eval.json'}", "evaluate.st_lpips=false"])
    report, _ = evaluation.evaluate_avatar(cfg, torch.device("cpu"))
    part = report["all"]
    assert part["frames"] == 8 and set(part["baselines"]) == {"mean_frame", "last_frame", "nearest"}
    assert part["gain"]["psnr"]["gain"] > 0.15, (part["model"]["psnr"], part["gain"]["psnr"])
