"""Every torch module runs on the configured device (issue 7, item 4).

There is no GPU here. PyTorch's `meta` device stands in for one: a meta tensor meeting a CPU tensor in an op raises
"not on the expected device", exactly what a CUDA tensor meeting a stray CPU constant does. So the networks and the
head model are run on `meta` to prove they create nothing on the CPU inside. Whole steps are checked on CUDA where
there is one (skipped here), and mixed precision (bfloat16 autocast) on the CPU.
"""
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from helpers import compose_config, interp_config

META = torch.device("meta")
needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")


def test_head_model_and_fit_loss_stay_on_the_device(head_model):
    from avatarlab.headmodel import load_head_model
    from avatarlab.preprocess.fit_rgb import FitWeights, rgb_fit_loss

    model = load_head_model(compose_config(["scale=smoke"]).head_model).to(META)
    p = model.zeros(3)
    assert p["shape"].device == META
    out = model(p["shape"], p["expression"], p["pose"])
    assert out.vertices.device == META and out.landmarks3d.shape == (3, 68, 3)
    assert model.albedo(p["texture"]).device == META
    rgb = torch.zeros(3, 3, 8, 8, device=META)
    lmk = torch.zeros(3, 68, 2, device=META)
    terms = rgb_fit_loss(rgb, rgb, rgb[:, :1], lmk, lmk, torch.ones(3, device=META), p["shape"], p["expression"],
                         p["texture"], p["pose"], FitWeights(), 8)
    assert all(v.device == META for v in terms.values())


def test_networks_stay_on_the_device():
    from avatarlab.model.cnerf import CNeRFConfig, camera_rays, ray_samples, sphere_interval, volume_render_features
    from avatarlab.model.head_nerf import HeadNeRFModel
    from avatarlab.preprocess.interp.network import XVFILite
    from avatarlab.render.camera import orbit_camera
    from avatarlab.speech.models import AudioToVisemes, PhonemeWindowMLP

    xvfi = XVFILite(8, 2).to(META)
    frames = torch.rand(2, 3, 16, 16, device=META)
    mid = xvfi(frames, frames)
    mid.mean().backward()
    assert mid.shape == (2, 3, 16, 16) and xvfi.flow.net[0][0].weight.grad.device == META

    lstm = AudioToVisemes(65, 12, 40, torch.zeros(12, 68, 2), 16, 16).to(META)
    weights, logits, landmarks, _ = lstm(torch.rand(2, 5, 20, 65, device=META))
    assert weights.shape == (2, 5, 12) and landmarks.shape == (2, 5, 68, 2) and landmarks.device == META

    window = PhonemeWindowMLP(40, 6, 11, 5, 32).to(META)
    one_hot = window.windows(torch.randint(0, 40, (30,), device=META))  # used to pad with CPU zeros
    assert one_hot.shape == (30, 11, 40) and window(one_hot).shape == (30, 5, 6)
    from avatarlab.speech.visemes import PHONEMES

    window = PhonemeWindowMLP(len(PHONEMES), 6, 11, 5, 32, inputs="linguistic").to(META)
    indicators = window.windows(torch.randint(0, len(PHONEMES), (30,), device=META))
    assert indicators.device == META and window(indicators).shape == (30, 5, 6)

    cfg = CNeRFConfig(frequencies=2, depth=3, width=16, skip_layer=1, feature_channels=4, samples=4, n_shape=3,
                      n_expression=2, n_texture=2)
    net = HeadNeRFModel(cfg, "proposed", 8, min_channels=4).to(META)
    camera = orbit_camera(torch.ones(2), 0.0, 0.0, image_size=(64, 64), batch=2, focal=60.0).to(META)
    # the parts of a render (the ray packing's nonzero() has a data-dependent size, which the meta device lacks)
    origins, dirs = camera_rays(camera, (8, 8))
    near, far, _ = sphere_interval(origins, dirs, net.nerf.bound_center, net.nerf.bound_radius)
    depths = ray_samples(near.reshape(-1), far.reshape(-1), 4, stratified=True)
    assert depths.device == META
    points = torch.rand(2 * 64 * 4, 3, device=META)
    sigma, feat = net.nerf(points, torch.zeros(2 * 64 * 4, dtype=torch.long, device=META),
                           torch.rand(2, 3 + 12 + 2, device=META), torch.rand(2, 2 + 27, device=META))
    values, _ = volume_render_features(sigma.reshape(-1, 4), feat.reshape(-1, 4, 4), depths)
    image = net.renderer(values.reshape(2, 8, 8, 4).permute(0, 3, 1, 2))
    assert sigma.device == META and image.shape == (2, 3, 64, 64) and image.device == META


