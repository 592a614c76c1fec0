"""Running the repository's workflow as a user runs it."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


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
    server, MLFLOW_TRACKING_URI is dropped so that a run uses its own store under results/."""
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}", **extra)
    if not tracking_server:
        env.pop("MLFLOW_TRACKING_URI", None)
    return env


def snakemake_command(workdir: Path, *args: str, snakefile: Path | None = None) -> list[str]:
    """The command line that runs the workflow (this repository's, or the Snakefile given) in `workdir`."""
    return [str(Path(sys.executable).parent / "snakemake"), "-s", str(snakefile or REPO / "Snakefile"),
            "--directory", str(workdir), *args]


def run_snakemake(workdir: Path, *args: str, env: dict | None = None, timeout: int = 2400, check: bool = True,
                  snakefile: Path | None = None) -> subprocess.CompletedProcess:
    """The workflow (this repository's, or the Snakefile given) run in `workdir`; a failure shows its output's end."""
    proc = subprocess.run(snakemake_command(workdir, *args, snakefile=snakefile), env=env or workflow_env(),
                          capture_output=True, text=True, timeout=timeout)
    if check and proc.returncode != 0:
        pytest.fail(f"snakemake {' '.join(args)} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return proc


def jobs_planned(proc: subprocess.CompletedProcess) -> dict[str, int]:
    """rule -> count from a dry run's "Job stats" table (empty when there is nothing to do)."""
    text = proc.stdout + proc.stderr
    if "Job stats" not in text:
        return {}
    table = text.split("Job stats:")[1].split("\n\n")[0].splitlines()[3:]
    counts = {}
    for line in table:
        parts = line.split()
        if len(parts) == 2 and parts[1].isdigit() and parts[0] not in ("total", "all"):
            counts[parts[0]] = int(parts[1])
    return counts
