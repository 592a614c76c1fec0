import numpy as np
import pytest
import torch
from helpers import compose_config, fake_real_set, step_cfg
from helpers.training import killed_at_optimizer_step

from avatarlab.data.schedule import scaled_schedule, synthetic_probability
from avatarlab.metrics.quality import STLPIPSDistance
from avatarlab.model.cnerf import (
    CNeRF,
    CNeRFConfig,
    camera_rays,
    head_bounds,
    positional_encoding,
    ray_distortion,
    ray_samples,
    sphere_interval,
    volume_render_features,
)
from avatarlab.model.losses import (
    RandomConvFeatures,
    VGGFeatures,
    crop_at,
    head_model_loss,
    head_patches,
    perceptual_network,
)
from avatarlab.model.renderer2d import NeuralRenderer2D
from avatarlab.render import orbit_camera

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
    net = NeuralRenderer2D(32, kind, min_channels=16)
    out = net(torch.randn(2, 32, 8, 8))
    assert out.shape == (2, 3, 64, 64) and out.min() >= 0 and out.max() <= 1
    with pytest.raises(ValueError, match="proposed' or 'baseline"):
        NeuralRenderer2D(32, "other")


def test_proposed_block_has_one_se_block_per_context_branch():
    """Seed 002, 3.1.2: the input goes through two separate SE blocks, one for the global (dilated 3x3) and one for
    the local (1x1) context; their sum is pixel-shuffled and blurred."""
    from avatarlab.model.renderer2d import ProposedStage, SqueezeExcite

    stage = NeuralRenderer2D(32, "proposed", min_channels=16).stages[0]
    assert isinstance(stage, ProposedStage)
    up = stage.up
    assert isinstance(up.se_global, SqueezeExcite) and isinstance(up.se_local, SqueezeExcite)
    assert up.se_global is not up.se_local
    convs = [m for m in up.global_branch if isinstance(m, torch.nn.Conv2d)]
    assert len(convs) == 2 and all(c.kernel_size == (3, 3) and c.dilation[0] > 1 for c in convs)
    local = [m for m in up.local_branch if isinstance(m, torch.nn.Conv2d)]
    assert len(local) == 2 and all(c.kernel_size == (1, 1) for c in local)
    assert isinstance(up.shuffle, torch.nn.PixelShuffle) and convs[-1].out_channels == 4 * 16
    # separate gates: shutting the local SE block leaves the global branch's input as it was
    x = torch.randn(1, 32, 8, 8)
    with torch.no_grad():
        g = up.global_branch(up.se_global(x))
        torch.nn.init.constant_(up.se_local.fc[2].weight, 0)
        torch.nn.init.constant_(up.se_local.fc[2].bias, -30)
        assert up.se_local(x).abs().max() < 1e-6
        torch.testing.assert_close(up.global_branch(up.se_global(x)), g)


def test_baseline_is_headnerfs_block():
    """HeadNeRF's renderer: RGB from the input feature map (1x1 conv, bilinear x2 + blur); per stage conv1x1 C->2C,
    LeakyReLU, conv1x1 2C->4C, LeakyReLU, + input x4, PixelShuffle, blur, conv1x1 -> max(C/2, min) + LeakyReLU."""
    from avatarlab.model.renderer2d import BaselineStage

    net = NeuralRenderer2D(64, "baseline", min_channels=16)
    assert (net.input_rgb.in_channels, net.input_rgb.out_channels) == (64, 3)
    widths = []
    for stage in net.stages:
        assert isinstance(stage, BaselineStage)
        c = stage.conv1.in_channels
        assert (stage.conv1.out_channels, stage.conv2.out_channels) == (2 * c, 4 * c)
        assert stage.conv1.kernel_size == stage.conv2.kernel_size == stage.reduce.kernel_size == (1, 1)
        widths.append(stage.reduce.out_channels)
    assert widths == [32, 16, 16]
    # LeakyReLU(0.2) after the channel-reducing conv: negative features are 0.2 x the conv's output
    stage = net.stages[0]
    x = torch.randn(1, 64, 4, 4)
    with torch.no_grad():
        feat, _ = stage(x, torch.zeros(1, 3, 8, 8))
        y = torch.nn.functional.leaky_relu(stage.conv2(torch.nn.functional.leaky_relu(stage.conv1(x), 0.2)), 0.2)
        pre = stage.reduce(stage.blur(stage.shuffle(y + x.repeat(1, 4, 1, 1))))
    torch.testing.assert_close(feat, torch.nn.functional.leaky_relu(pre, 0.2))


