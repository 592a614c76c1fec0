import numpy as np
import pytest
import torch

from avatarlab.evaluate.metrics import LPIPS, identity_similarity, load_backbone, lpips_metric, psnr, ssim
from avatarlab.train.finetune import split


def test_split_keeps_the_last_frames_for_testing():
    fitted = np.ones(20, bool)
    fitted[3] = fitted[18] = False
    train, test = split(20, fitted, 5)
    assert list(test) == [15, 16, 17, 19] and 3 not in train and max(train) == 14
    train, test = split(6, np.ones(6, bool), 350)  # never more than half the video
    assert list(test) == [3, 4, 5] and list(train) == [0, 1, 2]


def test_psnr_ssim_values():
    a = torch.full((1, 3, 32, 32), 0.5)
    assert psnr(a + 0.1, a) == pytest.approx(20.0, abs=1e-3)
    assert ssim(a, a) == pytest.approx(1.0, abs=1e-6)


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
    with pytest.raises(FileNotFoundError, match="missing.pth"):
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


@pytest.mark.slow
def test_finetuning_freezes_four_layers_and_keeps_identity_fixed(tmp_path):
    from conftest import compose_config
    from test_pretrain import fake_real_set

    from avatarlab.train import pretrain
    from avatarlab.train.finetune import finetune_config

    fake_real_set(tmp_path / "portraits")
    base = ["scale=smoke", "tracking.enabled=false", "model.depth=5"]
    parent = pretrain.train(compose_config(base + [f"pretrain.real_subject_dir={tmp_path / 'portraits'}",
                                                   f"pretrain.out_dir={tmp_path / 'alpha1'}"]))
    torch.save({"model": parent["net"].state_dict(), "step": parent["step"]}, tmp_path / "alpha1.pt")
    # a subject as fit_rgb writes it in video mode: shape, texture and lighting shared by all frames
    subject = tmp_path / "subject"
    fake_real_set(subject, count=6)
    with np.load(subject / "fit_rgb.npz") as f:
        fit = dict(f)
    fit.update(shape=fit["shape"][0], texture=fit["texture"][0], lighting=fit["lighting"][0])
    np.savez(subject / "fit_rgb.npz", **fit)
    cfg = compose_config(base + [f"finetune.subject_dir={subject}", f"finetune.init_model={tmp_path / 'alpha1.pt'}",
                                 f"finetune.out_dir={tmp_path / 'avatar'}"])
    result = pretrain.train(finetune_config(cfg, np.arange(4)))
    assert result["start_step"] == parent["step"] and len(result["real"]) == 4
    assert set(result["offsets"].keys()) == {"pose", "expression", "lighting"}, "shape and texture stay fixed"
    p_syn = [h["p_synthetic"] for h in result["history"] if h["step"] > result["start_step"]]
    assert p_syn[0] > p_syn[-1] and p_syn[-1] == pytest.approx(0.0), "synthetic share decays linearly to 0"
    before, after = parent["net"].nerf, result["net"].nerf
    for k in range(5):
        same = torch.equal(before.layers[k].weight, after.layers[k].weight)
        assert same == (k < 4), f"MLP layer {k} should be {'frozen' if k < 4 else 'trained'}"
