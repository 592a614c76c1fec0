"""The workflow on a cluster: a real SLURM (slurmctld + slurmd from Debian's packages, started by
cluster/local_cluster.sh on this machine) and an MLflow tracking server with a PostgreSQL backend store.

Skipped, with the reason, only where the Debian packages cannot be installed or the daemons cannot start."""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers import REPO, run_snakemake, workflow_env

SCRIPT = REPO / "cluster" / "local_cluster.sh"
# the synthetic subject's preprocessing chain at smoke scale: five steps, each a SLURM job
SUBJECT_TARGETS = ["results/smoke/subjects/synth_talk/fit_rgb.json", "results/smoke/subjects/synth_talk/masks.json"]
SPEECH_TARGETS = ["results/smoke/speech/lstm_reg/metrics.json", "results/smoke/speech/window/metrics.json"]


def _cluster(command: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHON=sys.executable)
    return subprocess.run(["bash", str(SCRIPT), command], capture_output=True, text=True, timeout=600, env=env)


@pytest.fixture(scope="module")
def cluster_env():
    if os.geteuid() != 0:
        pytest.skip("the one-machine SLURM / PostgreSQL cluster needs root (Debian packages, daemons)")
    if not shutil.which("slurmctld") or not shutil.which("munged") or not list(Path("/usr/lib/postgresql").glob("*/bin")):
        installed = _cluster("install")
        if installed.returncode != 0:
            pytest.skip(f"Debian's slurm-wlm / munge / postgresql could not be installed: {installed.stderr.strip()}")
    was_up = _cluster("status").stdout
    up = _cluster("up")
    if up.returncode != 0:
        pytest.skip(f"the local cluster did not start: {up.stderr.strip()[-500:]}")
    env = workflow_env(tracking_server=True)
    for line in up.stdout.splitlines():
        key, _, value = line.removeprefix("export ").partition("=")
        env[key] = value
    yield env
    if "idle" not in was_up and "OK" not in was_up:
        _cluster("down")


def snakemake(workdir: Path, env: dict, *args: str, timeout=1200) -> subprocess.CompletedProcess:
    return run_snakemake(workdir, *args, env=env, timeout=timeout)


def local_env(env: dict) -> dict:
    """The same environment without the tracking server: local runs use their own SQLite store."""
    return {k: v for k, v in env.items() if k != "MLFLOW_TRACKING_URI"}


