"""The wall between choosing and scoring: test frames are read by evaluation alone (issue 47).

At the fine-tuning step: replace every test frame of a subject (its image, mask, landmarks and fitted expression and
pose) with noise, and the trained weights, the chosen snapshot and everything the step writes are bit-identical; only
the evaluation changes. At the RGB fit: noise in the test and validation frames leaves the identity (shape, texture,
focal length, lighting) and every training frame's fit bit-identical; only the held-out frames' own expression, pose
and camera change (they are the test input that drives the avatar).
"""
from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
import torch
from helpers import step_cfg
from helpers.subjects import fake_video_subject, tiny_model_overrides
from PIL import Image


@pytest.fixture(scope="module")
def parent(tmp_path_factory):
    from helpers import fake_real_set

    from avatarlab.pretrain import train as pretrain

    folder = tmp_path_factory.mktemp("parent")
    fake_real_set(folder / "portraits")
    cfg = step_cfg(pretrain, tiny_model_overrides() + [f"pretrain.out_dir={folder / 'alpha1'}",
                                                       f"pretrain.real_subject_dir={folder / 'portraits'}"])
    pretrain.pretrain_model(cfg, torch.device("cpu"))
    return folder / "alpha1" / "model.pt"


def noise_the_test_frames(subject, test: list[int]) -> None:
    rng = np.random.default_rng(7)
    frames = json.loads((subject / "frames.json").read_text())["files"]
    for i in test:
        size = Image.open(subject / "frames" / frames[i]).size
        Image.fromarray((rng.random((size[1], size[0], 3)) * 255).astype(np.uint8)).save(subject / "frames" / frames[i])
    with np.load(subject / "masks.npz") as m:
        masks = m["masks"].copy()
    masks[test] = rng.random(masks[test].shape) > 0.5
    np.savez(subject / "masks.npz", masks=masks)
    with np.load(subject / "landmarks.npz") as m:
        points, found = m["points"].copy(), m["found"]
    points[test] += rng.normal(0, 5, points[test].shape)
    np.savez(subject / "landmarks.npz", points=points, found=found)
    with np.load(subject / "fit_rgb.npz") as f:
        fit = {k: f[k].copy() for k in f.files}
    for key in ("expression", "pose"):
        fit[key][test] += rng.normal(0, 0.5, fit[key][test].shape).astype(fit[key].dtype)
    np.savez(subject / "fit_rgb.npz", **fit)


def digests(folder) -> dict[str, str]:
    """Every file the fine-tuning step wrote, by content (train.json without its wall-clock seconds)."""
    out = {}
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        data = path.read_bytes()
        if path.name == "train.json":
            report = json.loads(data)
            for key in ("train_seconds", "seconds", "samples_per_second"):
                report.pop(key, None)
            for key in ("history", "validation_scores"):  # their wall-clock seconds aside
                report[key] = [{k: v for k, v in h.items() if k != "seconds"} for h in report.get(key) or []]
            data = json.dumps(report, sort_keys=True).encode()
        if path.suffix == ".pt":  # the weights and the iterations (its config names the subject's folder)
            content = torch.load(path, weights_only=True)
            weights = content["state"]
            assert weights, path
            data = b"".join(t.numpy().tobytes() for t in weights.values()) + repr(
                (content.get("step"), content.get("trained_to"))).encode()
        out[str(path.relative_to(folder))] = hashlib.sha256(data).hexdigest()
    return out


@pytest.mark.slow
def test_noise_in_the_test_frames_changes_the_scores_and_nothing_before_them(tmp_path, parent):
    from avatarlab.avatar import evaluate as evaluation
    from avatarlab.avatar import finetune

    runs = {}
    for name in ("clean", "noised"):
        subject = fake_video_subject(tmp_path / name / "subject", count=10)
        out = tmp_path / name / "avatar"
        common = tiny_model_overrides() + [f"finetune.subject_dir={subject}", "finetune.test_frames=2",
                                           "finetune.validation_frames=2", f"finetune.out_dir={out}",
                                           "tracking.enabled=false"]
        if name == "noised":
            noise_the_test_frames(subject, [8, 9])
        _, _, report = finetune.finetune_avatar(step_cfg(finetune, common + [f"finetune.init_model={parent}",
                                                                              "finetune.iterations=4"]),
                                                torch.device("cpu"))
        assert report["test_indices"] == [8, 9]
        written = digests(out)
        cfg = step_cfg(evaluation, common + [f"evaluate.model={out / 'model.pt'}", f"evaluate.out={out / 'eval.json'}",
                                             "evaluate.st_lpips=false"])
        scores, _ = evaluation.evaluate_avatar(cfg, torch.device("cpu"))
        chosen_on = [(c["step"], c["psnr"]) for c in report["validation_scores"]]
        runs[name] = (written, report["chosen_step"], chosen_on, scores["all"]["model"]["psnr"])
    clean, noised = runs["clean"], runs["noised"]
    assert clean[0] == noised[0], "every file the fine-tuning step wrote is the same, byte for byte"
    assert clean[1] == noised[1] and clean[2] == noised[2], "the same snapshot chosen on the same validation scores"
    assert clean[3] != pytest.approx(noised[3], abs=1e-3), "only the evaluation sees the test frames"


