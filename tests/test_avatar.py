import dataclasses
import json
import math

import numpy as np
import pytest
import torch
from helpers import fake_real_set, fake_video_subject, step_cfg
from helpers.subjects import tiny_model_overrides
from helpers.training import killed_at_optimizer_step

from avatarlab.data.splits import mouth_open_subset, subject_split
from avatarlab.metrics import baselines
from avatarlab.metrics.quality import (
    LPIPS,
    STLPIPS,
    colour_matched,
    face_metrics,
    identity_similarity,
    load_backbone,
    lpips_metric,
    psnr,
    psnr_colour_matched,
    psnr_in_mask,
    ssim,
)
from avatarlab.metrics.scoring import gains
from avatarlab.runtime.entry import InputError
from avatarlab.runtime.safe_load import InputFileError


def test_split_keeps_the_last_frames_for_testing():
    fitted = np.ones(20, bool)
    fitted[3] = fitted[18] = False
    split = subject_split(fitted, np.zeros(20, int), 5)
    assert list(split.test) == [15, 16, 17, 19] and 3 not in split.train and max(split.train) == 14
    assert split.protocol == "last_frames"
    b = subject_split(np.ones(20, bool), np.zeros(20, int), 5, variant="b")
    assert list(b.train) == list(range(0, 15, 2))
    c = subject_split(np.ones(20, bool), np.zeros(20, int), 5, variant="c", interpolated=[1, 3, 5])
    assert list(c.train) == sorted(list(range(0, 15, 2)) + [1, 3, 5])


def test_split_can_hold_out_whole_clips():
    clips = np.repeat([0, 1, 2], 4)
    split = subject_split(np.ones(12, bool), clips, test_frames=3, test_clips=1)
    assert list(split.test) == [8, 9, 10, 11] and list(split.train) == list(range(8))
    assert split.protocol == "held_out_clips"
    with pytest.raises(InputError, match="1 clip"):
        subject_split(np.ones(4, bool), np.zeros(4, int), 1, test_clips=1, source="frames.json")


def test_the_last_frames_of_each_training_clip_are_a_test_set_of_their_own():
    """finetune.recording_test_frames: with held-out clips, the last frames of every training clip are held out of
    training and scored apart (a later moment of a recording it trained on); each clip keeps its first frame; the
    preprocessing's wall (held_out) counts them as test frames; the last-frames protocol ignores the setting."""
    from avatarlab.data.splits import held_out

    clips = np.repeat([0, 1, 2, 3], [5, 1, 3, 3])  # clip 2 validation, clip 3 test
    fitted = np.ones(12, bool)
    fitted[4] = False
    split = subject_split(fitted, clips, 3, test_clips=1, validation_clips=1, recording_test_frames=2)
    assert list(split.recording) == [3] and list(split.test) == [9, 10, 11] and list(split.validation) == [6, 7, 8]
    assert list(split.train) == [0, 1, 2, 5], "clip 1's only frame stays a training frame"
    assert list(split.seen) == [0, 1, 2, 5, 6, 7, 8], "the baselines never copy a same-recording test frame"
    in_test, in_validation, protocol = held_out(clips, 3, 1, 0, 1, recording_test_frames=2)
    assert list(np.nonzero(in_test)[0]) == [3, 4, 9, 10, 11] and protocol == "held_out_clips"
    plain = subject_split(np.ones(12, bool), clips, 3, test_clips=1, validation_clips=1)
    assert len(plain.recording) == 0 and list(plain.train) == [0, 1, 2, 3, 4, 5]
    last = subject_split(np.ones(20, bool), np.repeat([0, 1], 10), 5, recording_test_frames=2)
    assert len(last.recording) == 0 and list(last.train) == list(range(15))
    assert list(np.nonzero(held_out(np.repeat([0, 1], 10), 5, recording_test_frames=2)[0])[0]) == list(range(15, 20))
    # the last-frame baseline of a same-recording frame is its clip's last training frame, of a test clip's frame
    # the last frame seen (a validation frame here), of a frame before everything seen the last frame seen
    from avatarlab.avatar.evaluate import last_seen_before

    seen = split.seen[::-1].copy()  # any order
    assert list(seen[last_seen_before(seen, np.array([3, 9, 11, 0]))]) == [2, 8, 8, 8]


