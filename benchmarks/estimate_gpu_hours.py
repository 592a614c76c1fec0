"""GPU-hours of the full reproduction at `paper` scale, from a measured CPU step and exact FLOP counts.

    python benchmarks/estimate_gpu_hours.py [--batch 2] [--threads 2] [--subjects 10] [--out docs/gpu_hours.md]

What it does:
1. builds the CNeRF + 2D renderer at the paper sizes (conf/scale/paper.yaml: 8x384 MLP, 64 samples, 32² feature map
   -> 256² image) and runs training steps on synthetic samples at a small batch on this CPU (timed);
2. counts the FLOPs of one step (forward + backward, every matmul and convolution) with torch's FlopCounterMode and
   scales them to the paper batch of 64 (the cost is linear in the batch);
3. multiplies by the iterations of every job in the workflow's job graph (2 alpha x 310 000, 12 beta x 2 500,
   2 renderer runs x 30 000 at 128², per subject 14 + 2 fine-tunings x 1 000) and divides by a GPU's sustained
   throughput, for a stated fraction of its peak.

The result is an estimate with its assumptions printed beside it, not a measurement on a GPU (none here).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch
from torch.utils.flop_counter import FlopCounterMode

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

# Peak dense throughput (TFLOPS) of the GPU the dissertation used, and of a common data-centre GPU.
GPUS = {"RTX 4090 (fp32)": 82.6, "RTX 4090 (bf16 tensor cores, AMP)": 165.2, "A100 (tf32)": 156.0}
SUSTAINED = 0.30  # fraction of peak a NeRF MLP + conv renderer step sustains (small matmuls, gathers, launches)


def paper_step(image_size: int, feature_size: int, batch: int, threads: int, steps: int):
    """(seconds per step, FLOPs per step) of a paper-size training step at `batch` on this CPU."""
    torch.set_num_threads(threads)
    from bench_pretrain import training_setup
    from helpers import compose_config

    run = training_setup(compose_config(["scale=paper"]), image_size, feature_size, batch)
    samples = [run.sample() for _ in range(steps + 1)]  # the head-model renders are not the model's cost
    with FlopCounterMode(display=False) as counter:
        run.train_step(samples[0])
    flops = counter.get_total_flops()
    t0 = time.perf_counter()
    for s in samples[1:]:
        run.train_step(s)
    return (time.perf_counter() - t0) / steps, flops


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch", type=int, default=2, help="batch measured on the CPU (scaled to 64)")
    parser.add_argument("--steps", type=int, default=2)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--subjects", type=int, default=10, help="avatars fine-tuned (INSTA has 10 subjects)")
    parser.add_argument("--out", default=None, help="also write the table as Markdown here")
    args = parser.parse_args()
    from helpers import compose_config

    s = compose_config(["scale=paper"]).scale
    batch = int(s.pretrain_batch)
    scale = batch / args.batch
    base = int(s.pretrain_image_size)
    sizes = sorted({base, int(s.renderer_experiment_image_size), *[int(r) for r in s.resolution_tiers]})
    measured = {size: paper_step(size, size // 8, args.batch, args.threads, args.steps) for size in sizes}
    per_iter = {size: flops * scale for size, (_, flops) in measured.items()}
    top = sizes[-1]
    cpu_flops = per_iter[top] / (measured[top][0] * scale)  # FLOP/s this CPU sustains in the largest paper step
    jobs = [  # (what, count, iterations each, FLOPs per iteration)
        (f"alpha pretraining (alpha1, alpha2) at {base}²", 2, int(s.pretrain_alpha_iterations), per_iter[base]),
        (f"beta continuations (beta1-6 x alpha1/alpha2) at {base}²", 12, int(s.pretrain_beta_iterations),
         per_iter[base]),
        (f"renderer experiment (proposed, baseline) at {s.renderer_experiment_image_size}²", 2,
         int(s.renderer_experiment_iterations), per_iter[int(s.renderer_experiment_image_size)]),
        (f"avatars at {base}²: {args.subjects} subjects x (14 inits + 2 interpolation variants)", args.subjects * 16,
         int(s.finetune_iterations), per_iter[base]),
    ]
    for size in s.resolution_tiers:
        jobs += [(f"final recipe continued at {size}²", 1, int(s.resolution_tier_iterations), per_iter[int(size)]),
                 (f"final-recipe avatars at {size}²: {args.subjects} subjects", args.subjects,
                  int(s.finetune_iterations), per_iter[int(size)])]
    lines = ["# GPU-hours of the full reproduction at paper scale (estimate)", "",
             f"Written by `python benchmarks/estimate_gpu_hours.py` on this machine ({args.threads} CPU threads).",
             "", "## Measured here", "",
             *[f"- Training step at paper sizes (CNeRF {s.nerf_depth}x{s.nerf_width}, {s.nerf_samples} samples/ray, "
               f"{size // 8}² feature map -> {size}² image, proposed renderer, perceptual stand-in) at batch "
               f"{args.batch}: **{measured[size][0]:.2f} s** on the CPU, **{measured[size][1] / 1e9:.1f} GFLOP** "
               f"(forward + backward, torch FlopCounterMode); at the paper batch of {batch}: "
               f"{per_iter[size] / 1e12:.2f} TFLOP per iteration" for size in sizes],
             f"- This CPU sustains {cpu_flops / 1e9:.0f} GFLOPS in the {top}² step.",
             "", "## Job graph", "", "| jobs | count | iterations each | PFLOP total | CPU-days here |",
             "| --- | --- | --- | --- | --- |"]
    total = 0.0
    for what, count, iters, per_iter in jobs:
        pflop = count * iters * per_iter / 1e15
        total += pflop
        cpu_days = count * iters * per_iter / cpu_flops / 86400
        lines.append(f"| {what} | {count} | {iters} | {pflop:.0f} | {cpu_days:.0f} |")
    lines.append(f"| **total** | | | **{total:.0f}** | **{total * 1e15 / cpu_flops / 86400:.0f}** |")
    lines += ["", f"## GPU-hours at {SUSTAINED:.0%} of peak", "",
              "| GPU | peak TFLOPS | GPU-hours (all jobs) | one alpha model | one avatar (1000 iterations) |",
              "| --- | --- | --- | --- | --- |"]
    for gpu, peak in GPUS.items():
        rate = peak * 1e12 * SUSTAINED
        lines.append(f"| {gpu} | {peak:.1f} | {total * 1e15 / rate / 3600:.0f} | "
                     f"{s.pretrain_alpha_iterations * per_iter[base] / rate / 3600:.1f} h | "
                     f"{s.finetune_iterations * per_iter[base] / rate / 60:.1f} min at {base}², "
                     f"{s.finetune_iterations * per_iter[top] / rate / 60:.1f} min at {top}² |")
    lines += ["", "Assumptions: the cost is linear in the batch; the head-model renders of synthetic samples and data "
              "loading overlap with the GPU step (not counted); the perceptual network is the stand-in (VGG16 adds "
              "about 2 x 15.5 GFLOP per 224² image forward, x3 with backward); "
              f"a sustained {SUSTAINED:.0%} of peak is typical of small-MLP NeRF training and is the main uncertainty "
              "(x2 either way). Check it against the dissertation's ~10 min per avatar on an RTX 4090.",
              "Not included: preprocessing (per-frame RGB fits, the interpolation networks, the 70 000-image real "
              "set's fits), which runs per subject and was not counted here."]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text)


if __name__ == "__main__":
    main()
