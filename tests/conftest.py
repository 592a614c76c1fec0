"""Fixtures only; shared helpers live in tests/helpers/."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest
import torch

from avatarlab.headmodel import HeadModel, ProceduralSpec, load_procedural_head

# `make test` runs the suite in two workers (pytest-xdist, one file per worker at a time): each takes one core, so
# that no OpenMP pool of one worker spins on the core the other needs; a plain `pytest` run takes both.
WORKER = os.environ.get("PYTEST_XDIST_WORKER")
torch.set_num_threads(1 if WORKER else 2)


#: the longest files first: with two workers (`make test`) one takes the whole workflow run while the other works
#: through the rest, instead of the workflow file starting last
FIRST = ("test_workflow.py", "test_cluster.py")


def pytest_collection_modifyitems(session, config, items):
    rank = {name: i for i, name in enumerate(FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(FIRST)))  # stable: each file keeps its own order


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
    """The workflow tests' steps started a fork server (src/avatarlab/runtime/forkserver.py): end it with the suite rather
    than after its idle time. Servers of edited repository copies (their own import path) end on their idle time.
    With workers, the controller does it once every worker is done."""
    if WORKER:
        return
    subprocess.run([sys.executable, "-m", "avatarlab.runtime.forkserver", "--stop"], capture_output=True, timeout=60,
                   cwd=session.config.rootpath)
