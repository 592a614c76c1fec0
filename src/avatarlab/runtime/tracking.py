"""MLflow tracking: one SQLite store under results/ (or the server in MLFLOW_TRACKING_URI), tags on every run.

The ./mlruns file store raises in MLflow >= 3.13, so the default is `sqlite:///<abs>/results/mlflow.db`. The database
and experiments are created once (`python -m avatarlab.runtime.tracking init`, the workflow's first rule) before parallel jobs
write to it; that rule also marks runs whose process died (kill -9, a lost node) as KILLED.
One step, one run: a resumed training continues its own run (the id is kept in the checkpoint), the evaluation step
logs its metrics into the run of the model it scores, and a rerun of a step retires (deletes) the run it replaces,
so the dashboard never shows two finished runs of the same step.
"""
from __future__ import annotations

import contextlib
import json
import logging
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

from avatarlab.runtime.errors import InputFileError

log = logging.getLogger(__name__)
TELEMETRY_OFF = {"MLFLOW_DISABLE_TELEMETRY": "true", "DO_NOT_TRACK": "true"}


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


def check_store(results_dir: str | Path) -> None:
    """The SQLite store must be a readable MLflow database: a truncated, emptied or overwritten `mlflow.db` stops here
    with one line naming it (not a page of SQLAlchemy per step, nor a new empty store over the old runs)."""
    uri = tracking_uri(results_dir)
    if not uri.startswith("sqlite:///"):
        return
    db = Path(uri[len("sqlite:///"):])
    if not db.exists() or db in _CHECKED:
        return
    import sqlite3

    advice = f"move it aside (mv {db} {db}.broken) and run again: a new store is made, the results files are untouched"
    if db.stat().st_size == 0:
        raise InputFileError(f"{db}: the MLflow store is empty (0 bytes); {advice}")
    try:
        with contextlib.closing(sqlite3.connect(f"file:{db}?mode=ro", uri=True)) as con:
            check = con.execute("PRAGMA quick_check").fetchone()[0]
            tables = {row[0] for row in con.execute("SELECT name FROM sqlite_master WHERE type='table'")}
    except sqlite3.DatabaseError as err:
        raise InputFileError(f"{db}: not a readable MLflow store ({err}); {advice}") from None
    if check != "ok" or not {"experiments", "runs"} <= tables:
        reason = f"integrity check: {check}" if check != "ok" else "no MLflow tables in it"
        raise InputFileError(f"{db}: not a readable MLflow store ({reason}); {advice}")
    _CHECKED.add(db)  # once per process: the check reads the whole file


_CHECKED: set[Path] = set()


def _mlflow(results_dir):
    os.environ.update(TELEMETRY_OFF)
    check_store(results_dir)
    import mlflow

    mlflow.set_tracking_uri(tracking_uri(results_dir))
    return mlflow


def ensure_experiment(name: str, results_dir: str | Path) -> str:
    mlflow = _mlflow(results_dir)
    exp = mlflow.get_experiment_by_name(name)
    if exp is not None:
        return exp.experiment_id
    try:
        # experimentKind: the UI opens the experiment as model training (runs table), not as a GenAI app;
        # a tracking server keeps the artifacts where it was told to, the SQLite default beside the database
        remote = mlflow.get_tracking_uri().startswith(("http://", "https://"))
        return mlflow.create_experiment(name, artifact_location=None if remote else artifact_root(results_dir),
                                        tags={"mlflow.experimentKind": "custom_model_development"})
    except Exception:  # another process created it between the two calls
        exp = mlflow.get_experiment_by_name(name)
        if exp is None:
            raise
        return exp.experiment_id


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def mark_dead_runs_killed(results_dir: str | Path, ids: list[str]) -> int:
    """Runs still RUNNING in the experiments `ids` whose process (pid tag, on this host) is gone become KILLED.
    -> how many."""
    mlflow = _mlflow(results_dir)
    client = mlflow.tracking.MlflowClient()
    host, count = socket.gethostname(), 0
    if not ids:
        return 0
    for run in client.search_runs(ids, "attributes.status = 'RUNNING'", max_results=5000):
        tags = run.data.tags
        if tags.get("host") == host and tags.get("pid", "").isdigit() and not _alive(int(tags["pid"])):
            client.set_terminated(run.info.run_id, status="KILLED")
            count += 1
    return count