def test_validation_frames_and_clips_are_held_out_of_training_and_testing():
    fitted = np.ones(20, bool)
    fitted[12] = False
    split = subject_split(fitted, np.zeros(20, int), 5, validation_frames=3)
    assert list(split.test) == list(range(15, 20)) and list(split.validation) == [13, 14]
    assert list(split.train) == list(range(12)) and list(split.seen) == list(range(12)) + [13, 14]
    c = subject_split(np.ones(20, bool), np.zeros(20, int), 5, variant="c", interpolated=[1, 13], validation_frames=3)
    assert 13 not in c.train and 1 in c.train, "an interpolated frame never replaces a validation frame"
    clips = np.repeat([0, 1, 2, 3], 3)
    held = subject_split(np.ones(12, bool), clips, test_frames=3, test_clips=1, validation_clips=1,
                         validation_frames=5)  # (frames apply to the last-frames protocol only)
    assert list(held.test) == [9, 10, 11] and list(held.validation) == [6, 7, 8] and list(held.train) == list(range(6))
    assert len(subject_split(np.ones(12, bool), clips, 3, test_clips=1).validation) == 0
    with pytest.raises(InputError, match="4 clip\\(s\\) cannot hold out 1 clip\\(s\\) for testing and 3 for validation"):
        subject_split(np.ones(12, bool), clips, 3, test_clips=1, validation_clips=3, source="frames.json")
    with pytest.raises(InputError, match="frames.json: 12 frames are too few for 5 test frames, 3 validation"):
        subject_split(np.ones(12, bool), np.zeros(12, int), 5, validation_frames=3, source="frames.json")


def test_too_few_frames_for_the_split_stop_with_the_file_named():
    with pytest.raises(InputError, match="subject/frames.json: 2 frames are too few for 3 test frames"):
        subject_split(np.ones(2, bool), np.zeros(2, int), 3, source="subject/frames.json")
    with pytest.raises(InputError, match="no fitted frame left for the test split"):
        subject_split(np.array([1, 1, 1, 0, 0, 0], bool), np.zeros(6, int), 3)
    assert list(mouth_open_subset(np.array([0.1, 0.3, 0.0, 0.2]), 2)) == [1, 3]


def test_psnr_ssim_values():
    a = torch.full((1, 3, 32, 32), 0.5)
    assert psnr(a + 0.1, a, max_value=1.0) == pytest.approx(20.0, abs=1e-3)
    # eq. (10): MAX is the ground truth's largest value, per image, and the images' PSNRs are averaged
    assert psnr(a + 0.1, a) == pytest.approx(20.0 + 20 * math.log10(0.5), abs=1e-3)
    b = torch.stack([torch.full((3, 8, 8), 1.0), torch.full((3, 8, 8), 1.0)])
    b[:, :, 0, 0] = 1.0
    pred = b.clone()
    pred[0] -= 0.1
    pred[1] -= 0.01
    assert psnr(pred, b) == pytest.approx((20.0 + 40.0) / 2, abs=1e-3)
    assert ssim(a, a) == pytest.approx(1.0, abs=1e-6)


def test_colour_matched_psnr_forgives_an_overall_colour_and_nothing_else():
    torch.manual_seed(0)
    target = torch.rand(2, 3, 16, 16) * 0.6 + 0.2
    mask = torch.zeros(2, 1, 16, 16)
    mask[..., 4:12, 4:12] = 1
    tinted = (target + torch.tensor([0.1, -0.05, 0.02]).view(1, 3, 1, 1)) * mask + target * (1 - mask)
    assert psnr_in_mask(tinted, target, mask) < 25 and psnr_colour_matched(tinted, target, mask) > 100
    noisy = target + 0.05 * torch.randn_like(target)  # zero-mean error: matching the colour changes little
    assert psnr_colour_matched(noisy, target, mask) == pytest.approx(psnr_in_mask(noisy, target, mask), abs=0.3)
    flat = colour_matched(torch.zeros_like(target), target, mask)  # a flat image takes each image's mean colour
    np.testing.assert_allclose(flat[:, :, 4:12, 4:12].mean((2, 3)), target[:, :, 4:12, 4:12].mean((2, 3)), atol=1e-6)
    assert (flat[:, :, :4] == 0).all()


def test_lpips_is_missing_without_backbone_and_matches_the_package_with_it(tmp_path):
    assert lpips_metric(None) is None
    import lpips
    from torchvision.models import vgg16

    torch.manual_seed(0)
    backbone = vgg16()  # random weights stand in for ImageNet's: the plumbing is what is tested
    torch.save(backbone.state_dict(), tmp_path / "vgg16.pth")
    ours = LPIPS(tmp_path / "vgg16.pth")
    reference = lpips.LPIPS(net="vgg", pretrained=True, pnet_rand=True, verbose=False).eval()
    load_backbone(reference, backbone.features)
    x, y = torch.rand(2, 3, 64, 64), torch.rand(2, 3, 64, 64)
    with torch.no_grad():
        expected = float(reference(x * 2 - 1, y * 2 - 1).mean())
    assert ours(x, y) == pytest.approx(expected, rel=1e-6)
    assert ours(x, x) == pytest.approx(0.0, abs=1e-6)
    # the backbone really is the file's: a different backbone gives a different distance
    other = lpips.LPIPS(net="vgg", pretrained=True, pnet_rand=True, verbose=False).eval()
    with torch.no_grad():
        assert float(other(x * 2 - 1, y * 2 - 1).mean()) != pytest.approx(expected, rel=1e-3)
    with pytest.raises(InputFileError, match="missing.pth: no such file"):
        LPIPS(tmp_path / "missing.pth")