@pytest.mark.parametrize("clips", [None, [0] * 6 + [1] * 4 + [2] * 3 + [3] * 3], ids=["last_frames", "held_out_clips"])
def test_noise_in_the_held_out_frames_leaves_the_identity_fit_unchanged(clips):
    from helpers import compose_config

    from avatarlab.preprocess.fit_rgb import fit_video, identity_frames
    from avatarlab.preprocess.synthetic_subject import render_subject

    clip_overrides = ["fit_rgb.held_out.test_clips=1", "fit_rgb.held_out.validation_clips=1",
                      "fit_rgb.lighting_per_clip=true"] if clips else \
        ["fit_rgb.held_out.test_frames=4", "fit_rgb.held_out.validation_frames=2", "fit_rgb.lighting_per_clip=false"]
    cfg = compose_config(["scale=smoke", "scale.subject_frames=16", "scale.fit_keyframe_iterations=30",
                          "scale.fit_frame_iterations=15",
                          *clip_overrides])
    truth = render_subject(cfg)
    frames, landmarks, masks = truth["video"], truth["landmarks2d"], truth["masks"]
    clips = None if clips is None else np.array(clips)
    seen = identity_frames(cfg.fit_rgb, clips, len(frames))
    if clips is None:
        assert seen.sum() == 10
    else:  # and smoke's finetune.recording_test_frames (1): the last frame of each training clip is a test frame too
        assert seen.sum() == 8 and not seen[[5, 9]].any()
    found = np.ones(len(frames), bool)

    def fit(video, points, mask):
        torch.manual_seed(0)
        _, _, shared, result, fitted, key, *_ = fit_video(cfg, video, points, found, mask, clips=clips)
        assert seen[key].all() and fitted.all()
        return shared, result

    rng = np.random.default_rng(3)
    video, points, mask = frames.copy(), landmarks.copy(), masks.copy()
    video[~seen] = rng.integers(0, 256, video[~seen].shape, dtype=np.uint8)
    points[~seen] += rng.normal(0, 3, points[~seen].shape)
    mask[~seen] = rng.random(mask[~seen].shape) > 0.5
    (shared, result), (noisy_shared, noisy_result) = fit(frames, landmarks, masks), fit(video, points, mask)
    for key in ("shape", "texture", "focal"):
        assert torch.equal(shared[key], noisy_shared[key]), key
    # the lighting: shared, or with held-out clips one per clip, each training clip's from its open frames alone
    lit, noisy_lit = shared["lighting"], noisy_shared["lighting"]
    assert torch.equal(lit[seen] if lit.shape[0] == len(frames) else lit,
                       noisy_lit[seen] if noisy_lit.shape[0] == len(frames) else noisy_lit)
    if clips is not None:
        assert lit.shape[0] == len(frames) and not torch.equal(lit[~seen], noisy_lit[~seen]), "per-clip lighting"
    for key in ("expression", "pose", "rot", "trans"):
        assert torch.equal(result[key][seen], noisy_result[key][seen]), key
    assert not torch.equal(result["expression"][~seen], noisy_result["expression"][~seen])


def test_a_video_fit_holds_each_frames_expression_under_its_own_prior():
    """fit_rgb.video_expression_reg: video mode fits every frame's 50 expression coefficients under that prior (a
    frame fitted alone otherwise wanders in all of them); images mode keeps weights.expression_reg. A stronger prior
    gives smaller codes on the same frames."""
    from helpers import compose_config

    from avatarlab.preprocess.fit_rgb import fit_video
    from avatarlab.preprocess.synthetic_subject import render_subject

    base = ["scale=smoke", "scale.subject_frames=8", "fit_rgb.lighting_per_clip=false",
            "scale.fit_keyframe_iterations=10", "scale.fit_frame_iterations=10", "scale.fit_rigid_iterations=5",
            "scale.fit_frame_rigid_iterations=5", "fit_rgb.held_out.test_frames=2",
            "fit_rgb.held_out.validation_frames=1"]
    truth = render_subject(compose_config(base))
    found = np.ones(len(truth["video"]), bool)
    size = {}
    for mode, prior in (("video", 1e-4), ("video", 1.0), ("images", 1.0)):
        cfg = compose_config(base + [f"fit_rgb.mode={mode}", f"fit_rgb.video_expression_reg={prior}"])
        torch.manual_seed(0)
        _, fitter, _, result, fitted, *_ = fit_video(cfg, truth["video"], truth["landmarks2d"], found, truth["masks"])
        expected = prior if mode == "video" else float(cfg.fit_rgb.weights.expression_reg)
        assert fitter.weights.expression_reg == pytest.approx(expected)
        size[(mode, prior)] = float(result["expression"][fitted].norm(dim=1).mean())
    assert size[("video", 1.0)] < 0.5 * size[("video", 1e-4)], size