#: the runs-table view the dashboard link opens (MLflow's shared view state, an experiment tag): the quality numbers
#: beside their gain over the best trivial predictor, and the tags that say which run is which
VIEW_KEY = "avatarlab"
VIEW_COLUMNS = [f"metrics.`{m}`" for m in (
    "test_all_psnr", "test_all_gain_psnr", "test_all_ssim", "test_all_st_lpips", "test_all_lpips",
    "test_psnr_head", "test_gain_psnr_head", "test_ssim", "test_st_lpips")] + [
    f"tags.`{t}`" for t in ("stage", "strategy", "subject", "init", "recipe", "sweep", "point", "seed")]


def set_dashboard_view(experiment_id: str, results_dir: str | Path) -> None:
    """The shared view `?viewStateShareKey=avatarlab` of the experiment's runs table: VIEW_COLUMNS as visible
    columns, newest runs first."""
    mlflow = _mlflow(results_dir)
    client, key = mlflow.tracking.MlflowClient(), f"mlflow.sharedViewState.{VIEW_KEY}"
    value = json.dumps({"selectedColumns": VIEW_COLUMNS, "orderByKey": "attributes.start_time", "orderByAsc": False})
    if client.get_experiment(experiment_id).tags.get(key) == value:
        return
    try:
        client.set_experiment_tag(experiment_id, key, value)
    except Exception:  # two workflows starting at once against one server: the other one's insert came first
        if client.get_experiment(experiment_id).tags.get(key) is None:
            raise
        client.set_experiment_tag(experiment_id, key, value)  # the row exists now: this is an update


def init_store(results_dir: str | Path, scales=("smoke", "tiny", "paper")) -> str:
    Path(results_dir).mkdir(parents=True, exist_ok=True)
    ids = [ensure_experiment(experiment_name(s), results_dir) for s in scales]
    for experiment_id in ids:
        set_dashboard_view(experiment_id, results_dir)
    killed = mark_dead_runs_killed(results_dir, ids)
    if killed:
        log.info("%d runs left RUNNING by a process that no longer exists are now KILLED", killed)
    return tracking_uri(results_dir)


def _retire_superseded(mlflow, experiment_id: str, output: str, keep: str) -> None:
    """Delete the earlier runs of the same step (same `output` tag), so a rerun leaves one run."""
    client = mlflow.tracking.MlflowClient()
    escaped = output.replace("'", "\\'")
    for run in client.search_runs([experiment_id], f"tags.output = '{escaped}'", max_results=1000):
        if run.info.run_id != keep:
            client.delete_run(run.info.run_id)


@contextlib.contextmanager
def start_run(cfg, stage: str, run_name: str, tags: dict | None = None, run_id: str | None = None,
              output: str | Path | None = None):
    """An MLflow run with the standard tags; yields the active run (or None when tracking is off).
    `run_id`: continue that run (a resumed step). `output`: the step's output folder, which identifies the step:
    a new run retires the earlier runs of the same output."""
    tr = cfg.tracking
    if not tr.enabled:
        yield None
        return
    mlflow = _mlflow(cfg.paths.results)
    experiment_id = ensure_experiment(tr.experiment, cfg.paths.results)
    mlflow.set_experiment(experiment_id=experiment_id)
    # a step killed with kill -9 (or a lost node) left its run RUNNING: every step's start closes such runs
    if mark_dead_runs_killed(cfg.paths.results, [experiment_id]):
        log.info("runs left RUNNING by processes that no longer exist are now KILLED")
    all_tags = {"stage": stage, "scale": tr.scale, "git_sha": git_sha(), "pid": str(os.getpid()),
                "host": socket.gethostname(),
                "results_dir": str(Path(cfg.paths.results).resolve())}  # which checkout / work dir, on a server
    if output is not None:
        all_tags["output"] = str(Path(output).resolve())
    all_tags.update({k: str(v) for k, v in (tags or {}).items() if v is not None})
    if tr.get("sweep"):
        all_tags.update(sweep=str(tr.sweep), point=str(tr.point))
    existing = None
    if run_id:
        try:
            existing = mlflow.get_run(run_id)
        except Exception:  # deleted, or another store
            existing = None
    if existing is not None:
        run = mlflow.start_run(run_id=run_id)
        mlflow.set_tags({"pid": all_tags["pid"], "host": all_tags["host"]})
    else:
        run = mlflow.start_run(run_name=run_name, tags=all_tags)
        from omegaconf import OmegaConf

        mlflow.log_dict(OmegaConf.to_container(cfg, resolve=True), "config.yaml")  # the step's resolved config
        if tr.get("point_overrides"):
            mlflow.log_params({f"sweep.{k}": v for k, _, v in
                               (o.partition("=") for o in str(tr.point_overrides).split())})
    with run:
        yield run
    if output is not None:  # only once this run has finished: a failed rerun (a full disk) keeps the old one
        _retire_superseded(mlflow, experiment_id, all_tags["output"], run.info.run_id)


