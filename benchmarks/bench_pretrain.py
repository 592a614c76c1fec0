"""Training throughput of the parametric head model, its MLP's arithmetic rate and its rendering speed.

    python benchmarks/bench_pretrain.py [--scale tiny] [--iterations 20] [--threads 2] [--amp | --no-amp]
    python benchmarks/bench_pretrain.py --processes 2 --threads 1   # the workflow's way: two one-thread jobs at once
    python benchmarks/bench_pretrain.py --mlp-precision bfloat16     # the CNeRF MLP alone in bfloat16
    python benchmarks/bench_pretrain.py --against bcd0053 --rounds 3  # today's training step beside a commit's

Prints, at the scale's sizes and in one process:
- samples/s of a training step as pretraining runs it (alpha: every sample synthetic, so the head-model renders
  are included): the batch drawn by the training code's BatchStream (one batch ahead in a background thread) and
  the loop's train_step (CNeRF + 2D renderer forward and backward, eq. 8, Adam);
- the CNeRF MLP's achieved GFLOPS over the points of one training batch (forward + backward, FLOPs counted by
  torch's FlopCounterMode, so the per-sample conditioning projection is counted as what it is) beside the sgemm rate
  of a 2048 x 2048 float32 matrix product measured in the same run;
- frames/s of rendering an image (inference) at the scale's size and at 128x128.
With --processes N: N processes measure the training step at the same time and the summed samples/s is printed
(what `snakemake --cores 2` gets from two one-thread training jobs).
With --against COMMIT: that commit is checked out into a temporary git worktree, and its own benchmark script (on its
own code and its own config of the scale) and today's measure the training step in turns, one process at a time,
alternating which goes first, --rounds times; the median samples/s of each and their ratio are printed. A speed-up is
only ever such a ratio: two codes on one machine in one sitting.
Timings are the median over repeats; the machine is shared, so compare figures of one run with each other.
"""
from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # tests/helpers


