"""MLflow tracking: one SQLite store under results/ (or the server in MLFLOW_TRACKING_URI), tags on every run.

The ./mlruns file store raises in MLflow >= 3.13, so the default is `sqlite:///<abs>/results/mlflow.db`. The database
and experiments are created once (`python -m avatarlab.tracking init`, the workflow's first rule) before parallel jobs
write to it. Child runs in other processes link to a parent with the `mlflow.parentRunId` tag.
"""
from __future__ import annotations

import contextlib
import logging
import os
import subprocess
import sys
from pathlib import Path

log = logging.getLogger(__name__)


def tracking_uri(results_dir: str | Path = "results") -> str:
    uri = os.environ.get("MLFLOW_TRACKING_URI")
    if uri:
        return uri
    return f"sqlite:///{Path(results_dir).resolve() / 'mlflow.db'}"


def git_sha() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=5,
                              cwd=Path(__file__).resolve().parent).stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def experiment_name(scale: str) -> str:
    return f"avatarlab-{scale}"


def artifact_root(results_dir: str | Path = "results") -> str:
    """Artifacts live beside the database (results/mlartifacts), never in a ./mlruns of whatever the cwd is."""
    return (Path(results_dir).resolve() / "mlartifacts").as_uri()


def ensure_experiment(name: str, results_dir: str | Path) -> str:
    import mlflow

    exp = mlflow.get_experiment_by_name(name)
    if exp is not None:
        return exp.experiment_id
    try:
        # experimentKind: the UI opens the experiment as model training (runs table), not as a GenAI app
        # a tracking server keeps the artifacts where it was told to (--artifacts-destination); the SQLite default
        # keeps them beside the database
        remote = mlflow.get_tracking_uri().startswith(("http://", "https://"))
        return mlflow.create_experiment(name, artifact_location=None if remote else artifact_root(results_dir),
                                        tags={"mlflow.experimentKind": "custom_model_development"})
    except Exception:  # another process created it between the two calls
        exp = mlflow.get_experiment_by_name(name)
        if exp is None:
            raise
        return exp.experiment_id


def init_store(results_dir: str | Path, scales=("smoke", "tiny", "paper")) -> str:
    import mlflow

    Path(results_dir).mkdir(parents=True, exist_ok=True)
    uri = tracking_uri(results_dir)
    mlflow.set_tracking_uri(uri)
    for scale in scales:
        ensure_experiment(experiment_name(scale), results_dir)
    return uri


@contextlib.contextmanager
def start_run(cfg, stage: str, run_name: str, tags: dict | None = None, enabled: bool = True):
    """An MLflow run with the standard tags; yields the mlflow module (or None when tracking is off)."""
    if not enabled:
        yield None
        return
    import mlflow

    mlflow.set_tracking_uri(tracking_uri(cfg.paths.results))
    ensure_experiment(experiment_name(cfg.scale.name), cfg.paths.results)
    mlflow.set_experiment(experiment_name(cfg.scale.name))
    all_tags = {"stage": stage, "scale": cfg.scale.name, "git_sha": git_sha(), "head_model": cfg.head_model.kind,
                "results_dir": str(Path(cfg.paths.results).resolve())}  # which checkout / work dir, on a shared server
    all_tags.update({k: str(v) for k, v in (tags or {}).items()})
    with mlflow.start_run(run_name=run_name, tags=all_tags):
        yield mlflow


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) >= 1 and argv[0] == "init":
        results = argv[1] if len(argv) > 1 else "results"
        marker = Path(argv[2]) if len(argv) > 2 else None
        uri = init_store(results)
        if marker:
            marker.write_text(uri + "\n")
        print(f"MLflow store ready: {uri}")
        return 0
    print("usage: python -m avatarlab.tracking init [results_dir] [marker_file]")
    return 2


if __name__ == "__main__":
    sys.exit(main())
