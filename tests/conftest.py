"""Fixtures only; shared helpers live in tests/helpers/."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest
import torch

from avatarlab.headmodel import HeadModel, ProceduralSpec, load_procedural_head

torch.set_num_threads(2)


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


def pytest_sessionfinish(session, exitstatus):
    """The workflow tests' steps started a fork server (src/avatarlab/forkserver.py): end it with the suite rather
    than after its idle time. Servers of edited repository copies (their own import path) end on their idle time."""
    subprocess.run([sys.executable, "-m", "avatarlab.forkserver", "--stop"], capture_output=True, timeout=60,
                   cwd=session.config.rootpath)