@pytest.mark.slow
def test_slurm_run_gives_the_same_outputs_as_a_local_run(cluster_env, tmp_path):
    local, cluster = tmp_path / "local", tmp_path / "slurm"
    env = local_env(cluster_env)
    # the local run goes on while the SLURM executor waits between its status checks (the suite's time budget)
    failures = []

    def run_locally():
        try:
            snakemake(local, env, "--cores", "1", *SUBJECT_TARGETS, "--config", "scale=smoke")
        except Exception as err:  # reported below, in the test's thread
            failures.append(err)

    local_run = threading.Thread(target=run_locally)
    local_run.start()
    # the executor looks first after --slurm-init-seconds-before-status-checks, then backs off by 10 s per look that
    # finds nothing finished: a smoke step (a Snakemake start inside the job, then the step) is done within 20 s
    out = snakemake(cluster, env, "--profile", str(REPO / "profiles" / "slurm"), "--slurm-status-command", "squeue",
                    "--slurm-init-seconds-before-status-checks", "20", *SUBJECT_TARGETS, "--config", "scale=smoke")
    local_run.join()
    assert not failures, failures
    text = out.stdout + out.stderr
    job_ids = [int(j) for j in re.findall(r"submitted with SLURM jobid (\d+)", text)]
    kinds = {"synthesize_subject": "light", "extract_frames": "light", "detect_landmarks": "light",
             "segment_masks": "light", "fit_rgb": "fit"}
    requests = yaml.safe_load((REPO / "conf/scale/smoke.yaml").read_text())["resources"]
    assert len(job_ids) == len(kinds), text[-2000:]
    # every step ran as a SLURM job, with the request of its kind in conf/scale/smoke.yaml
    seen = set()
    for job_id in job_ids:
        show = subprocess.run(["scontrol", "show", "job", str(job_id)], capture_output=True, text=True,
                              env=cluster_env).stdout
        assert "JobState=COMPLETED" in show, show
        rule = re.search(r"Comment=rule_(\w+?)(_wildcards\S*)?\s", show).group(1)
        want = requests[kinds[rule]]
        assert f"TimeLimit=00:{want['runtime']:02d}:00" in show, show
        assert f"MinMemoryNode={want['mem_mb']}M" in show and f"NumCPUs={want['cpus']} " in show, show
        seen.add(rule)
    assert seen == set(kinds)

    # the same outputs: the same frames, landmarks, masks and fitted parameters
    a, b = local / "results/smoke/subjects/synth_talk", cluster / "results/smoke/subjects/synth_talk"
    for name in ("landmarks.npz", "masks.npz", "fit_rgb.npz"):
        with np.load(a / name) as x, np.load(b / name) as y:
            assert sorted(x.files) == sorted(y.files)
            for key in x.files:
                if x[key].dtype.kind in "fc":
                    np.testing.assert_allclose(x[key], y[key], rtol=1e-5, atol=1e-6, err_msg=f"{name}:{key}")
                else:
                    assert np.array_equal(x[key], y[key]), f"{name}:{key}"
    fit_a, fit_b = (json.loads((d / "fit_rgb.json").read_text()) for d in (a, b))
    assert fit_a["landmark_error_px"] == pytest.approx(fit_b["landmark_error_px"], rel=1e-5)
    # and nothing left to do, seen from either side
    assert "Nothing to be done" in snakemake(cluster, env, "-n", *SUBJECT_TARGETS, "--config", "scale=smoke").stdout


def test_paper_scale_dry_run_lists_the_full_graph_with_cluster_resources(tmp_path):
    """No cluster needed: the job graph of the whole reproduction at paper scale, as the SLURM profile submits it."""
    env = workflow_env()
    # --cores: a dry run counts this machine's cores and clips threads to them; the cluster has more
    out = snakemake(tmp_path, env, "-n", "--profile", str(REPO / "profiles" / "slurm"), "--cores", "64",
                    "--config", "scale=paper", timeout=600)
    text = out.stdout
    counts = dict(re.findall(r"^(\w+)\s+(\d+)$", text, flags=re.M))
    assert int(counts["pretrain_alpha"]) == 2 and int(counts["pretrain_beta"]) == 12
    assert int(counts["finetune_avatar"]) >= 14
    assert int(counts["pretrain_resolution"]) == 2  # the final recipe continued at 256² and 512²
    jobs = text.split("\nrule ")
    tier = next(j for j in jobs if j.startswith("pretrain_resolution:") and "_512px/model.pt" in j)
    assert "beta6_from_alpha2_256px/model.pt" in tier.split("output:")[0], "512² continues the 256² model"
    assert "strategy=beta6 model.image_size=512 model.feature_size=64" in tier and "threads: 8" in tier
    apps = next(j for j in jobs if j.startswith("novel_views:"))
    assert "final/beta6_from_alpha2_512px/model.pt" in apps, "the applications use the 512² avatar"
    pretrain = next(j for j in jobs if j.startswith("pretrain_alpha:"))
    assert "threads: 8" in pretrain and re.search(r"runtime=10080, gpu=1, mem_mb=64000", pretrain), pretrain
    light = next(j for j in jobs if j.startswith("extract_frames:"))
    assert re.search(r"gpu=0, mem_mb=16000", light)
    assert " scale=paper " in pretrain and re.search(r"'pretrain.out_dir=\"results/paper/pretrain/alpha[12]\"'", pretrain)


