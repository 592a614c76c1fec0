"""The Snakemake workflow as a user runs it: dry run, a real smoke-scale run, and a no-op rerun."""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from conftest import REPO


def snakemake(workdir: Path, *args: str, check=True) -> subprocess.CompletedProcess:
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    cmd = [str(Path(sys.executable).parent / "snakemake"), "-s", str(REPO / "Snakefile"), "--directory", str(workdir),
           "--cores", "2", "--config", "scale=smoke", *args]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900)
    if check and proc.returncode != 0:
        pytest.fail(f"snakemake {' '.join(args)} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return proc


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return tmp_path_factory.mktemp("workflow")


def test_dry_run_lists_the_jobs(workdir):
    out = snakemake(workdir, "-n")
    text = out.stdout + out.stderr
    for rule in ("render_demo", "dlib_check", "all"):
        assert rule in text


@pytest.mark.slow
def test_smoke_run_produces_checked_outputs_and_reruns_nothing(workdir):
    snakemake(workdir)
    results = workdir / "results" / "smoke" / "headmodel"
    grid = np.asarray(Image.open(results / "render_grid.png"))
    assert grid.shape[0] > 15 * 64 and grid.shape[1] > 5 * 64 and grid.std() > 20
    report = json.loads((results / "dlib_check.json").read_text())
    assert report["renders"] == 8
    assert report["detection_rate"] >= 0.9 and report["nme_mean"] <= 0.10 and report["meets_targets"]
    assert report["head_model"].startswith("procedural")
    log = (workdir / "logs" / "smoke" / "headmodel" / "dlib_check.log").read_text()
    assert "procedural open default" in log, "the log must say which head model is in use"
    assert (workdir / "results" / "cache" / "headmodel").is_dir()
    again = snakemake(workdir, "-n")
    assert "Nothing to be done" in again.stdout + again.stderr
    # a changed setting reruns the steps that read it
    forced = snakemake(workdir, "-n", "--forcerun", "dlib_check")
    assert "dlib_check" in forced.stdout and "render_demo" not in forced.stdout.split("Job stats")[-1].split("Reasons")[0]
