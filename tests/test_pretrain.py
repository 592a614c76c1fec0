import json

import numpy as np
import pytest
import torch
from PIL import Image

from avatarlab.data.schedule import scaled_schedule, synthetic_probability
from avatarlab.model.cnerf import CNeRF, CNeRFConfig, camera_rays, positional_encoding, volume_render_features
from avatarlab.model.losses import RandomConvFeatures, VGGFeatures, head_model_loss, perceptual_network
from avatarlab.model.renderer2d import NeuralRenderer2D
from avatarlab.render import orbit_camera
from conftest import compose_config

STRATEGIES = ["alpha1", "alpha2"] + [f"beta{i}" for i in range(1, 7)]
# (M, N, p_min, p_max, z_aug, init) from the dissertation (DESIGN.md "Synthetic data and strategies")
PAPER = {"alpha1": (310000, 310000, None, None, False, None), "alpha2": (310000, 310000, None, None, False, None),
         "beta1": (310000, 312500, 0.0, 0.0, False, "alpha1"), "beta2": (310000, 312500, 0.0, 0.0, True, "alpha1"),
         "beta3": (310000, 312500, 0.25, 0.25, False, "alpha1"), "beta4": (310000, 312500, 0.0, 0.25, False, "alpha1"),
         "beta5": (310000, 312500, 0.25, 0.25, True, "alpha1"), "beta6": (310000, 312500, 0.0, 0.25, True, "alpha1")}


def test_eq9_schedule():
    assert synthetic_probability(100, 100, 200, 0.0, 0.25) == 1.0
    assert synthetic_probability(150, 100, 200, 0.0, 0.25) == pytest.approx(0.125)
    assert synthetic_probability(200, 100, 200, 0.0, 0.25) == pytest.approx(0.0)
    assert synthetic_probability(180, 100, 200, 0.25, 0.25) == pytest.approx(0.25)
    assert synthetic_probability(5, 10, 10, 0.0, 0.0) == 1.0


@pytest.mark.parametrize("name", STRATEGIES)
def test_strategy_configs_match_the_dissertation(name):
    cfg = compose_config([f"strategy={name}", "scale=paper"])
    s = cfg.strategy
    M, N, p_min, p_max, z_aug, init = PAPER[name]
    assert (s.name, s.M, s.N, bool(s.z_aug), s.init) == (name, M, N, z_aug, init)
    if p_min is not None:
        assert (s.p_min, s.p_max) == (p_min, p_max)
    sched = scaled_schedule(s, cfg.scale.pretrain_alpha_iterations, cfg.scale.pretrain_beta_iterations)
    assert (sched.M, sched.N) == (M, N), "paper scale must use the dissertation's iteration counts exactly"
    assert sched.mouth_from == (300000 if name == "alpha2" else None)
    tiny = compose_config([f"strategy={name}", "scale=tiny"])
    t = scaled_schedule(tiny.strategy, tiny.scale.pretrain_alpha_iterations, tiny.scale.pretrain_beta_iterations)
    assert t.M == tiny.scale.pretrain_alpha_iterations
    assert t.N - t.M == (tiny.scale.pretrain_beta_iterations if name.startswith("beta") else 0)
    smoke = compose_config([f"strategy={name}", "scale=smoke"])
    s_sched = scaled_schedule(smoke.strategy, smoke.scale.pretrain_alpha_iterations,
                              smoke.scale.pretrain_beta_iterations)
    if name == "alpha2":
        assert 0 < s_sched.mouth_from < s_sched.M, "alpha2 keeps a mouth-interior phase at every scale"


def test_volume_rendering_eq7():
    depths = torch.tensor([[[1.0, 1.1, 1.2]]])
    feats = torch.tensor([[[[1.0], [2.0], [3.0]]]])
    out, opacity = volume_render_features(torch.tensor([[[1e4, 0.0, 0.0]]]), feats, depths)
    assert out.item() == pytest.approx(1.0, abs=1e-4) and opacity.item() == pytest.approx(1.0, abs=1e-4)
    out, opacity = volume_render_features(torch.zeros(1, 1, 3), feats, depths)
    assert out.item() == 0.0 and opacity.item() == 0.0
    sigma = torch.tensor([[[0.0, 5.0, 0.0]]])  # half-transparent middle sample
    out, opacity = volume_render_features(sigma, feats, depths)
    alpha = 1 - np.exp(-5.0 * 0.1)
    assert out.item() == pytest.approx(2.0 * alpha, rel=1e-4) and opacity.item() == pytest.approx(alpha, rel=1e-4)