def test_identity_similarity_on_renders(head_model):
    from avatarlab.render import orbit_camera
    from avatarlab.render.head_renderer import HeadRenderer

    renderer = HeadRenderer(head_model)
    params = head_model.zeros(2)
    torch.manual_seed(3)
    params["shape"][1] = torch.randn(100).clamp(-2, 2) * 1.5
    params["texture"][1] = torch.randn(50).clamp(-2, 2)
    with torch.no_grad():
        out = renderer(params, orbit_camera(1.0, 0.0, 0.0, image_size=(256, 256), batch=2))
    images = (out.rgb.permute(0, 2, 3, 1).numpy() * 255).astype(np.uint8)
    same = identity_similarity(images[0], images[0])
    other = identity_similarity(images[0], images[1])
    assert same == pytest.approx(1.0, abs=1e-6)
    assert other is not None and other < same
    assert identity_similarity(np.zeros((64, 64, 3), np.uint8), images[0]) is None



def test_st_lpips_ranks_real_photographs_and_tolerates_a_pixel_shift():
    """ST-LPIPS (weights shipped in the stlpips-pytorch wheel) on scikit-image's photographs: identical = 0 < a mild
    blur < an unrelated image, and a one-pixel shift scores lower than a blur of higher PSNR."""
    import kornia
    from skimage import data

    def photo(image):
        t = torch.from_numpy(image).permute(2, 0, 1)[None].float() / 255
        return torch.nn.functional.interpolate(t, size=(128, 128), mode="area")

    metric = STLPIPS()
    img, other = photo(data.astronaut()), photo(data.chelsea())
    blur = kornia.filters.gaussian_blur2d(img, (5, 5), (1.0, 1.0))
    shift = torch.roll(img, 1, dims=3)
    same, mild, unrelated, shifted = (metric(x, img) for x in (img, blur, other, shift))
    assert same == pytest.approx(0.0, abs=1e-6) and 0 < mild < unrelated
    assert psnr(shift, img) < psnr(blur, img) - 3, "the shift is the larger change by PSNR"
    assert shifted < mild, "and the smaller one to a shift-tolerant perceptual metric"
    assert "ST-LPIPS" in metric.name and "LPIPS (VGG" not in metric.name and "AlexNet" in metric.name
    vgg = STLPIPS(net="vgg")  # the VGG16 variant (a training term's network), its weights from the same wheel
    same, mild, unrelated = (vgg(x, img) for x in (img, blur, other))
    assert same == pytest.approx(0.0, abs=1e-6) and 0 < mild < unrelated and "VGG16" in vgg.name
    assert abs(mild - metric(blur, img)) > 1e-3, "a network of its own, not AlexNet again"
    with pytest.raises(ValueError, match="must be one of"):
        STLPIPS(net="resnet")


def test_face_metrics_on_renders_of_the_head_model(head_model):
    from avatarlab.render import orbit_camera
    from avatarlab.render.head_renderer import HeadRenderer

    with torch.no_grad():
        out = HeadRenderer(head_model)(head_model.zeros(2), orbit_camera(1.0, 0.0, 0.0, image_size=(256, 256),
                                                                        batch=2))
    faces = (out.rgb.permute(0, 2, 3, 1).numpy() * 255).astype(np.uint8)
    blank = np.full_like(faces, 128)
    found = face_metrics(faces, faces)
    assert found["face_detection_rate"] == 1.0 and found["landmark_nme"] == pytest.approx(0.0, abs=1e-9)
    assert found["identity_similarity"] == pytest.approx(1.0, abs=1e-6)
    none = face_metrics(blank, faces)
    assert none["face_detection_rate"] == 0.0 and none["landmark_nme"] is None and none["identity_similarity"] is None


def test_baselines_predict_from_training_frames_only():
    train = torch.zeros(3, 3, 8, 8)
    train[:, 0] = torch.tensor([0.2, 0.4, 0.6])[:, None, None]
    masks = torch.ones(3, 1, 8, 8)
    test_masks = torch.zeros(2, 1, 8, 8)
    test_masks[:, :, 2:6, 2:6] = 1
    colour = baselines.mean_colour(train, masks, test_masks)
    assert colour[0, 0, 3, 3] == pytest.approx(0.4) and colour[0, 0, 0, 0] == pytest.approx(0.5)  # grey outside
    last = baselines.frames_at(train, masks, [2, 2], test_masks)
    assert last[1, 0, 3, 3] == pytest.approx(0.6)
    pool = {"jaw": torch.tensor([[0.0], [0.1], [0.3]]), "camera": torch.zeros(3, 2)}
    query = {"jaw": torch.tensor([[0.28], [0.02]]), "camera": torch.zeros(2, 2)}
    assert list(baselines.nearest_indices(pool, query)) == [2, 0]