def test_interpolation_trains_in_mixed_precision_like_float32(tmp_path):
    from avatarlab.preprocess.interp.training import train, training_triplets

    frames = torch.rand(9, 3, 16, 16, generator=torch.Generator().manual_seed(0))
    triplets = training_triplets(np.arange(0, 9, 2))
    _, full, _ = train(frames, triplets, interp_config(), tmp_path / "fp32.pt")
    model, mixed, _ = train(frames, triplets, interp_config(amp=True), tmp_path / "amp.pt")
    assert len(mixed) == 6 and np.isfinite(mixed).all()
    assert mixed != full  # bfloat16 really ran
    np.testing.assert_allclose(mixed, full, rtol=0.05)
    assert next(model.parameters()).dtype == torch.float32  # autocast: the weights stay float32


def _toy_corpus(n_items=6, frames=40):
    rng = np.random.default_rng(0)
    items = []
    for k in range(n_items):
        labels = rng.integers(0, 40, frames)
        base = rng.normal(0, 1, (68, 2)) * 10
        items.append({"split": "train" if k < 4 else ("val" if k == 4 else "test"), "labels": labels,
                      "windows": rng.normal(0, 1, (frames, 20, 65)).astype(np.float32),
                      "landmarks": (base + rng.normal(0, 0.5, (frames, 68, 2))).astype(np.float32)})
    return SimpleNamespace(split=lambda name: [i for i in items if i["split"] == name])


def test_speech_models_train_in_mixed_precision(head_model):
    from avatarlab.speech.train import evaluate_window, train_lstm, train_window
    from avatarlab.speech.visemes import viseme_basis

    cfg = compose_config(["scale=smoke", "amp=true"])
    corpus = _toy_corpus()
    basis = viseme_basis(head_model)
    model, history = train_lstm(cfg, corpus, basis, regularize=True, device=torch.device("cpu"))
    assert len(history) == int(cfg.scale.speech_epochs)
    assert all(np.isfinite(h["loss"]) and np.isfinite(h["val_lip_error_percent"]) for h in history)
    window, pca, history = train_window(cfg, corpus, torch.device("cpu"))
    assert np.isfinite(history[-1]["loss"])
    assert np.isfinite(evaluate_window(window, pca, corpus.split("test"))["lip_error_percent"])


@needs_cuda
def test_fits_renders_and_networks_on_cuda_match_the_cpu(tmp_path, head_model):
    from avatarlab.preprocess.interp.training import train, training_triplets
    from avatarlab.pretrain.portraits import render_portraits

    cfg = compose_config(["scale=smoke", "subject=portraits"])
    cpu_params, cpu_chunks, _ = render_portraits(cfg, torch.device("cpu"))
    gpu_params, gpu_chunks, _ = render_portraits(cfg, torch.device("cuda"))
    cpu_img, gpu_img = np.concatenate(list(cpu_chunks)), np.concatenate(list(gpu_chunks))
    assert np.abs(cpu_img.astype(int) - gpu_img).mean() < 1.0  # the same portraits up to rasterisation ties

    frames = torch.rand(9, 3, 16, 16, generator=torch.Generator().manual_seed(0))
    triplets = training_triplets(np.arange(0, 9, 2))
    _, cpu_losses, _ = train(frames, triplets, interp_config(), tmp_path / "cpu.pt", torch.device("cpu"))
    model, gpu_losses, _ = train(frames, triplets, interp_config(), tmp_path / "gpu.pt", torch.device("cuda"))
    assert next(model.parameters()).device.type == "cuda"
    np.testing.assert_allclose(gpu_losses, cpu_losses, rtol=1e-3)
    _, amp_losses, _ = train(frames, triplets, interp_config(amp=True), tmp_path / "amp.pt", torch.device("cuda"))
    np.testing.assert_allclose(amp_losses, cpu_losses, rtol=0.05)


@needs_cuda
def test_rgb_fit_on_cuda_matches_the_cpu():
    from avatarlab.preprocess.fit_rgb import evaluate_fit, fit_video
    from avatarlab.preprocess.synthetic_subject import render_subject

    cfg = compose_config(["scale=smoke", "subject=synth_talk"])
    truth = render_subject(cfg, torch.device("cuda"))
    frames, landmarks, masks = truth["video"], truth["landmarks2d"], truth["masks"]
    found = np.ones(len(frames), bool)
    errors = {}
    for name in ("cpu", "cuda"):
        device = torch.device(name)
        model, fitter, shared, result, fitted, *_ = fit_video(cfg, frames, landmarks, found, masks, device)
        assert shared["shape"].device.type == name
        images = (torch.from_numpy(frames).permute(0, 3, 1, 2).float() / 255).to(device)
        _, _, report = evaluate_fit(fitter, shared, result, fitted, images, landmarks, found, masks)
        errors[name] = report["landmark_error_px"]
    assert abs(errors["cuda"] - errors["cpu"]) < 0.25 * errors["cpu"] + 0.2
