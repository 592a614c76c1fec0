from __future__ import annotations

import os
import shutil
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

torch.set_num_threads(2)


def compose_config(overrides: list[str] | None = None):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=overrides or [])


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