def test_gain_over_the_best_baseline_respects_each_metrics_direction():
    model = {"psnr": 25.0, "st_lpips": 0.20, "ssim": 0.80}
    base = {"last": {"psnr": 26.0, "st_lpips": 0.30, "ssim": 0.85}, "mean": {"psnr": 20.0, "st_lpips": 0.10,
                                                                              "ssim": 0.70}}
    g = gains(model, base)
    assert g["psnr"] == {"best_baseline": "last", "baseline": 26.0, "gain": -1.0, "beats": False}
    assert g["st_lpips"]["best_baseline"] == "mean" and g["st_lpips"]["gain"] == pytest.approx(-0.1)
    assert not g["ssim"]["beats"]


@pytest.fixture(scope="module")
def parent_model(tmp_path_factory):
    """A tiny pretrained model (alpha1 at smoke scale, a very small network)."""
    from avatarlab.pretrain import train as pretrain

    folder = tmp_path_factory.mktemp("parent")
    fake_real_set(folder / "portraits")
    cfg = step_cfg(pretrain, tiny_model_overrides() + ["model.depth=5", f"pretrain.out_dir={folder / 'alpha1'}",
                                                       f"pretrain.real_subject_dir={folder / 'portraits'}"])
    net, result, _ = pretrain.pretrain_model(cfg, torch.device("cpu"))
    return folder / "alpha1" / "model.pt", net


def test_weight_average_is_the_exponential_moving_average_and_swaps_back():
    from avatarlab.training.loop import WeightAverage

    net = torch.nn.Sequential(torch.nn.Linear(2, 2), torch.nn.BatchNorm1d(2))
    with torch.no_grad():
        net[0].weight.fill_(1.0)
    ema = WeightAverage(net, 0.75)
    assert "1.num_batches_tracked" not in ema.state_dict(), "integer buffers are not averaged"
    for value in (5.0, 9.0):
        with torch.no_grad():
            net[0].weight.fill_(value)
        ema.update(net)
    expected = 0.75 * (0.75 * 1.0 + 0.25 * 5.0) + 0.25 * 9.0  # 4.0
    torch.testing.assert_close(ema.state_dict()["0.weight"], torch.full((2, 2), expected))
    with ema.swapped_in(net):
        torch.testing.assert_close(net[0].weight.detach(), torch.full((2, 2), expected))
    torch.testing.assert_close(net[0].weight.detach(), torch.full((2, 2), 9.0), msg="training weights back after it")
    resumed = WeightAverage(net, 0.75, ema.state_dict())
    torch.testing.assert_close(resumed.state_dict()["0.weight"], torch.full((2, 2), expected))
    with pytest.raises(ValueError, match="ema_decay"):
        WeightAverage(net, 1.0)


def test_ema_decay_outside_zero_to_one_is_a_config_error():
    from avatarlab.avatar import finetune
    from avatarlab.runtime.schema import problems

    assert any("finetune.ema_decay: must be below 1" in p
               for p in problems(step_cfg(finetune, ["finetune.ema_decay=1.0"])))
    assert any("finetune.ema_decay: must be at least 0" in p
               for p in problems(step_cfg(finetune, ["finetune.ema_decay=-0.1"])))
    assert not [p for p in problems(step_cfg(finetune, ["finetune.ema_decay=0.99"])) if "ema_decay" in p]