def median_seconds(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def sgemm_gflops(size: int = 2048, repeats: int = 10) -> float:
    a, b = torch.randn(size, size), torch.randn(size, size)
    return 2 * size**3 / median_seconds(lambda: a @ b, repeats) / 1e9


def training_setup(cfg, batch: int) -> SimpleNamespace:
    """Pretraining's pieces at the config's sizes, with a real image set of neutral fits (the samples are all
    synthetic, as in alpha): `stream` draws batches, `step(batch)` is one iteration of the training loop."""
    from avatarlab.data.batches import BatchSource, BatchStream
    from avatarlab.data.schedule import Schedule
    from avatarlab.data.synthetic import SyntheticGenerator
    from avatarlab.headmodel import load_head_model
    from avatarlab.model.head_nerf import build_model
    from avatarlab.model.losses import RandomConvFeatures
    from avatarlab.runtime.config import grad_scaler
    from avatarlab.training.loop import MLP_PRECISIONS, Recipe, make_optimizer, offset_table, train_step

    head = load_head_model(cfg.head_model)
    n = 8
    real = SimpleNamespace(params={"shape": torch.zeros(n, head.n_shape), "expression": torch.zeros(n, head.n_expression),
                                   "texture": torch.zeros(n, head.n_texture), "lighting": torch.zeros(n, 9, 3)})
    real.params["lighting"][:, 0] = 2.8
    real.__len__ = lambda: n
    size = int(cfg.model.image_size)
    device = torch.device("cpu")
    gen = SyntheticGenerator(head, real.params, cfg.synthetic, size, tuple(cfg.render.background), device)
    torch.manual_seed(0)
    net = build_model(cfg, head)
    net.nerf.compute_dtype = MLP_PRECISIONS[str(cfg.model.mlp_precision)]  # as the training loop sets it
    schedule = Schedule(M=10**9, N=10**9, p_min=1.0, p_max=1.0, mouth_from=None)
    recipe = Recipe(schedule=schedule, start=0, batch=batch, lr=1e-3, offset_lr=1e-3, amp=bool(cfg.amp))
    offsets = offset_table(n, {"pose": 12}, (), device)
    optim = make_optimizer(net, offsets, recipe, device)
    scaler, feats = grad_scaler(device, recipe.amp), RandomConvFeatures()
    source = BatchSource(synthetic=gen, real=SimpleNamespace(__len__=lambda: n), schedule=schedule, batch_size=batch,
                         device=device)
    stream = BatchStream(source, 0, 10**9, torch.Generator().manual_seed(0))
    return SimpleNamespace(net=net, gen=gen, source=source, stream=stream, recipe=recipe, device=device,
                           step=lambda b: train_step(net, b, offsets, feats, optim, scaler, recipe, device))


def mlp_rate(run, cfg, batch: int, repeats: int) -> tuple[float, float]:
    """GFLOP and GFLOPS of the CNeRF MLP over one training batch's points (forward + backward)."""
    from torch.utils.flop_counter import FlopCounterMode

    from avatarlab.model.head_nerf import assemble_codes
    from avatarlab.runtime.config import autocast

    fs, samples = int(cfg.model.feature_size), int(cfg.model.samples)
    points = batch * fs * fs * samples
    s = run.gen.sample(batch, torch.Generator().manual_seed(1))
    geometry, appearance = assemble_codes(s["params"], s["lighting"])
    x = (torch.rand(points, 3) - 0.5) * 0.4
    owner = torch.arange(batch).repeat_interleave(points // batch)

    def forward_backward():
        with autocast(run.device, run.recipe.amp):
            sigma, feat = run.net.nerf(x, owner, geometry, appearance)
        (sigma.float().sum() + feat.float().sum()).backward()

    with FlopCounterMode(display=False) as counter:
        forward_backward()
    flops = counter.get_total_flops()
    return flops / 1e9, flops / median_seconds(forward_backward, repeats) / 1e9


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scale", default="tiny")
    parser.add_argument("--iterations", type=int, default=20)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--amp", action=argparse.BooleanOptionalAction, default=None,
                        help="bfloat16 autocast (default: the config's amp)")
    parser.add_argument("--mlp-precision", choices=("float32", "bfloat16"), default=None,
                        help="the CNeRF MLP's training precision (default: the config's model.mlp_precision)")
    parser.add_argument("--processes", type=int, default=1, help="measure the training step in N processes at once")
    parser.add_argument("--against", metavar="COMMIT", help="measure that commit's training step beside today's")
    parser.add_argument("--rounds", type=int, default=3, help="with --against: alternating runs of each")
    parser.add_argument("--step-only", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.against:
        side_by_side(args)
        return
    if args.processes > 1:
        concurrent_training(args)
        return
    torch.set_num_threads(args.threads)
    from helpers import compose_config

    overrides = [f"scale={args.scale}"] + ([f"amp={str(args.amp).lower()}"] if args.amp is not None else [])
    overrides += [f"model.mlp_precision={args.mlp_precision}"] if args.mlp_precision else []
    cfg = compose_config(overrides)
    m, batch = cfg.model, int(cfg.pretrain.batch)
    run = training_setup(cfg, batch)
    step_time = median_seconds(lambda: run.step(run.stream.next()), args.iterations)
    if args.step_only:
        run.stream.close()
        print(f"samples/s {batch / step_time}")
        return
    serial = median_seconds(lambda: run.step(run.source.draw(1, torch.Generator().manual_seed(2))),
                            max(3, args.iterations // 4))
    run.stream.close()
    gflop, gflops = mlp_rate(run, cfg, batch, 10)
    sgemm = sgemm_gflops()
    print(f"scale {args.scale}: batch {batch}, image {m.image_size}x{m.image_size}, feature map "
          f"{m.feature_size}x{m.feature_size}, {m.samples} samples/ray, MLP {m.depth}x{m.width}, renderer "
          f"{m.renderer} (min {m.renderer_min_channels} channels); {args.threads} threads; "
          f"{'bfloat16 autocast' if cfg.amp else 'float32'}, CNeRF MLP in {cfg.model.mlp_precision}")
    print(f"training step: {step_time * 1000:.0f} ms, {batch / step_time:.1f} samples/s (synthetic rendering "
          f"included; without the background batch thread: {serial * 1000:.0f} ms, {batch / serial:.1f} samples/s)")
    print(f"CNeRF MLP forward+backward over one batch's points: {gflop:.2f} GFLOP at {gflops:.1f} GFLOPS = "
          f"{100 * gflops / sgemm:.0f} % of sgemm ({sgemm:.1f} GFLOPS, 2048x2048 float32, same run)")
    net = run.net.eval()
    net.nerf.compute_dtype = None  # renders as evaluation renders: float32
    from avatarlab.model.head_nerf import assemble_codes

    for res in sorted({int(m.image_size), 128}):
        s = run.gen.sample(1, torch.Generator().manual_seed(3))
        geometry, appearance = assemble_codes(s["params"], s["lighting"])
        cam = s["camera"].scaled((res, res))
        net.feature_size = res // 8
        with torch.no_grad():
            fps = 1 / median_seconds(lambda: net(geometry, appearance, cam, stratified=False), 5)
        print(f"render {res}x{res} (feature map {res // 8}x{res // 8}): {fps:.1f} frames/s")


def concurrent_training(args) -> None:
    """The training step measured in args.processes processes started together; prints each rate and the sum."""
    command = [sys.executable, __file__, "--scale", args.scale, "--iterations", str(args.iterations),
               "--threads", str(args.threads), "--step-only"]
    command += [] if args.amp is None else ["--amp" if args.amp else "--no-amp"]
    command += ["--mlp-precision", args.mlp_precision] if args.mlp_precision else []
    processes = [subprocess.Popen(command, stdout=subprocess.PIPE, text=True) for _ in range(args.processes)]
    rates = []
    for process in processes:
        out, _ = process.communicate()
        if process.returncode:
            raise SystemExit(f"a benchmark process failed (exit {process.returncode})")
        rates.append(float(out.strip().splitlines()[-1].split()[-1]))
    print(f"scale {args.scale}: {args.processes} processes x {args.threads} thread(s) at once: "
          f"{sum(rates):.1f} samples/s in all ({', '.join(f'{r:.1f}' for r in rates)} each)")


ROOT = Path(__file__).resolve().parents[1]
RATE = re.compile(r"training step: .*?([0-9.]+) samples/s")


def git(*words: str, cwd: Path = ROOT) -> str:
    return subprocess.run(["git", *words], cwd=cwd, check=True, capture_output=True, text=True).stdout.strip()


def step_rate(tree: Path, args, today: bool) -> float:
    """samples/s of one run of `tree`'s own benchmark script on `tree`'s own code (PYTHONPATH first)."""
    command = [sys.executable, str(tree / "benchmarks" / "bench_pretrain.py"), "--scale", args.scale,
               "--threads", str(args.threads), "--iterations", str(args.iterations)] + (["--step-only"] if today else [])
    env = dict(os.environ, PYTHONPATH=str(tree / "src"))
    out = subprocess.run(command, cwd=tree, env=env, capture_output=True, text=True)
    if out.returncode:
        raise SystemExit(f"{tree}: its benchmark failed (exit {out.returncode}): {out.stderr.strip()[-400:]}")
    found = RATE.search(out.stdout) or re.search(r"samples/s ([0-9.]+)", out.stdout)
    if not found:
        raise SystemExit(f"{tree}: its benchmark printed no training-step rate")
    return float(found.group(1))


def imported_from(tree: Path) -> str:
    return subprocess.run([sys.executable, "-c", "import avatarlab; print(avatarlab.__file__)"], cwd=tree,
                          env=dict(os.environ, PYTHONPATH=str(tree / "src")), capture_output=True, text=True,
                          check=True).stdout.strip()


def side_by_side(args) -> None:
    """Today's training step and `args.against`'s, measured in turns on this machine; prints medians and the ratio."""
    old_commit = git("rev-parse", "--verify", f"{args.against}^{{commit}}")
    today = git("rev-parse", "HEAD") + (" (with uncommitted changes)" if git("status", "--porcelain", "--", "src")
                                          else "")
    with tempfile.TemporaryDirectory(prefix="bench_against_") as tmp:
        old_tree = Path(tmp) / "old"
        git("worktree", "add", "--detach", str(old_tree), old_commit)
        try:
            for tree in (old_tree, ROOT):
                where = imported_from(tree)
                if not where.startswith(str(tree)):
                    raise SystemExit(f"{tree}: avatarlab was imported from {where}, not from this tree")
            rates: dict[str, list[float]] = {"old": [], "today": []}
            for k in range(args.rounds):
                order = [("old", old_tree), ("today", ROOT)]
                for label, tree in order if k % 2 == 0 else order[::-1]:
                    rates[label].append(step_rate(tree, args, label == "today"))
                    print(f"round {k + 1}: {label} {rates[label][-1]:.1f} samples/s", flush=True)
        finally:
            git("worktree", "remove", "--force", str(old_tree))
    old, new = statistics.median(rates["old"]), statistics.median(rates["today"])
    print(f"machine: {cpu_model()}; {args.threads} thread(s), scale {args.scale}, {args.rounds} alternating rounds")
    print(f"{old_commit[:7]}: {old:.1f} samples/s (median of {', '.join(f'{r:.1f}' for r in rates['old'])})")
    print(f"{today[:7]}{today[40:]}: {new:.1f} samples/s (median of {', '.join(f'{r:.1f}' for r in rates['today'])})")
    print(f"speed-up {new / old:.2f}x (today / {old_commit[:7]}, same machine, same sitting)")


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    import platform

    return platform.processor() or platform.machine()


if __name__ == "__main__":
    main()
