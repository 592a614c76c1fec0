"""MLflow bookkeeping: runs left RUNNING by a killed process become KILLED, a resumed step continues its own run,
and a rerun of a step leaves one run per output."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest
from omegaconf import OmegaConf


@pytest.fixture
def store(tmp_path):
    saved = os.environ.pop("MLFLOW_TRACKING_URI", None)
    from avatarlab.runtime.tracking import init_store

    results = tmp_path / "results"
    init_store(results, scales=("smoke",))
    cfg = OmegaConf.create({"paths": {"results": str(results)},
                            "tracking": {"enabled": True, "experiment": "avatarlab-smoke", "scale": "smoke"}})
    yield results, cfg
    os.environ.pop("MLFLOW_TRACKING_URI", None)
    if saved is not None:
        os.environ["MLFLOW_TRACKING_URI"] = saved


def client(results):
    from mlflow.tracking import MlflowClient

    return MlflowClient(f"sqlite:///{results / 'mlflow.db'}")


def runs_of(results, filter_string=""):
    c = client(results)
    exp = c.get_experiment_by_name("avatarlab-smoke")
    return c.search_runs([exp.experiment_id], filter_string, run_view_type=1)  # active runs only


def test_a_run_killed_with_kill_9_is_marked_killed_by_the_next_start(store, tmp_path):
    results, _ = store
    script = tmp_path / "killed.py"
    script.write_text(
        "import os, sys\nfrom omegaconf import OmegaConf\nfrom avatarlab.runtime.tracking import start_run\n"
        f"cfg = OmegaConf.create({{'paths': {{'results': {str(results)!r}}}, 'tracking': {{'enabled': True, "
        "'experiment': 'avatarlab-smoke', 'scale': 'smoke'}})\n"
        "with start_run(cfg, 'pretrain', 'doomed'):\n    os.kill(os.getpid(), 9)\n")
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    proc = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == -9
    (doomed,) = runs_of(results, "attributes.run_name = 'doomed'")
    assert doomed.info.status == "RUNNING"
    from avatarlab.runtime.tracking import start_run

    with start_run(store[1], "pretrain", "the next step"):  # any later step's start, not only the store's creation
        pass
    assert client(results).get_run(doomed.info.run_id).info.status == "KILLED"


def test_a_failed_rerun_keeps_the_finished_run_it_would_replace(store, tmp_path):
    """A full disk: the new run of an output dies; the old FINISHED run of that output stays until a new one ends."""
    from avatarlab.runtime.tracking import start_run

    results, cfg = store
    out = tmp_path / "results" / "smoke" / "avatars" / "x"
    with start_run(cfg, "finetune", "x", output=out) as run:
        old = run.info.run_id
    with pytest.raises(OSError):
        with start_run(cfg, "finetune", "x", output=out):
            raise OSError(28, "No space left on device")
    statuses = {r.info.run_id: r.info.status for r in runs_of(results, f"tags.output = '{out.resolve()}'")}
    assert statuses[old] == "FINISHED" and sorted(statuses.values()) == ["FAILED", "FINISHED"]
    with start_run(cfg, "finetune", "x", output=out) as run:
        new = run.info.run_id
    assert [r.info.run_id for r in runs_of(results, f"tags.output = '{out.resolve()}'")] == [new]


@pytest.mark.parametrize("damage", ["truncated", "garbage", "emptied"])
def test_a_damaged_store_stops_once_in_one_line_naming_it(store, damage):
    from avatarlab.runtime import tracking
    from avatarlab.runtime.errors import InputFileError
    from avatarlab.runtime.tracking import main, start_run

    results, cfg = store
    db = results / "mlflow.db"
    tracking._CHECKED.clear()  # this process checked the store while it was whole
    data = db.read_bytes()
    db.write_bytes({"truncated": data[: len(data) // 3], "garbage": b"not a database at all" * 100,
                    "emptied": b""}[damage])
    before = db.read_bytes()
    with pytest.raises(InputFileError) as err:
        with start_run(cfg, "pretrain", "alpha1"):
            pass
    message = str(err.value)
    assert message.startswith(f"{db}: ") and "\n" not in message and f"mv {db} {db}.broken" in message
    assert main(["init", str(results)]) == 2 and db.read_bytes() == before, "never replaced by a new store"


def test_a_resumed_step_continues_its_run_and_a_rerun_leaves_one_run(store, tmp_path):
    import mlflow

    from avatarlab.runtime.tracking import start_run

    results, cfg = store
    out = tmp_path / "results" / "smoke" / "pretrain" / "alpha1"
    with start_run(cfg, "pretrain", "alpha1", output=out) as run:
        first = run.info.run_id
        mlflow.log_metric("loss", 1.0, step=1)
    with start_run(cfg, "pretrain", "alpha1", run_id=first, output=out) as run:  # resumed after a kill
        assert run.info.run_id == first
        mlflow.log_metric("loss", 0.5, step=2)
    assert [m.step for m in client(results).get_metric_history(first, "loss")] == [1, 2]
    with start_run(cfg, "pretrain", "alpha1", output=out) as run:  # a rerun (code edit, --forcerun)
        second = run.info.run_id
    left = runs_of(results, f"tags.output = '{out.resolve()}'")
    assert [r.info.run_id for r in left] == [second] and second != first
    assert client(results).get_run(second).data.tags["stage"] == "pretrain"


def test_two_workflows_starting_at_once_both_get_the_dashboard_view(store, monkeypatch):
    """Seen on the PostgreSQL server: two `init_tracking` jobs inserted the view tag at once and the second failed
    (unique key). Now a view already in place is left alone, and losing that race is not an error."""
    import json

    from mlflow.tracking import MlflowClient

    from avatarlab.runtime.tracking import VIEW_COLUMNS, VIEW_KEY, init_store, set_dashboard_view

    results, _ = store
    experiment = client(results).get_experiment_by_name("avatarlab-smoke").experiment_id
    real, calls = MlflowClient.set_experiment_tag, []

    def counted(self, *args, **kwargs):
        calls.append(args)
        return real(self, *args, **kwargs)

    monkeypatch.setattr(MlflowClient, "set_experiment_tag", counted)
    init_store(results, scales=("smoke",))
    assert calls == [], "the view is in place already: no second write"
    key = f"mlflow.sharedViewState.{VIEW_KEY}"
    real(client(results), experiment, key, "an older view")

    def raced(self, experiment_id, name, value):  # the other workflow's insert lands first, ours then fails
        monkeypatch.setattr(MlflowClient, "set_experiment_tag", real)
        real(self, experiment_id, name, value)
        raise RuntimeError("duplicate key value violates unique constraint \"experiment_tag_pk\"")

    monkeypatch.setattr(MlflowClient, "set_experiment_tag", raced)
    set_dashboard_view(experiment, results)
    view = json.loads(client(results).get_experiment(experiment).tags[key])
    assert view["selectedColumns"] == VIEW_COLUMNS


def test_evaluation_metrics_reach_the_dashboard_rounded(store):
    """What the dashboard shows: 4 decimals (eval.json keeps every digit); the gain and the baselines too."""
    from avatarlab.runtime.tracking import log_to_run, start_run

    results, cfg = store
    with start_run(cfg, "finetune", "s/alpha1") as run:
        run_id = run.info.run_id
    gains = {"psnr": {"gain": 1.234567891, "best_baseline": "nearest", "beats": True}}
    log_to_run(cfg, run_id, {"psnr": 24.123456789, "ssim": 0.85312345}, {"nearest": {"psnr": 22.88888888}}, gains)
    metrics = client(results).get_run(run_id).data.metrics
    assert metrics["test_psnr"] == 24.1235 and metrics["test_ssim"] == 0.8531
    assert metrics["test_gain_psnr"] == 1.2346 and metrics["test_baseline_nearest_psnr"] == 22.8889


def test_an_evaluation_logs_into_a_finished_run_without_reopening_it(store, monkeypatch):
    """The evaluation writes into the finished run of the model it scored. A step starting meanwhile closes runs left
    RUNNING by a dead process; the scored run must never look like one (it did, when the evaluation reopened it
    under its training process's pid: smoke run of 2026-12-06, a pretrained model's run marked KILLED)."""
    import mlflow

    from avatarlab.runtime import tracking
    from avatarlab.runtime.tracking import log_to_run, mark_dead_runs_killed, start_run

    results, cfg = store
    with start_run(cfg, "pretrain", "beta5_from_alpha1") as run:
        run_id = run.info.run_id
    mlflow.tracking.MlflowClient().set_tag(run_id, "pid", "999999999")  # its training process is gone
    seen = []
    real = mlflow.tracking.MlflowClient.log_batch

    def another_step_starts(self, *args, **kwargs):  # while the evaluation writes, another step starts
        seen.append(self.get_run(run_id).info.status)
        mark_dead_runs_killed(results, [run.info.experiment_id])
        return real(self, *args, **kwargs)

    monkeypatch.setattr(mlflow.tracking.MlflowClient, "log_batch", another_step_starts)
    gains = {"psnr": {"gain": 0.5, "best_baseline": "nearest", "beats": True}}
    log_to_run(cfg, run_id, {"psnr": 20.0}, {"nearest": {"psnr": 19.5}}, gains)
    after = client(results).get_run(run_id)
    assert seen == ["FINISHED"] and after.info.status == "FINISHED"
    assert after.data.metrics["test_psnr"] == 20.0 and after.data.tags["test_beats_baselines"] == "True"
    assert tracking.DASHBOARD_DECIMALS == 4