@pytest.mark.slow
def test_weight_averaged_finetuning_resumes_exactly_after_a_kill(tmp_path, parent_model, monkeypatch):
    from avatarlab.avatar import finetune

    path, _ = parent_model
    subject = fake_video_subject(tmp_path / "subject", count=8)

    def cfg(name, decay):
        return step_cfg(finetune, tiny_model_overrides() + [
            f"finetune.subject_dir={subject}", f"finetune.init_model={path}", "finetune.test_frames=2",
            f"finetune.out_dir={tmp_path / name}", "finetune.iterations=6", "finetune.snapshots=2",
            "finetune.checkpoint_every=2", f"finetune.ema_decay={decay}", "tracking.enabled=false"])

    last_iterate, plain, _ = finetune.finetune_avatar(cfg("plain", 0.0), torch.device("cpu"))
    full_net, full, _ = finetune.finetune_avatar(cfg("full", 0.5), torch.device("cpu"))
    assert [h["loss"] for h in full.history] == pytest.approx([h["loss"] for h in plain.history], rel=1e-6, abs=0), \
        "averaging does not steer training"
    moved = [not torch.allclose(p, q) for p, q in zip(last_iterate.parameters(), full_net.parameters())]
    assert any(moved), "the avatar is the average, not the last iterate"
    with killed_at_optimizer_step(monkeypatch, 4):
        finetune.finetune_avatar(cfg("killed", 0.5), torch.device("cpu"))
    saved = torch.load(tmp_path / "killed" / "checkpoint.pt", weights_only=True)
    assert saved["ema"] is not None and saved["step"] == full.start + 2
    net, resumed, _ = finetune.finetune_avatar(cfg("killed", 0.5), torch.device("cpu"))
    for p, q in zip(full_net.parameters(), net.parameters()):
        torch.testing.assert_close(p, q)
    name = f"step_{full.start + 3:07d}.pt"  # the curve's weights are the average too, swapped in for the snapshot
    averaged = torch.load(tmp_path / "full" / "snapshots" / name, weights_only=True)["state"]
    iterate = torch.load(tmp_path / "plain" / "snapshots" / name, weights_only=True)["state"]
    assert any(not torch.allclose(averaged[k], iterate[k]) for k in iterate if iterate[k].is_floating_point())


@pytest.mark.slow
def test_finetuning_freezes_the_first_layers_and_keeps_identity_fixed(tmp_path, parent_model):
    from avatarlab.avatar import finetune

    path, parent = parent_model
    subject = fake_video_subject(tmp_path / "subject", count=8)
    cfg = step_cfg(finetune, tiny_model_overrides() + [
        "finetune=final", f"finetune.subject_dir={subject}", f"finetune.init_model={path}", "finetune.test_frames=2",
        f"finetune.out_dir={tmp_path / 'avatar'}", "finetune.iterations=4", "finetune.snapshots=2"])
    net, result, report = finetune.finetune_avatar(cfg, torch.device("cpu"))
    assert report["train_indices"] == list(range(6)) and report["test_indices"] == [6, 7]
    assert set(result.offsets.keys()) == {"pose", "expression", "lighting"}, "shape and texture stay fixed"
    p_syn = [h["p_synthetic"] for h in result.history]
    assert p_syn[0] > p_syn[-1] and p_syn[-1] == pytest.approx(0.0), "synthetic share decays linearly to 0"
    freeze, depth = int(cfg.finetune.freeze_layers), len(net.nerf.layers)
    assert 0 < freeze < depth  # half the MLP: 2 of 4 at smoke/tiny, 4 of 8 at paper
    for k in range(depth):
        same = torch.equal(parent.nerf.layers[k].weight, net.nerf.layers[k].weight)
        assert same == (k < freeze), f"MLP layer {k} should be {'frozen' if k < freeze else 'trained'}"
    assert [p.name for p in sorted((tmp_path / "avatar" / "snapshots").glob("*.pt"))] == [
        f"step_{result.start + 2:07d}.pt"]
    base = step_cfg(finetune, tiny_model_overrides() + ["finetune=base"]).finetune
    assert (base.z_aug, base.p_max) == (False, 0.0), "ablation fine-tunes: no z-augmentation, no synthetic share"


