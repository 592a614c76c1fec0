"""How long a workflow step takes to start and finish, plain (`python -m`) and through the fork server.

    python benchmarks/bench_step_start.py [--repeats 5]

Runs a small real step (the head-model demo grid at smoke scale, with its MLflow run, in a temporary directory)
`repeats` times each way and prints the mean and spread of the wall time, and the import time alone of what the
server imports. The first forked run is not counted (it waits for nothing, but the server has to be up: the script
starts it and waits for its socket).
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from avatarlab.runtime.forkserver import PRELOAD, socket_path
from avatarlab.runtime.tracking import TELEMETRY_OFF


def run_step(cwd: Path, forked: bool, index: int) -> float:
    out = cwd / f"grid_{int(forked)}_{index}.png"
    module = ["-m", "avatarlab.runtime.forkserver", "avatarlab.pretrain.head_model_demo"] if forked else \
        ["-m", "avatarlab.pretrain.head_model_demo"]
    env = dict(os.environ, AVATARLAB_FORKSERVER="1" if forked else "0", AVATARLAB_FORKSERVER_IDLE="120")
    start = time.perf_counter()
    subprocess.run([sys.executable, *module, "scale=smoke", f"demo.out={out}", f"hydra.run.dir={cwd}/.hydra/{index}",
                    "threads=1"], cwd=cwd, env=env, check=True, capture_output=True)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    code = "import time, importlib; t = time.perf_counter()\n" \
           f"for m in {PRELOAD!r}: importlib.import_module(m)\nprint(time.perf_counter() - t)"
    imports = float(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                                   env=dict(os.environ, **TELEMETRY_OFF)).stdout)
    print(f"importing what the server preloads: {imports:.2f} s")
    with tempfile.TemporaryDirectory() as tmp:
        cwd = Path(tmp)
        plain = [run_step(cwd, False, i) for i in range(args.repeats)]
        run_step(cwd, True, -1)  # starts the server (and runs plain)
        deadline = time.monotonic() + 120
        while not socket_path().exists() and time.monotonic() < deadline:
            time.sleep(0.2)
        forked = [run_step(cwd, True, i) for i in range(args.repeats)]
        subprocess.run([sys.executable, "-m", "avatarlab.runtime.forkserver", "--stop"], capture_output=True)
    for name, times in (("plain python -m", plain), ("fork server", forked)):
        spread = statistics.stdev(times) if len(times) > 1 else 0.0
        print(f"{name:16s} {statistics.mean(times):6.2f} s per step (± {spread:.2f}, {len(times)} runs)")
    print(f"speed-up: {statistics.mean(plain) / statistics.mean(forked):.1f}x")


if __name__ == "__main__":
    main()
