"""Training throughput of the parametric head model and its rendering speed (issue: pretraining benchmark).

    python benchmarks/bench_pretrain.py [--scale tiny] [--iterations 5] [--threads 2]

Prints, for the chosen scale's sizes: samples/s of a training step (synthetic samples rendered by the head model,
CNeRF + 2D renderer forward and backward), the CNeRF MLP's achieved GFLOPS (from an exact count of its linear
layers), and the inference frame rate of CNeRF + renderer at the scale's image size (and at 128x128).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def mlp_flops_per_point(nerf) -> int:
    """Multiply-adds x 2 of every Linear layer of the CNeRF MLP for one sample point (forward)."""
    return sum(2 * m.in_features * m.out_features for m in nerf.modules() if isinstance(m, torch.nn.Linear))


def training_setup(cfg, image_size: int, feature_size: int, batch: int) -> SimpleNamespace:
    """The head model's synthetic generator and a CNeRF + proposed renderer with its optimiser at the config's sizes:
    `sample()` draws a batch of synthetic samples, `train_step(sample)` is one forward + backward + Adam step."""
    from avatarlab.data.synthetic import SyntheticGenerator
    from avatarlab.headmodel import load_head_model
    from avatarlab.model.losses import RandomConvFeatures, head_model_loss
    from avatarlab.train.pretrain import HeadNeRFModel, codes, composite, nerf_config

    head = load_head_model(cfg.head_model)
    real = {"shape": torch.zeros(4, head.n_shape), "expression": torch.zeros(4, head.n_expression),
            "texture": torch.zeros(4, head.n_texture), "lighting": torch.zeros(4, 9, 3)}
    real["lighting"][:, 0] = 2.8
    gen = SyntheticGenerator(head, real, cfg.synthetic, image_size, (0.5, 0.5, 0.5))
    torch.manual_seed(0)
    net = HeadNeRFModel(nerf_config(cfg, head), "proposed", feature_size)
    optim = torch.optim.Adam(net.parameters(), lr=1e-4)
    feats = RandomConvFeatures()
    g = torch.Generator().manual_seed(0)

    def train_step(s):
        geometry, appearance = codes(s["params"], s["lighting"])
        optim.zero_grad()
        pred = net(geometry, appearance, s["camera"])
        loss = head_model_loss(pred, composite(s["images"], s["masks"]), s["masks"], feats, {}, {},
                               torch.zeros(batch, dtype=torch.bool))["total"]
        loss.backward()
        optim.step()

    return SimpleNamespace(gen=gen, net=net, real=real, g=g, sample=lambda: gen.sample(batch, g),
                           train_step=train_step)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scale", default="tiny")
    parser.add_argument("--iterations", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    from conftest import compose_config

    from avatarlab.train.pretrain import codes

    cfg = compose_config([f"scale={args.scale}"])
    size, fsize, batch = cfg.scale.pretrain_image_size, cfg.scale.pretrain_feature_size, cfg.scale.pretrain_batch
    run = training_setup(cfg, size, fsize, batch)
    gen, net, real, g = run.gen, run.net, run.real, run.g

    def step():  # synthetic rendering included, as in training
        run.train_step(run.sample())

    step()
    t0 = time.perf_counter()
    for _ in range(args.iterations):
        step()
    per_step = (time.perf_counter() - t0) / args.iterations
    points = batch * fsize * fsize * cfg.model.samples
    flops = 3 * points * mlp_flops_per_point(net.nerf)  # forward + backward ~ 3x forward
    mlp_time = time.perf_counter()
    x = torch.rand(batch, fsize * fsize * cfg.model.samples, 3, requires_grad=False)
    gc, ac = codes(gen.sample(batch, g)["params"], real["lighting"][:batch].repeat(batch // 4 + 1, 1, 1)[:batch])
    sigma, feat = net.nerf(x, gc, ac)
    (sigma.sum() + feat.sum()).backward()
    mlp_time = time.perf_counter() - mlp_time
    print(f"scale {args.scale}: batch {batch}, image {size}x{size}, feature map {fsize}x{fsize}, "
          f"{cfg.model.samples} samples/ray, MLP {cfg.model.depth}x{cfg.model.width}; {args.threads} threads")
    print(f"training step: {per_step * 1000:.0f} ms, {batch / per_step:.1f} samples/s "
          f"(synthetic rendering included)")
    print(f"CNeRF MLP forward+backward: {flops / 1e9:.2f} GFLOP in {mlp_time * 1000:.0f} ms = "
          f"{flops / 1e9 / mlp_time:.1f} GFLOPS")
    net.eval()
    for res in sorted({size, 128}):
        s = gen.sample(1, g)
        geometry, appearance = codes(s["params"], s["lighting"])
        cam = s["camera"]
        cam = type(cam)(K=cam.K * torch.tensor([[res / size], [res / size], [1.0]]), R=cam.R, t=cam.t,
                        image_size=(res, res))
        net.feature_size = res // 8
        with torch.no_grad():
            net(geometry, appearance, cam, stratified=False)
            t0 = time.perf_counter()
            for _ in range(5):
                net(geometry, appearance, cam, stratified=False)
        fps = 5 / (time.perf_counter() - t0)
        print(f"render {res}x{res} (feature map {res // 8}x{res // 8}): {fps:.1f} frames/s")
    net.feature_size = fsize


if __name__ == "__main__":
    main()