DASHBOARD_DECIMALS = 4  # an evaluation's metrics in MLflow: 24.1235 dB, SSIM 0.8531 (far below their seed noise)


def log_to_run(cfg, run_id: str | None, model: dict, baselines: dict, gains: dict, prefix: str = "test",
               artifact: Path | None = None, extra: dict | None = None) -> None:
    """An evaluation's numbers into the run of the model it scored: `<prefix>_<metric>` for the model,
    `<prefix>_baseline_<name>_<metric>` for each baseline, `<prefix>_gain_<metric>` over the best baseline, each
    rounded to `DASHBOARD_DECIMALS` so the dashboard's tables read (eval.json keeps every digit)."""
    if not cfg.tracking.enabled or not run_id:
        return
    mlflow = _mlflow(cfg.paths.results)
    metrics = {f"{prefix}_{k}": v for k, v in model.items() if _number(v)}
    for name, scores in baselines.items():
        metrics.update({f"{prefix}_baseline_{name}_{k}": v for k, v in scores.items() if _number(v)})
    for metric, g in gains.items():
        metrics[f"{prefix}_gain_{metric}"] = g["gain"]
    metrics.update({k: v for k, v in (extra or {}).items() if _number(v)})
    metrics = {k: round(float(v), DASHBOARD_DECIMALS) for k, v in metrics.items()}
    tags = {f"{prefix}_best_baseline": gains.get("psnr", {}).get("best_baseline", ""),
            f"{prefix}_beats_baselines": str(all(g["beats"] for k, g in gains.items() if k in ("psnr", "psnr_head")))}
    # through the client, leaving the finished run's status alone: reopening it (start_run) would make it RUNNING
    # under its training process's pid, which is gone, and a step starting meanwhile would mark it KILLED
    from mlflow.entities import Metric, RunTag

    try:
        client, now = mlflow.tracking.MlflowClient(), int(time.time() * 1000)
        client.log_batch(run_id, metrics=[Metric(k, v, now, 0) for k, v in metrics.items()],
                         tags=[RunTag(k, v) for k, v in tags.items()])
        if artifact is not None and Path(artifact).is_file():
            client.log_artifact(run_id, str(artifact))
    except Exception as err:  # the model's run is gone (deleted store): the numbers are in eval.json anyway
        log.warning("MLflow run %s not updated: %s", run_id, err)


def log_history(run, entries: list[dict],
                keys=("loss", "mse", "perceptual", "offsets", "st_lpips_term", "distortion_term", "psnr",
                      "p_synthetic")) -> None:
    """Per-iteration training numbers into the active run (each entry once: the loop hands over each segment)."""
    if run is None or not entries:
        return
    import mlflow
    from mlflow.entities import Metric

    now = int(time.time() * 1000)
    metrics = [Metric(k, float(h[k]), now, int(h["step"])) for h in entries for k in keys if k in h]
    client = mlflow.tracking.MlflowClient()
    for start in range(0, len(metrics), 1000):  # MLflow's batch limit
        client.log_batch(run.info.run_id, metrics=metrics[start:start + 1000])


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and v == v


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) >= 1 and argv[0] == "init":
        results = argv[1] if len(argv) > 1 else "results"
        marker = Path(argv[2]) if len(argv) > 2 else None
        try:
            uri = init_store(results)
        except InputFileError as err:
            print(f"avatarlab error: {err}", file=sys.stderr)
            return 2
        if marker:
            marker.write_text(uri + "\n")
        print(f"MLflow store ready: {uri}")
        return 0
    print("usage: python -m avatarlab.runtime.tracking init [results_dir] [marker_file]")
    return 2


if __name__ == "__main__":
    sys.exit(main())