def small_nerf(**kw):
    cfg = CNeRFConfig(frequencies=2, depth=3, width=16, skip_layer=1, feature_channels=4, samples=4, n_shape=3,
                      n_expression=2, n_texture=2, **kw)
    torch.manual_seed(0)
    return CNeRF(cfg)


def test_cnerf_conditioning_changes_density_and_features():
    nerf = small_nerf()
    pts, idx = torch.rand(5, 3) * 0.1, torch.zeros(5, dtype=torch.long)
    g0, a0 = torch.zeros(1, 3 + 12 + 2), torch.zeros(1, 2 + 27)
    s0, f0 = nerf(pts, idx, g0, a0)
    s1, f1 = nerf(pts, idx, g0 + 1, a0)
    s2, f2 = nerf(pts, idx, g0, a0 + 1)
    assert not torch.allclose(s0, s1) and torch.allclose(s0, s2), "texture/lighting enter after the density"
    assert not torch.allclose(f0, f2)
    assert len(nerf.frozen_prefix(2)) == 4


def test_per_sample_projection_equals_the_concatenated_layers():
    """Projecting each sample's code once is the same arithmetic as the dissertation's per-point concatenation."""
    nerf = small_nerf()
    pts = torch.rand(2, 7, 3) * 0.3 - 0.15
    geo, app = torch.randn(2, 17), torch.randn(2, 29)
    dense_s, dense_f = nerf.forward_dense(pts, geo, app)
    idx = torch.arange(2).repeat_interleave(7)
    split_s, split_f = nerf(pts.reshape(-1, 3), idx, geo, app)
    torch.testing.assert_close(split_s, dense_s.reshape(-1), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(split_f, dense_f.reshape(-1, 4), rtol=1e-5, atol=1e-6)


def test_the_mlp_alone_computes_in_bfloat16_when_asked():
    """model.mlp_precision=bfloat16: the MLP's products run in bfloat16 (its outputs differ from float32 by bfloat16's
    rounding, not more) and come back float32; unset again, it is float32 to the bit."""
    nerf = small_nerf()
    pts, idx = torch.rand(40, 3) * 0.3 - 0.15, torch.arange(2).repeat_interleave(20)
    geo, app = torch.randn(2, 17), torch.randn(2, 29)
    s32, f32 = nerf(pts, idx, geo, app)
    nerf.compute_dtype = torch.bfloat16
    s16, f16 = nerf(pts, idx, geo, app)
    assert s16.dtype == f16.dtype == torch.float32
    assert not torch.equal(f16, f32), "the products ran in bfloat16"
    torch.testing.assert_close(f16, f32, rtol=0.05, atol=0.05)
    nerf.compute_dtype = None
    assert torch.equal(nerf(pts, idx, geo, app)[1], f32)


def test_rays_are_sampled_inside_the_heads_bounding_sphere():
    cam = orbit_camera(1.0, 0.0, 0.0, image_size=(64, 64))
    origins, dirs = camera_rays(cam, (8, 8))
    near, far, hit = sphere_interval(origins, dirs, torch.zeros(3), torch.tensor(0.2))
    centre = 4 * 8 + 4  # the ray next to the optical axis: enters ~0.2 m before the centre, leaves ~0.2 m after
    assert hit[0, centre] and near[0, centre] == pytest.approx(0.8, abs=0.01)
    assert far[0, centre] == pytest.approx(1.2, abs=0.01)
    for r in range(64):  # a ray hits exactly when one of its points is inside the sphere
        pts = origins[0, r] + dirs[0, r] * torch.linspace(0.5, 1.5, 400)[:, None]
        assert bool(hit[0, r]) == bool((pts.norm(dim=-1) < 0.2).any())
    depths = ray_samples(near[hit], far[hit], 8, stratified=True)
    assert (depths >= near[hit][:, None]).all() and (depths <= far[hit][:, None]).all()


def test_every_posed_head_lies_inside_its_rays_interval(head_model):
    """The bounding sphere covers the head under every pose the data has (random shapes and expressions in [-2, 2],
    the config's neck and jaw ranges): each vertex lies between where its ray enters and leaves the sphere."""
    cfg = compose_config(["scale=tiny"])
    centre, radius = head_bounds(head_model, cfg.synthetic.neck_deg, cfg.synthetic.jaw_open[1])
    g = torch.Generator().manual_seed(5)
    params = head_model.zeros(16)
    params["shape"] = torch.rand(16, 100, generator=g) * 4 - 2
    params["expression"] = torch.rand(16, 50, generator=g) * 4 - 2
    limits = torch.tensor(list(cfg.synthetic.neck_deg), dtype=torch.float32) * np.pi / 180
    params["pose"][:, 3:6] = (torch.rand(16, 3, generator=g) * 2 - 1) * limits
    params["pose"][:, 6] = torch.rand(16, generator=g) * cfg.synthetic.jaw_open[1]
    with torch.no_grad():
        verts = head_model(params["shape"], params["expression"], params["pose"]).vertices
    cam = orbit_camera(torch.full((16,), 1.0), torch.linspace(-10, 10, 16), 0.0, image_size=(64, 64))
    cam_pts = cam.world_to_camera(verts)
    dirs = torch.einsum("bij,bnj->bni", cam.R.transpose(1, 2), cam_pts / cam_pts[..., 2:])  # z = 1 directions
    origins = (-torch.einsum("bij,bj->bi", cam.R.transpose(1, 2), cam.t))[:, None].expand_as(dirs)
    near, far, hit = sphere_interval(origins, dirs, torch.tensor(centre), torch.tensor(radius))
    z = cam_pts[..., 2]
    assert hit.all() and (z >= near - 1e-5).all() and (z <= far + 1e-5).all()
    assert radius < 0.3, "a tight sphere: samples are spent on the head, not on empty space"


def test_ray_distortion_is_low_for_a_surface_and_not_lowered_by_transparency():
    """`finetune.w_distortion`'s term: a ray whose weight sits in one bin scores below one whose weight is spread
    along it; scaling a ray's density down (more transparent, same shape) does not lower it below the same shape at
    full opacity divided by that opacity (the opacity is held fixed in it), and its gradient reaches the density."""
    depths = torch.linspace(1.0, 1.3, 16)[None].expand(2, -1)
    near, far = torch.full((2,), 1.0), torch.full((2,), 1.3)
    surface = torch.zeros(2, 16)
    surface[:, 8] = 1e4
    spread = torch.full((2, 16), 20.0)
    thin, thick = ray_distortion(surface, depths, near, far), ray_distortion(spread, depths, near, far)
    assert float(thin.max()) < 0.03 < 0.15 < float(thick.min())
    faint = spread * 0.05
    opacity = lambda s: 1 - torch.exp(-(s * 0.02).sum(-1))  # noqa: E731  (bins 2 cm apart)
    per_opacity = ray_distortion(faint, depths, near, far) / opacity(faint)
    assert float(per_opacity.min()) > 0.2, "a transparent spread ray still pays for its spread"
    sigma = spread.clone().requires_grad_(True)
    ray_distortion(sigma, depths, near, far).sum().backward()
    assert sigma.grad is not None and float(sigma.grad.abs().sum()) > 0
    from avatarlab.model.cnerf import compositing_weights  # weights computed once by the caller: the same term
    again = ray_distortion(spread, depths, near, far, compositing_weights(spread, depths))
    assert torch.equal(again, thick)


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
    from torchvision.models import vgg16

    torch.save(vgg16().state_dict(), tmp_path / "vgg16.pth")
    vgg = perceptual_network(str(tmp_path / "vgg16.pth"))
    assert isinstance(vgg, VGGFeatures) and len(vgg(torch.rand(1, 3, 32, 32))) == 4
    with pytest.raises(FileNotFoundError, match="nothere.pth"):
        VGGFeatures(tmp_path / "nothere.pth")


def test_st_lpips_term_is_a_differentiable_distance():
    """The ST-LPIPS term (`finetune.w_st_lpips`): zero for the target itself, larger for a blurred render than for a
    slightly noisy one, and its gradient reaches the render; on head windows it still sees the difference."""
    torch.manual_seed(0)
    target = torch.rand(2, 3, 64, 64)
    target = torch.nn.functional.avg_pool2d(target, 3, 1, 1)  # some structure at several scales
    mask = torch.zeros(2, 1, 64, 64)
    mask[:, :, 16:48, 16:48] = 1
    before = torch.get_rng_state()
    whole = STLPIPSDistance()
    assert torch.equal(torch.get_rng_state(), before), "building it must not move the run's random stream (resumes)"
    assert not any(p.requires_grad for p in whole.parameters())
    assert float(whole.distance(target, target, mask)) == pytest.approx(0.0, abs=1e-6)
    blurred = torch.nn.functional.avg_pool2d(target, 7, 1, 3)
    noisy = (target + 0.01 * torch.randn_like(target)).clamp(0, 1)
    assert float(whole.distance(blurred, target, mask)) > float(whole.distance(noisy, target, mask)) > 0
    pred = blurred.clone().requires_grad_(True)
    whole.distance(pred, target, mask).backward()
    assert pred.grad is not None and float(pred.grad.abs().sum()) > 0
    windows = STLPIPSDistance(crop=32)
    assert windows.crop == 32 and float(windows.distance(blurred, target, mask)) > 0
    assert float(windows.distance(target, target, mask)) == pytest.approx(0.0, abs=1e-6)


def test_head_windows_lie_inside_the_image_around_the_head():
    images = torch.rand(64, 3, 40, 50)
    mask = torch.zeros(64, 1, 40, 50)
    mask[:, :, 30:34, 40:44] = 1  # a small head near the bottom-right corner
    corners = head_patches(mask, 16, generator=torch.Generator().manual_seed(0))
    assert corners.shape == (64, 2)
    assert (corners[:, 0] >= 0).all() and (corners[:, 0] <= 40 - 16).all()
    assert (corners[:, 1] >= 0).all() and (corners[:, 1] <= 50 - 16).all()
    # every window holds its centre pixel, drawn from the mask
    assert ((corners[:, 0] + 16 > 30) & (corners[:, 1] + 16 > 40)).all()
    crops = crop_at(images, corners, 16)
    assert crops.shape == (64, 3, 16, 16)
    r, c = corners[5].tolist()
    assert torch.equal(crops[5], images[5, :, r:r + 16, c:c + 16])


def pretrain_cfg(tmp_path, name, *extra):
    from avatarlab.pretrain import train as pretrain

    if not (tmp_path / "real").is_dir():
        fake_real_set(tmp_path / "real")
    return step_cfg(pretrain, ["scale=smoke", "strategy=beta4", "strategy.init=null",
                               f"pretrain.real_subject_dir={tmp_path / 'real'}", "tracking.enabled=false",
                               "pretrain.checkpoint_every=2", f"pretrain.out_dir={tmp_path / name}", *extra])


def short_training(tmp_path, name, *extra):
    from avatarlab.pretrain import train as pretrain

    return pretrain.pretrain_model(pretrain_cfg(tmp_path, name, *extra), torch.device("cpu"))


def test_cosine_learning_rate_decay_falls_from_the_first_to_the_last_iteration():
    from avatarlab.data.schedule import Schedule
    from avatarlab.training.loop import Recipe, lr_factor

    schedule = Schedule(M=100, N=110, p_min=0.0, p_max=0.0, mouth_from=None)
    constant = Recipe(schedule=schedule, start=100, batch=1, lr=1e-3, offset_lr=1e-3)
    assert [lr_factor(constant, k) for k in (101, 105, 110)] == [1.0, 1.0, 1.0]
    cosine = Recipe(schedule=schedule, start=100, batch=1, lr=1e-3, offset_lr=1e-3, lr_decay="cosine", lr_final=0.1)
    factors = [lr_factor(cosine, k) for k in range(101, 111)]
    assert factors[0] == pytest.approx(1.0) and factors[-1] == pytest.approx(0.1)
    assert all(a > b for a, b in zip(factors, factors[1:])), "falls at every iteration"
    assert lr_factor(cosine, 105.5) == pytest.approx(0.55), "half-way: half-way between 1 and lr_final"
    with pytest.raises(ValueError, match="lr_decay"):
        lr_factor(Recipe(schedule=schedule, start=100, batch=1, lr=1e-3, offset_lr=1e-3, lr_decay="step"), 101)


def test_the_st_lpips_weight_falls_linearly_to_its_last_iteration_only_when_asked():
    from avatarlab.data.schedule import Schedule
    from avatarlab.training.loop import Recipe, st_lpips_weight

    schedule = Schedule(M=100, N=111, p_min=0.0, p_max=0.0, mouth_from=None)
    flat = Recipe(schedule=schedule, start=100, batch=1, lr=1e-3, offset_lr=1e-3, w_st_lpips=0.02)
    assert [st_lpips_weight(flat, k) for k in (101, 106, 111)] == [0.02, 0.02, 0.02]
    for decay, last in ((1.0, 0.0), (0.5, 0.01)):
        falling = Recipe(schedule=schedule, start=100, batch=1, lr=1e-3, offset_lr=1e-3, w_st_lpips=0.02,
                         st_lpips_decay=decay)
        weights = [st_lpips_weight(falling, k) for k in range(101, 112)]
        assert weights[0] == pytest.approx(0.02) and weights[-1] == pytest.approx(last, abs=1e-12)
        assert weights[5] == pytest.approx((0.02 + last) / 2), "half-way: half-way between the first and the last"
        assert all(a > b for a, b in zip(weights, weights[1:]))


@pytest.mark.slow
@pytest.mark.parametrize("decay, ema", [("none", 0.0), ("cosine", 0.0), ("none", 0.5)])
def test_pretraining_resumes_exactly_after_a_kill(tmp_path, monkeypatch, decay, ema):
    from avatarlab.pretrain import train as pretrain

    settings = [f"pretrain.lr_decay={decay}", "pretrain.lr_final=0.05", f"pretrain.ema_decay={ema}"]
    full_net, full, _ = short_training(tmp_path, "full", *settings)
    assert [h["step"] for h in full.history] == list(range(1, 10))
    assert [h["n_synthetic"] for h in full.history][:6] == [2] * 6  # p = 1 up to M
    assert not (tmp_path / "full" / "checkpoint.pt").exists(), "a finished step leaves no checkpoint"
    expected_final = 1.0 if decay == "none" else 0.05
    assert full.history[0]["lr_factor"] == 1.0 and full.history[-1]["lr_factor"] == pytest.approx(expected_final)
    cfg = pretrain_cfg(tmp_path, "killed", *settings)
    with killed_at_optimizer_step(monkeypatch, 5):
        pretrain.pretrain_model(cfg, torch.device("cpu"))
    saved = torch.load(tmp_path / "killed" / "checkpoint.pt", weights_only=True)
    assert saved["step"] == 4 and saved["seconds"] > 0
    assert (saved["ema"] is not None) == (ema > 0), "the checkpoint carries the weight average when there is one"
    net, resumed, report = pretrain.pretrain_model(cfg, torch.device("cpu"))
    for p, q in zip(full_net.parameters(), net.parameters()):
        torch.testing.assert_close(p, q)
    # the same trajectory; float32 kernels may differ in the last bits between two runs in one busy process (seen
    # once under pytest-xdist, at step 4, before the kill: 7.3775081e-3 against 7.3775076e-3)
    assert [h["loss"] for h in resumed.history] == pytest.approx([h["loss"] for h in full.history], rel=1e-6, abs=0)
    assert report["iterations"] == 9 and resumed.seconds > saved["seconds"], "time adds up across resumes"
    assert report["samples_per_second"] == pytest.approx(9 * 2 / resumed.seconds)


@pytest.mark.slow
def test_a_checkpoint_of_other_work_is_not_resumed(tmp_path):
    """A checkpoint left by other settings (or code, or data) is ignored: the run trains from iteration 0."""
    from avatarlab.runtime.provenance import fingerprint
    from avatarlab.training.checkpoint import Checkpoint

    _, first, _ = short_training(tmp_path, "run")
    stale = Checkpoint(tmp_path / "run" / "checkpoint.pt", fingerprint({"other": 1}, "code", {}))
    stale.save({"step": 8, "seconds": 1.0, "history": []})
    assert Checkpoint(stale.path, "another fingerprint").load() is None
    _, again, report = short_training(tmp_path, "run")
    assert report["iterations"] == 9 and again.history[0]["step"] == 1, "trained from iteration 0, not resumed"
    assert [h["loss"] for h in again.history] == pytest.approx([h["loss"] for h in first.history], rel=1e-6, abs=0)
    _, other_lr, _ = short_training(tmp_path, "run", "pretrain.lr=0.01")
    assert other_lr.history[-1]["loss"] != first.history[-1]["loss"]


@pytest.mark.slow
def test_a_resolution_tier_continues_the_final_recipe_at_twice_the_size(tmp_path):
    """The tier step as the workflow runs it (Plan's overrides, the final recipe's strategy): the parent's weights
    at twice the image and feature-map size, from the parent's last iteration, for the tier's iterations."""
    from avatarlab.model.head_nerf import load_model_file
    from avatarlab.pretrain import train as pretrain
    from avatarlab.workflow.targets import resolution_tiers

    smoke = compose_config(["scale=smoke"]).scale
    parent_net, _, parent = short_training(tmp_path, "beta6_from_alpha2")  # beta4 schedule from scratch: 6 + 3
    scale = {**smoke, "resolution_tiers": [128], "resolution_tier_iterations": 2}
    (tier,) = resolution_tiers("beta6_from_alpha2", scale)
    assert (tier.name, tier.parent, tier.start, tier.size) == ("beta6_from_alpha2_128px", "beta6_from_alpha2", 9, 128)
    cfg = step_cfg(pretrain, ["scale=smoke", "strategy=beta6", *tier.overrides(), "tracking.enabled=false",
                              f"pretrain.real_subject_dir={tmp_path / 'real'}", f"pretrain.out_dir={tmp_path / tier.name}",
                              f"pretrain.init_model={tmp_path / 'beta6_from_alpha2' / 'model.pt'}"])
    net, result, report = pretrain.pretrain_model(cfg, torch.device("cpu"))
    assert [h["step"] for h in result.history] == [10, 11] and report["start_step"] == 9
    assert report["image_size"] == 128 and net.feature_size == 16 and parent_net.feature_size == 8
    loaded, content = load_model_file(tmp_path / tier.name / "model.pt")
    assert content["spec"]["feature_size"] == 16 and content["step"] == 11
    assert loaded.feature_size == 16, "the tier model renders 128² (its training loss was taken at 128²)"
    with pytest.raises(ValueError, match="must rise above pretrain_image_size"):
        resolution_tiers("x", {**smoke, "resolution_tiers": [32], "resolution_tier_iterations": 2})


def test_paper_scale_sizes_match_the_dissertation():
    """conf/scale/paper.yaml is the dissertation's set-up (DESIGN.md sections 3-4), number for number."""
    s = compose_config(["scale=paper"]).scale
    assert (s.pretrain_alpha_iterations, s.pretrain_beta_iterations, s.pretrain_batch) == (310000, 2500, 64)
    assert (s.pretrain_image_size, s.pretrain_feature_size) == (128, 16)  # the 14 models and the ablations at 128²
    assert list(s.resolution_tiers) == [256, 512] and s.resolution_tier_iterations == 300000  # final recipe, 2.4
    assert (s.nerf_frequencies, s.nerf_depth, s.nerf_width, s.nerf_skip_layer) == (10, 8, 384, 5)
    assert (s.nerf_feature_channels, s.nerf_samples) == (256, 64)
    assert list(s.synthetic_neck_deg) == [80, 60, 80]
    assert (s.renderer_experiment_iterations, s.renderer_experiment_image_size) == (30000, 128)
    assert s.renderer_experiment_image_size // s.renderer_experiment_feature_size == 8  # three x2 stages
    assert (s.finetune_iterations, s.finetune_test_frames, s.mouth_open_frames) == (1000, 350, 30)
    assert (s.fit_rigid_iterations, s.fit_keyframe_iterations) == (200, 800)
    assert s.speech_speakers == 34 and s.speech_window_hidden == 3000 and s.speech_epochs == 400  # seed 000


def test_device_comes_from_the_config():
    from avatarlab.runtime.config import resolve_device

    assert resolve_device(compose_config(["device=cpu"])) == torch.device("cpu")
    expected = "cuda" if torch.cuda.is_available() else "cpu"
    assert resolve_device(compose_config([])).type == expected  # the default is auto
    if not torch.cuda.is_available():
        with pytest.raises(RuntimeError, match="device=cuda requested but CUDA is not available"):
            resolve_device(compose_config(["device=cuda"]))




@pytest.mark.slow
def test_mixed_precision_training_runs_and_stays_close(tmp_path):
    """amp=true: bfloat16 autocast on the CPU (float16 + GradScaler on CUDA); the run trains like float32."""
    _, full, _ = short_training(tmp_path, "fp32", "amp=false")
    net, mixed, _ = short_training(tmp_path, "amp", "amp=true")
    assert len(mixed.history) == len(full.history)
    assert all(np.isfinite(h["loss"]) for h in mixed.history)
    assert mixed.history[0]["loss"] == pytest.approx(full.history[0]["loss"], rel=0.05)
    assert mixed.history[-1]["psnr"] == pytest.approx(full.history[-1]["psnr"], abs=1.0)
    assert next(net.parameters()).dtype == torch.float32  # master weights stay float32


@pytest.mark.slow
def test_a_bfloat16_mlp_trains_like_float32_and_leaves_the_model_float32(tmp_path):
    """model.mlp_precision=bfloat16 (the CNeRF MLP alone under bfloat16 autocast): a different but close run, and the
    trained network renders in float32 afterwards (evaluation does not inherit the training precision)."""
    full_net, full, _ = short_training(tmp_path, "fp32")
    net, mixed, _ = short_training(tmp_path, "mlp", "model.mlp_precision=bfloat16")
    assert [h["loss"] for h in mixed.history] != [h["loss"] for h in full.history], "the setting reached the MLP"
    assert mixed.history[0]["loss"] == pytest.approx(full.history[0]["loss"], rel=0.05)
    assert mixed.history[-1]["psnr"] == pytest.approx(full.history[-1]["psnr"], abs=1.0)
    assert net.nerf.compute_dtype is None and next(net.parameters()).dtype == torch.float32


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
def test_training_on_cuda_matches_the_cpu(tmp_path):
    _, cpu, _ = short_training(tmp_path, "cpu", "device=cpu")
    net, gpu, _ = short_training(tmp_path, "cuda", "device=cuda")
    assert next(net.parameters()).device.type == "cuda"
    assert gpu.history[-1]["psnr"] == pytest.approx(cpu.history[-1]["psnr"], abs=0.5)


def test_controlled_sweeps_move_one_control_and_measure_whether_a_model_follows_it():
    """pretrain/controls.py (figs. 27, 29-32): each variant differs from the frame in its control only; the response
    correlation is 1 for a model that changes as the head model does, 0 for one that ignores the control."""
    from omegaconf import OmegaConf

    from avatarlab.pretrain.controls import response_correlation, variants
    from avatarlab.render.camera import orbit_camera

    cfg = OmegaConf.create({"jaw_rad": [0.0, 0.2, 0.4], "neck_deg": [-20, 0, 20], "distance_offsets": [-0.1, 0, 0.1],
                            "expression_values": [-1, 0, 1]})
    params = {"shape": torch.randn(1, 5), "expression": torch.randn(1, 4), "pose": torch.randn(1, 15) * 0.1,
              "texture": torch.randn(1, 3), "lighting": torch.randn(1, 9, 3)}
    camera = orbit_camera(torch.tensor([1.0]), image_size=(32, 32), focal=80.0)
    jaw, cams, values = variants(params, camera, "jaw", cfg)
    assert values == [0.0, 0.2, 0.4] and torch.equal(jaw["pose"][:, 6], torch.tensor(values))
    keep = torch.ones(15, dtype=torch.bool)
    keep[6] = False
    assert torch.equal(jaw["pose"][:, keep], params["pose"][:, keep].expand(3, -1))
    assert torch.equal(jaw["expression"], params["expression"].expand(3, -1)) and torch.equal(cams.t, camera.t.expand(3, -1))
    neck, _, _ = variants(params, camera, "neck", cfg)
    assert torch.allclose(neck["pose"][:, 4], torch.deg2rad(torch.tensor([-20.0, 0, 20])))
    far, cams, _ = variants(params, camera, "distance", cfg)
    assert torch.allclose(cams.t[:, 2] - camera.t[0, 2], torch.tensor([-0.1, 0, 0.1]))
    assert torch.equal(far["pose"], params["pose"].expand(3, -1))
    fitted, _, values = variants(params, camera, "fitted", cfg)
    assert values == [0.0] and torch.equal(fitted["pose"], params["pose"])
    truth = torch.rand(3, 3, 8, 8)
    masks = torch.ones(3, 1, 8, 8)
    assert response_correlation(truth * 0.5 + 0.1, truth, masks) == pytest.approx(1.0)
    assert response_correlation(truth[:1].expand(3, -1, -1, -1), truth, masks) == 0.0
    assert response_correlation(truth[:1], truth[:1], masks[:1]) is None
