"""Renders per second of the head model + pure-PyTorch rasterizer on this machine (batch 8).

    python benchmarks/bench_render.py [--sizes 64 128 256] [--batch 8] [--repeats 5] [--threads 2] [--backward]

Prints one line per resolution: forward (and optionally forward+backward) renders/s and ms per batch.
"""
from __future__ import annotations

import argparse
import time

import torch

from avatarlab.headmodel import ProceduralSpec, load_procedural_head
from avatarlab.headmodel.flame import HeadModel
from avatarlab.render import orbit_camera
from avatarlab.render.head_renderer import HeadRenderer


def bench(renderer, model, size: int, batch: int, repeats: int, backward: bool) -> float:
    torch.manual_seed(0)
    params = model.zeros(batch)
    params["shape"].normal_()
    params["expression"].normal_()
    params["pose"][:, 3:6].uniform_(-0.3, 0.3)
    camera = orbit_camera(1.0, 0.0, 0.0, image_size=(size, size), batch=batch)
    if backward:
        params = {k: v.requires_grad_() for k, v in params.items()}

    def step():
        out = renderer(params, camera)
        if backward:
            out.rgb.mean().backward()

    step()  # warm-up
    start = time.perf_counter()
    for _ in range(repeats):
        step()
    return (time.perf_counter() - start) / repeats


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256])
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--backward", action="store_true", help="also time forward+backward (fitting cost)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    data = load_procedural_head(ProceduralSpec())
    model = HeadModel(data)
    renderer = HeadRenderer(model)
    print(f"head model {data.source}: {data.v_template.shape[0]} vertices, {data.faces.shape[0]} triangles; "
          f"batch {args.batch}, {args.threads} threads, torch {torch.__version__}")
    for size in args.sizes:
        for backward in ([False, True] if args.backward else [False]):
            seconds = bench(renderer, model, size, args.batch, args.repeats, backward)
            mode = "forward+backward" if backward else "forward"
            print(f"{size:>4}x{size:<4} {mode:<17} {args.batch / seconds:8.1f} renders/s  "
                  f"{1000 * seconds:8.1f} ms/batch")


if __name__ == "__main__":
    main()