@pytest.mark.slow
def test_avatar_evaluation_scores_model_and_baselines_on_the_same_frames(tmp_path, parent_model, monkeypatch):
    from avatarlab.avatar import evaluate as evaluation
    from avatarlab.avatar import finetune
    from avatarlab.data.real_images import RealImageSet
    from avatarlab.model.head_nerf import load_model_file, render_frames
    from avatarlab.model.losses import composite

    path, _ = parent_model
    subject = fake_video_subject(tmp_path / "subject", count=8)
    common = tiny_model_overrides() + [f"finetune.subject_dir={subject}", "finetune.test_frames=2",
                                       f"finetune.out_dir={tmp_path / 'avatar'}"]
    finetune.finetune_avatar(step_cfg(finetune, common + [f"finetune.init_model={path}", "finetune.iterations=4"]),
                             torch.device("cpu"))
    cfg = step_cfg(evaluation, common + [f"evaluate.model={tmp_path / 'avatar' / 'model.pt'}",
                                         f"evaluate.out={tmp_path / 'avatar' / 'eval.json'}"])
    report, grid = evaluation.evaluate_avatar(cfg, torch.device("cpu"))
    json.dumps(report)  # plain values only
    part = report["all"]
    assert part["frames"] == 2 and set(part["baselines"]) == {"mean_frame", "last_frame", "nearest"}
    for scores in [part["model"], *part["baselines"].values()]:
        assert {"psnr", "psnr_head", "ssim", "st_lpips", "face_detection_rate"} <= set(scores)
        assert scores["lpips"] is None, "no VGG backbone given: LPIPS is missing, not made up"
    assert part["gain"]["psnr"]["baseline"] == max(b["psnr"] for b in part["baselines"].values())
    assert part["gain"]["psnr"]["gain"] == pytest.approx(part["model"]["psnr"] - part["gain"]["psnr"]["baseline"])
    assert [pt["step"] for pt in report["curve"]] == [7, 8, 9, 10] and report["step"] == 10  # 4 snapshots by default
    assert grid.shape[1] == 3 * 64, "rows: truth, model, best baseline"
    # the fit of what it saw: evenly spaced training frames (6 here: 8 - 2 test frames), rendered as test frames are
    trained = report["trained"]
    assert trained["frames"] == 6 and trained["indices"] == list(range(6)) and not set(trained["indices"]) & {6, 7}
    quick = common + [f"evaluate.model={tmp_path / 'avatar' / 'model.pt'}", "evaluate.st_lpips=false",
                      "evaluate.face_metrics=false"]
    few, _ = evaluation.evaluate_avatar(step_cfg(evaluation, quick + ["evaluate.trained_frames=3"]),
                                        torch.device("cpu"))
    assert few["trained"]["indices"] == [0, 2, 5]
    net, _ = load_model_file(tmp_path / "avatar" / "model.pt")
    frames = RealImageSet(subject, 64, np.array([0, 2, 5]))
    target = composite(frames.images, frames.masks)
    expected = psnr(composite(render_frames(net, frames), frames.masks), target)
    assert few["trained"]["model"]["psnr"] == pytest.approx(expected, abs=1e-4)
    assert few["trained"]["model"]["psnr"] != pytest.approx(few["all"]["model"]["psnr"], abs=1e-3)
    none, _ = evaluation.evaluate_avatar(step_cfg(evaluation, quick + ["evaluate.trained_frames=0"]),
                                         torch.device("cpu"))
    assert none["trained"] is None
    extras = evaluation.run_extras(few, "all")  # into the avatar's MLflow run
    assert extras["trained_psnr"] == few["trained"]["model"]["psnr"] and "trained_ssim" in extras
    assert set(evaluation.run_extras(none, "all")) == set(evaluation.run_extras(few, "mouth_open")) == {
        "render_seconds_per_frame"}
    # same-recording test frames (finetune.recording_test_frames with held-out clips): here frame 5, scored apart
    assert report["same_recording"] is None, "the last-frames protocol has none"
    split = evaluation.avatar_split(cfg.finetune)
    monkeypatch.setattr(evaluation, "avatar_split", lambda ft: dataclasses.replace(
        split, train=split.train[:5], recording=np.array([5])))
    later, _ = evaluation.evaluate_avatar(step_cfg(evaluation, quick), torch.device("cpu"))
    same = later["same_recording"]
    assert same["frames"] == 1 and same["indices"] == [5] and later["all"]["frames"] == 2
    frame = RealImageSet(subject, 64, np.array([5]))
    assert same["model"]["psnr"] == pytest.approx(
        psnr(composite(render_frames(net, frame), frame.masks), composite(frame.images, frame.masks)), abs=1e-4)
    seen = RealImageSet(subject, 64, np.array([4]))  # the last frame it saw, not frame 5 itself
    assert same["baselines"]["last_frame"]["psnr"] == pytest.approx(
        psnr(composite(seen.images, frame.masks), composite(frame.images, frame.masks)), abs=1e-4)
    assert same["gain"]["psnr"]["gain"] == pytest.approx(same["model"]["psnr"] - same["gain"]["psnr"]["baseline"])