def test_rays_go_through_the_scaled_pixels():
    cam = orbit_camera(1.0, 0.0, 0.0, image_size=(128, 128))
    origins, dirs = camera_rays(cam, (16, 16))
    assert origins.shape == dirs.shape == (1, 256, 3)
    np.testing.assert_allclose(origins[0, 0].numpy(), [0, 0, 1.0], atol=1e-5)  # the camera centre
    hits = origins + dirs * 1.0  # depth 1 along the camera axis lands on the z = 0 plane
    back = cam.scaled((16, 16)).project(hits)
    ys, xs = torch.meshgrid(torch.arange(16.0), torch.arange(16.0), indexing="ij")
    np.testing.assert_allclose(back[0, :, 0].numpy(), (xs.reshape(-1) + 0.5).numpy(), atol=1e-3)
    np.testing.assert_allclose(back[0, :, 1].numpy(), (ys.reshape(-1) + 0.5).numpy(), atol=1e-3)
    assert positional_encoding(torch.zeros(2, 3), 4).shape == (2, 27)


@pytest.mark.parametrize("kind", ["proposed", "baseline"])
def test_renderers_upsample_by_eight(kind):
    net = NeuralRenderer2D(32, kind)
    out = net(torch.randn(2, 32, 8, 8))
    assert out.shape == (2, 3, 64, 64) and out.min() >= 0 and out.max() <= 1
    names = " ".join(n for n, _ in net.named_modules())
    assert ("se" in names and "global_branch" in names) == (kind == "proposed")
    with pytest.raises(ValueError, match="proposed' or 'baseline"):
        NeuralRenderer2D(32, "other")


def test_cnerf_conditioning_changes_density_and_features():
    cfg = CNeRFConfig(frequencies=2, depth=3, width=16, skip_layer=1, feature_channels=4, samples=4, n_shape=3,
                      n_expression=2, n_texture=2)
    torch.manual_seed(0)
    nerf = CNeRF(cfg)
    pts = torch.rand(1, 5, 3) * 0.1
    g0, a0 = torch.zeros(1, 3 + 12 + 2), torch.zeros(1, 2 + 27)
    s0, f0 = nerf(pts, g0, a0)
    s1, f1 = nerf(pts, g0 + 1, a0)
    s2, f2 = nerf(pts, g0, a0 + 1)
    assert not torch.allclose(s0, s1) and torch.allclose(s0, s2), "texture/lighting enter after the density"
    assert not torch.allclose(f0, f2)
    assert len(nerf.frozen_prefix(2)) == 4


def test_eq8_offsets_only_for_real_samples(tmp_path):
    pred, target = torch.rand(2, 3, 16, 16), torch.rand(2, 3, 16, 16)
    mask = torch.ones(2, 1, 16, 16)
    offsets = {"shape": torch.ones(2, 3)}
    feats = RandomConvFeatures()
    only_synthetic = head_model_loss(pred, target, mask, feats, offsets, {"shape": 1.0}, torch.tensor([False, False]))
    assert float(only_synthetic["offsets"]) == 0.0
    mixed = head_model_loss(pred, target, mask, feats, offsets, {"shape": 1.0}, torch.tensor([True, False]))
    assert float(mixed["offsets"]) == pytest.approx(3.0)
    same = head_model_loss(target, target, mask, feats, {}, {}, torch.tensor([True, False]))
    assert float(same["total"]) == pytest.approx(0.0, abs=1e-7)
    # the VGG16 path loads a torchvision state dict given by path (random weights stand in for ImageNet's here)
    from torchvision.models import vgg16

    torch.save(vgg16().state_dict(), tmp_path / "vgg16.pth")
    vgg = perceptual_network(str(tmp_path / "vgg16.pth"))
    assert isinstance(vgg, VGGFeatures) and len(vgg(torch.rand(1, 3, 32, 32))) == 4
    with pytest.raises(FileNotFoundError, match="nothere.pth"):
        VGGFeatures(tmp_path / "nothere.pth")


def fake_real_set(folder, count=4, size=64):
    """A preprocessed image subject: frames, masks and a per-image fit, as fit_rgb writes them."""
    (folder / "frames").mkdir(parents=True)
    rng = np.random.default_rng(0)
    names = []
    for i in range(count):
        Image.fromarray((rng.random((size, size, 3)) * 255).astype(np.uint8)).save(folder / "frames" / f"{i:06d}.png")
        names.append(f"{i:06d}.png")
    (folder / "frames.json").write_text(json.dumps({"files": names, "count": count}))
    np.savez(folder / "masks.npz", masks=np.ones((count, size, size), np.uint8))
    cam = orbit_camera(1.0, 0.0, 0.0, image_size=(size, size), batch=count)
    np.savez(folder / "fit_rgb.npz", shape=np.zeros((count, 100), np.float32),
             texture=np.zeros((count, 50), np.float32), lighting=np.zeros((count, 9, 3), np.float32),
             expression=np.zeros((count, 50), np.float32), pose=np.zeros((count, 15), np.float32),
             K=cam.K.numpy(), R=cam.R.numpy(), t=cam.t.numpy(), fitted=np.ones(count, bool))