@pytest.mark.slow
def test_the_cluster_state_is_private_and_postgres_wants_a_password(cluster_env):
    """Not a predictable /tmp folder, the password file 0600, no `trust` login: a local user without the password
    cannot reach the tracking database."""
    pgpass = Path(cluster_env["PGPASSFILE"])
    folder = pgpass.parent
    assert folder != Path("/tmp/avatarlab-cluster") and not folder.is_symlink()
    assert folder.stat().st_mode & 0o777 in (0o700, 0o711) and folder.stat().st_uid == os.geteuid()
    assert pgpass.stat().st_mode & 0o777 == 0o600
    hba = (folder / "postgres" / "data" / "pg_hba.conf").read_text()
    assert not re.search(r"^\s*(local|host)\S*\s.*\btrust\s*$", hba, flags=re.M), hba
    psql = next(Path("/usr/lib/postgresql").glob("*/bin/psql"))
    port = os.environ.get("AVATARLAB_PG_PORT", "55432")
    no_password = {k: v for k, v in cluster_env.items() if k not in ("PGPASSFILE", "PGPASSWORD")}
    no_password["PGPASSFILE"] = "/dev/null"
    refused = subprocess.run([str(psql), "-w", "-h", "127.0.0.1", "-p", port, "-U", "postgres", "-d", "mlflow", "-tAc",
                              "SELECT 1"], capture_output=True, text=True, env=no_password)
    assert refused.returncode != 0 and "password" in refused.stderr, refused.stderr
    allowed = subprocess.run([str(psql), "-w", "-h", "127.0.0.1", "-p", port, "-U", "postgres", "-d", "mlflow", "-tAc",
                              "SELECT 1"], capture_output=True, text=True, env=cluster_env)
    assert allowed.stdout.strip() == "1", allowed.stderr


@pytest.mark.slow
def test_two_workflows_log_concurrently_to_the_postgres_tracking_server(cluster_env, tmp_path):
    """Two workflow runs write to one PostgreSQL-backed MLflow server at the same time: no run and no metric is lost."""
    import mlflow

    dirs = [tmp_path / "first", tmp_path / "second"]
    errors = []

    def run(workdir):
        try:
            snakemake(workdir, cluster_env, "--cores", "1", *SPEECH_TARGETS, "--config", "scale=smoke",
                      "threads_per_job=1")
        except BaseException as err:  # pytest.fail raises an Outcome, not an Exception
            errors.append(f"{workdir.name}: {err}")

    threads = [threading.Thread(target=run, args=(d,)) for d in dirs]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors

    client = mlflow.MlflowClient(tracking_uri=cluster_env["MLFLOW_TRACKING_URI"])
    experiment = client.get_experiment_by_name("avatarlab-smoke")
    for workdir in dirs:
        results = str((workdir / "results").resolve())
        runs = client.search_runs([experiment.experiment_id], f"tags.results_dir = '{results}'")
        assert sorted(r.data.tags["speech_model"] for r in runs) == ["lstm_reg", "window"]
        for run in runs:
            report = json.loads((workdir / f"results/smoke/speech/{run.data.tags['speech_model']}/metrics.json")
                                .read_text())
            assert run.info.status == "FINISHED"
            # every epoch of every training curve, and every test metric, arrived
            for key in (k for k in report["history"][0] if k != "epoch"):
                history = client.get_metric_history(run.info.run_id, f"train_{key}")
                assert [m.step for m in sorted(history, key=lambda m: m.step)] == [h["epoch"] for h in report["history"]]
                assert [m.value for m in sorted(history, key=lambda m: m.step)] == pytest.approx(
                    [h[key] for h in report["history"]])
            assert run.data.metrics["test_lip_error_percent"] == pytest.approx(report["test"]["lip_error_percent"])
    # the store behind the server is PostgreSQL: the runs are rows there
    psql = next(Path("/usr/lib/postgresql").glob("*/bin/psql"))
    port = os.environ.get("AVATARLAB_PG_PORT", "55432")
    rows = subprocess.run([str(psql), "-h", "127.0.0.1", "-p", port, "-U", "postgres", "-d", "mlflow", "-tAc",
                           "SELECT count(*) FROM tags WHERE key = 'results_dir' AND value LIKE "
                           f"'{tmp_path.resolve()}/%'"], capture_output=True, text=True, check=True,
                          env=cluster_env).stdout
    assert int(rows.strip()) == 4