@pytest.mark.slow
def test_a_validation_split_chooses_the_stop_and_the_test_frames_stay_unseen(tmp_path, parent_model, monkeypatch):
    """With validation frames, the snapshot scoring best on them becomes the avatar (model.pt holds its weights and
    step), the end of training stays on the quality curve, and the baselines may copy the validation frames."""
    from avatarlab.avatar import evaluate as evaluation
    from avatarlab.avatar import finetune
    from avatarlab.model.head_nerf import load_model_file

    path, _ = parent_model
    subject = fake_video_subject(tmp_path / "subject", count=10)
    out = tmp_path / "avatar"
    common = tiny_model_overrides() + [f"finetune.subject_dir={subject}", "finetune.test_frames=2",
                                       "finetune.validation_frames=2", f"finetune.out_dir={out}"]
    scores = iter([30.0, 29.0, 28.0, 27.0])  # the candidates in step order: the first snapshot is the best
    scored = []
    monkeypatch.setattr(finetune, "psnr", lambda pred, target: scored.append(pred.shape) or next(scores))
    net, result, report = finetune.finetune_avatar(
        step_cfg(finetune, common + [f"finetune.init_model={path}", "finetune.iterations=4"]), torch.device("cpu"))
    start = result.start
    assert report["train_indices"] == list(range(6)) and report["validation_indices"] == [6, 7]
    assert report["test_indices"] == [8, 9] and scored == [torch.Size([2, 3, 64, 64])] * 4
    assert [c["step"] for c in report["validation_scores"]] == [start + 1, start + 2, start + 3, start + 4]
    assert report["chosen_step"] == start + 1 and report["iterations"] == 4 and report["validation_psnr"] == 30.0
    # ST-LPIPS beside each candidate's PSNR, recorded (the chosen one's too), never chosen on
    assert all(0 < c["st_lpips"] < 10 for c in report["validation_scores"]), report["validation_scores"]
    assert report["validation_st_lpips"] == report["validation_scores"][0]["st_lpips"]
    model, content = load_model_file(out / "model.pt")
    first, _ = load_model_file(out / "snapshots" / f"step_{start + 1:07d}.pt")
    end, _ = load_model_file(out / "snapshots" / f"step_{start + 4:07d}.pt")
    assert content["step"] == start + 1 and content["trained_to"] == start + 4
    for name, weights in model.state_dict().items():
        assert torch.equal(weights, first.state_dict()[name])
    assert any(not torch.equal(w, end.state_dict()[k]) for k, w in model.state_dict().items())
    cfg = step_cfg(evaluation, common + [f"evaluate.model={out / 'model.pt'}", f"evaluate.out={out / 'eval.json'}"])
    report, _ = evaluation.evaluate_avatar(cfg, torch.device("cpu"))
    assert [pt["step"] for pt in report["curve"]] == [start + 1, start + 2, start + 3, start + 4]
    assert [bool(pt.get("model")) for pt in report["curve"]] == [True, False, False, False]
    assert report["step"] == start + 1 and report["trained_to"] == start + 4 and report["validation_frames"] == 2
    assert report["trained"]["indices"] == list(range(6)), "trained frames: never a validation or test frame"
    last = report["all"]["baselines"]["last_frame"]
    monkeypatch.setattr(evaluation, "avatar_split", lambda ft: type(finetune.avatar_split(ft))(
        train=finetune.avatar_split(ft).train, test=finetune.avatar_split(ft).test, protocol="last_frames"))
    without, _ = evaluation.evaluate_avatar(cfg, torch.device("cpu"))
    assert without["all"]["baselines"]["last_frame"]["psnr"] != pytest.approx(last["psnr"]), \
        "the last-frame baseline copies frame 7 (a validation frame), not frame 5"


def test_the_st_lpips_and_distortion_terms_join_the_loss_only_when_weighted(tmp_path, parent_model):
    """finetune.w_st_lpips > 0 adds the ST-LPIPS term (on head windows with st_lpips_crop) to eq. (8), and
    finetune.w_distortion > 0 the rays' distortion term: each logged loss is the sum of its terms; at 0 (the defaults)
    the terms are absent and the loss is eq. (8) alone."""
    from avatarlab.avatar import finetune

    path, _ = parent_model
    subject = fake_video_subject(tmp_path / "subject", count=8)
    first_term = {}
    for weight, crop, distortion, decay, net in ((0.0, 0, 0.0, 0.0, "alex"), (0.5, 32, 0.0, 0.0, "alex"),
                                                 (0.0, 0, 0.5, 0.0, "alex"), (0.5, 32, 0.0, 1.0, "alex"),
                                                 (0.5, 32, 0.0, 0.0, "vgg")):
        out = tmp_path / f"avatar_{weight}_{distortion}_{decay}_{net}"
        cfg = step_cfg(finetune, tiny_model_overrides() + [
            f"finetune.subject_dir={subject}", "finetune.test_frames=2", f"finetune.out_dir={out}",
            f"finetune.init_model={path}", "finetune.iterations=3", "finetune.log_every=1",
            f"finetune.w_st_lpips={weight}", f"finetune.st_lpips_crop={crop}", f"finetune.w_distortion={distortion}",
            f"finetune.st_lpips_decay={decay}", f"finetune.st_lpips_net={net}"])
        _, _, report = finetune.finetune_avatar(cfg, torch.device("cpu"))
        history = report["history"]
        if weight and not decay:  # the same first batch and render: only the term's network differs
            first_term[net] = history[0]["st_lpips_term"]
        assert len(history) == 3
        assert all(("st_lpips_term" in h) == (weight > 0) for h in history)
        assert all(("distortion_term" in h) == (distortion > 0) for h in history)
        if decay:  # finetune.st_lpips_decay = 1: the term's weight falls to 0 at the last iteration
            assert history[0]["st_lpips_term"] > 0 and history[-1]["st_lpips_term"] == 0.0
        for h in history:  # loss = eq. (8)'s mse + perceptual + offsets, + the extras
            extras = h.get("st_lpips_term", 0.0) + h.get("distortion_term", 0.0)
            assert extras > 0 or weight == distortion == 0 or (decay and h is history[-1])
            assert h["loss"] == pytest.approx(h["mse"] + h["perceptual"] + h["offsets"] + extras, rel=1e-5, abs=1e-7)
    assert first_term["vgg"] > 0 and abs(first_term["vgg"] - first_term["alex"]) > 1e-4 * first_term["alex"], \
        "finetune.st_lpips_net=vgg trains with the VGG16 network"