@pytest.mark.slow
def test_pretraining_resumes_exactly_after_a_kill(tmp_path, monkeypatch):
    from avatarlab.train import pretrain

    fake_real_set(tmp_path / "real")
    overrides = ["scale=smoke", "strategy=beta4", f"pretrain.real_subject_dir={tmp_path / 'real'}",
                 "pretrain.checkpoint_every=2", "tracking.enabled=false", "strategy.init=null"]
    cfg_full = compose_config(overrides + [f"pretrain.out_dir={tmp_path / 'full'}"])
    full = pretrain.train(cfg_full)
    assert [h["step"] for h in full["history"]] == list(range(1, 10))
    assert [h["n_synthetic"] for h in full["history"]][:6] == [2] * 6  # p = 1 up to M
    cfg_killed = compose_config(overrides + [f"pretrain.out_dir={tmp_path / 'killed'}"])
    real_step = torch.optim.Adam.step
    calls = {"n": 0}

    def dying_step(self, *a, **k):
        calls["n"] += 1
        if calls["n"] == 5:
            raise KeyboardInterrupt("killed")
        return real_step(self, *a, **k)

    monkeypatch.setattr(torch.optim.Adam, "step", dying_step)
    with pytest.raises(KeyboardInterrupt):
        pretrain.train(cfg_killed)
    monkeypatch.setattr(torch.optim.Adam, "step", real_step)
    assert (tmp_path / "killed" / "checkpoint.pt").is_file()
    resumed = pretrain.train(cfg_killed)
    for p, q in zip(full["net"].parameters(), resumed["net"].parameters()):
        torch.testing.assert_close(p, q)
    assert resumed["metrics"] == full["metrics"]


def test_paper_scale_sizes_match_the_dissertation():
    """conf/scale/paper.yaml is the dissertation's set-up (DESIGN.md sections 3-4), number for number."""
    s = compose_config(["scale=paper"]).scale
    assert (s.pretrain_alpha_iterations, s.pretrain_beta_iterations, s.pretrain_batch) == (310000, 2500, 64)
    assert (s.pretrain_image_size, s.pretrain_feature_size) == (256, 32)          # 32² feature map -> 256² image
    assert (s.nerf_frequencies, s.nerf_depth, s.nerf_width, s.nerf_skip_layer) == (10, 8, 384, 4)
    assert (s.nerf_feature_channels, s.nerf_samples) == (256, 64)
    assert list(s.synthetic_neck_deg) == [80, 60, 80]
    assert (s.renderer_experiment_iterations, s.renderer_experiment_image_size) == (30000, 128)
    assert s.renderer_experiment_image_size // s.renderer_experiment_feature_size == 8  # three x2 stages
    assert (s.finetune_iterations, s.finetune_test_frames, s.mouth_open_frames) == (1000, 350, 30)
    assert (s.fit_rigid_iterations, s.fit_keyframe_iterations) == (200, 800)
    assert s.speech_speakers == 34 and s.speech_window_hidden == 3000


def test_device_comes_from_the_config():
    from avatarlab.config import resolve_device

    assert resolve_device(compose_config(["device=cpu"])) == torch.device("cpu")
    expected = "cuda" if torch.cuda.is_available() else "cpu"
    assert resolve_device(compose_config([])).type == expected  # the default is auto
    if not torch.cuda.is_available():
        with pytest.raises(RuntimeError, match="device=cuda requested but CUDA is not available"):
            resolve_device(compose_config(["device=cuda"]))


def _short_training(tmp_path, name, *extra):
    from avatarlab.train import pretrain

    if not (tmp_path / "real").is_dir():
        fake_real_set(tmp_path / "real")
    cfg = compose_config(["scale=smoke", "strategy=beta4", f"pretrain.real_subject_dir={tmp_path / 'real'}",
                          "tracking.enabled=false", "strategy.init=null", f"pretrain.out_dir={tmp_path / name}",
                          *extra])
    return pretrain.train(cfg)


@pytest.mark.slow
def test_mixed_precision_training_runs_and_stays_close(tmp_path):
    """amp=true: bfloat16 autocast on the CPU (float16 + GradScaler on CUDA); the run trains like float32."""
    full = _short_training(tmp_path, "fp32", "device=cpu")
    mixed = _short_training(tmp_path, "amp", "device=cpu", "amp=true")
    assert len(mixed["history"]) == len(full["history"])
    assert all(np.isfinite(h["loss"]) for h in mixed["history"])
    assert mixed["history"][0]["loss"] == pytest.approx(full["history"][0]["loss"], rel=0.05)
    assert mixed["metrics"]["psnr"] == pytest.approx(full["metrics"]["psnr"], abs=1.0)
    assert next(mixed["net"].parameters()).dtype == torch.float32  # master weights stay float32


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
def test_training_on_cuda_matches_the_cpu(tmp_path):
    cpu = _short_training(tmp_path, "cpu", "device=cpu")
    gpu = _short_training(tmp_path, "cuda", "device=cuda")
    assert next(gpu["net"].parameters()).device.type == "cuda"
    assert gpu["metrics"]["psnr"] == pytest.approx(cpu["metrics"]["psnr"], abs=0.5)
