from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from avatarlab.config import CONF_DIR
from avatarlab.headmodel import HeadModel, ProceduralSpec, load_procedural_head

REPO = Path(__file__).resolve().parents[1]


def _shared_data() -> Path:
    """The workplace's real test data: $AVATARLAB_SHARED_DATA, else ../shared/data beside the checkout, else
    /work/shared/data (where a fresh clone elsewhere still finds it on this workplace)."""
    for candidate in (os.environ.get("AVATARLAB_SHARED_DATA"), REPO.parent / "shared" / "data", "/work/shared/data"):
        if candidate and Path(candidate).is_dir():
            return Path(candidate)
    return REPO.parent / "shared" / "data"


SHARED_DATA = _shared_data()


def workflow_env(tracking_server: bool = False, **extra: str) -> dict:
    """os.environ with this interpreter's bin first on PATH (the steps run `python -m ...`); without a tracking
    server, MLFLOW_TRACKING_URI is dropped so that a run uses its own store under results/ (an earlier
    mlflow.set_tracking_uri in this process exports it)."""
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}", **extra)
    if not tracking_server:
        env.pop("MLFLOW_TRACKING_URI", None)
    return env


def run_snakemake(workdir: Path, *args: str, env: dict | None = None, timeout: int = 2400,
                  check: bool = True) -> subprocess.CompletedProcess:
    """The repository's workflow run in `workdir` as a user runs it; a failure shows the end of its output."""
    cmd = [str(Path(sys.executable).parent / "snakemake"), "-s", str(REPO / "Snakefile"), "--directory", str(workdir),
           *args]
    proc = subprocess.run(cmd, env=env or workflow_env(), capture_output=True, text=True, timeout=timeout)
    if check and proc.returncode != 0:
        pytest.fail(f"snakemake {' '.join(args)} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return proc

torch.set_num_threads(2)


def compose_config(overrides: list[str] | None = None):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=overrides or [])


def interp_config(**extra):
    """A small interpolation-training config (8 channels, 2 scales, 6 steps of batch 2, checkpoints every 3)."""
    from omegaconf import OmegaConf

    return OmegaConf.create({"seed": 0, "interp": {"width": 8, "scales": 2, "lr": 1e-3, "batch": 2, "iterations": 6,
                                                   "checkpoint_every": 3}, **extra})


@pytest.fixture(scope="session")
def head_data():
    return load_procedural_head(ProceduralSpec())


@pytest.fixture(scope="session")
def head_model(head_data):
    return HeadModel(head_data)


@pytest.fixture(scope="session")
def snakemake_bin():
    exe = shutil.which("snakemake", path=os.path.dirname(os.sys.executable) + os.pathsep + os.environ["PATH"])
    if exe is None:
        pytest.fail("snakemake is not installed in the test environment")
    return exe