@pytest.mark.slow
def test_betas_from_alpha2_and_their_avatars_keep_the_mouth_interior(tmp_path, monkeypatch):
    """Seed 002, 3.4: alpha2 ends on the mouth-interior head; a beta continued from it, and the final-recipe avatar
    fine-tuned from that beta, draw their synthetic samples from the same head (from alpha1: the plain head), and
    each run names the model it continues."""
    from avatarlab.avatar import finetune
    from avatarlab.data.synthetic import SyntheticGenerator
    from avatarlab.model.head_nerf import load_model_file, synthetic_mouth
    from avatarlab.pretrain import train as pretrain

    faces = []  # the face count of the head each synthetic draw comes from (the mouth interior adds faces)
    sample = SyntheticGenerator.sample
    monkeypatch.setattr(SyntheticGenerator, "sample",
                        lambda self, *a, **k: faces.append(int(self.model.faces.shape[0])) or sample(self, *a, **k))
    fake_real_set(tmp_path / "portraits")
    common = tiny_model_overrides() + ["model.depth=5", f"pretrain.real_subject_dir={tmp_path / 'portraits'}"]

    def pretrain_run(name, *extra):
        faces.clear()
        cfg = step_cfg(pretrain, common + [f"pretrain.name={name}", f"pretrain.out_dir={tmp_path / name}", *extra])
        _, _, report = pretrain.pretrain_model(cfg, torch.device("cpu"))
        return report, sorted(set(faces)), load_model_file(tmp_path / name / "model.pt")[1]

    always_synthetic = ["strategy.p_min=1.0", "strategy.p_max=1.0"]
    a1, a1_heads, a1_file = pretrain_run("alpha1", "strategy=alpha1")
    a2, a2_heads, a2_file = pretrain_run("alpha2", "strategy=alpha2")
    plain, with_mouth = a1_heads[0], max(a2_heads)
    assert a1_heads == [plain] and a2_heads == [plain, with_mouth] and with_mouth > plain
    assert (synthetic_mouth(a1_file), synthetic_mouth(a2_file)) == (False, True)
    b1, b1_heads, b1_file = pretrain_run("beta5_from_alpha1", "strategy=beta5", *always_synthetic,
                                         f"pretrain.init_model={tmp_path / 'alpha1' / 'model.pt'}")
    b2, b2_heads, b2_file = pretrain_run("beta5_from_alpha2", "strategy=beta5", *always_synthetic,
                                         f"pretrain.init_model={tmp_path / 'alpha2' / 'model.pt'}")
    assert (b1["init"], b1_heads, b1["mouth_from"], synthetic_mouth(b1_file)) == ("alpha1", [plain], None, False)
    assert (b2["init"], b2_heads, synthetic_mouth(b2_file)) == ("alpha2", [with_mouth], True)
    assert b2["mouth_from"] == b2["M"] - 1, "every continued iteration draws from the mouth-interior head"
    # a file written before the flag existed answers from its strategy's mouth phase
    assert synthetic_mouth({k: v for k, v in a2_file.items() if k != "synthetic_mouth"})

    subject = fake_video_subject(tmp_path / "subject", count=8)
    for parent, head in (("beta5_from_alpha1", plain), ("beta5_from_alpha2", with_mouth)):
        faces.clear()
        cfg = step_cfg(finetune, tiny_model_overrides() + [
            "model.depth=5", "finetune=final", "finetune.p_max=1.0", f"finetune.subject_dir={subject}",
            f"finetune.init_model={tmp_path / parent / 'model.pt'}", "finetune.test_frames=2",
            f"finetune.out_dir={tmp_path / 'avatar' / parent}", "finetune.iterations=4"])
        _, _, report = finetune.finetune_avatar(cfg, torch.device("cpu"))
        assert sorted(set(faces)) == [head], parent
        assert report["synthetic_samples"] == ("mouth interior" if head == with_mouth else "plain head")
