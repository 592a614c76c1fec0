"""The metrics dashboard: the MLflow UI over the workflow's store, on 127.0.0.1 only.

`python -m avatarlab.runtime.dashboard [--results results] [--port 5000] [--scale tiny]` (what `make dashboard` runs). The
server (MLflow's uvicorn and its job workers) runs in a process group of its own, which SIGTERM, SIGINT (Ctrl-C) or
the end of this process stops as a whole (a watchdog process stops it when this one is killed outright, kill -9); a port already in use is reported and the exit status is 1. MLflow's usage
telemetry is off for the servers the project starts. With MLFLOW_TRACKING_URI set to a shared server (http...), open
that server's UI instead: there is nothing to serve here.
"""
from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

from avatarlab.runtime.tracking import TELEMETRY_OFF, VIEW_KEY


def command(results: Path, port: int, host: str = "127.0.0.1") -> list[str]:
    db = Path(results).resolve() / "mlflow.db"
    if not db.is_file():
        raise FileNotFoundError(f"{db}: no MLflow store yet (run the workflow first: `make main`)")
    artifacts = Path(results).resolve() / "mlartifacts"
    return [sys.executable, "-m", "mlflow", "server", "--backend-store-uri", f"sqlite:///{db}",
            "--default-artifact-root", artifacts.as_uri(), "--host", host, "--port", str(port), "--workers", "1"]


def port_taken(port: int, host: str = "127.0.0.1") -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError:
            return True
    return False


#: a process of its own that outlives this one: when the launcher is gone (even by kill -9, which no handler sees),
#: it stops the server's whole process group (MLflow's server, uvicorn, its job workers), then ends
WATCHDOG = """
import os, signal, sys, time
launcher, group = int(sys.argv[1]), int(sys.argv[2])
def alive(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    return True
def group_alive():
    try:
        os.killpg(group, 0)
    except ProcessLookupError:
        return False
    return True
while alive(launcher) and group_alive():
    time.sleep(0.5)
if group_alive():
    os.killpg(group, signal.SIGTERM)
    for _ in range(20):
        time.sleep(0.5)
        if not group_alive():
            break
    else:
        os.killpg(group, signal.SIGKILL)
"""


def serve(cmd: list[str], env: dict) -> int:
    """Runs the server in a new session (its own process group) and stops the group with this process: on SIGTERM,
    SIGINT or SIGHUP here, and through a watchdog process when this one is killed outright."""
    proc = subprocess.Popen(cmd, env=env, start_new_session=True)
    subprocess.Popen([sys.executable, "-c", WATCHDOG, str(os.getpid()), str(proc.pid)], start_new_session=True,
                     stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def stop(*_):
        try:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(timeout=10)
        except ProcessLookupError:
            pass
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)

    for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
        signal.signal(sig, lambda *_: (stop(), sys.exit(0)))
    try:
        return proc.wait()
    finally:
        stop()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--results", type=Path, default=Path("results"))
    parser.add_argument("--port", type=int, default=int(os.environ.get("PORT", 5000)))
    parser.add_argument("--scale", default=os.environ.get("SCALE", "tiny"), help="the experiment the link opens")
    args = parser.parse_args(argv)
    remote = os.environ.get("MLFLOW_TRACKING_URI", "")
    if remote.startswith(("http://", "https://")):
        print(f"MLFLOW_TRACKING_URI={remote}: the runs are on that server; open its UI")
        return 0
    try:
        cmd = command(args.results, args.port)
    except FileNotFoundError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    if port_taken(args.port):
        print(f"error: port {args.port} on 127.0.0.1 is already in use (another dashboard?); choose another with "
              f"`make dashboard PORT=5001` or --port", file=sys.stderr)
        return 1
    env = dict(os.environ, **TELEMETRY_OFF)
    link = dashboard_link(args.results, args.port, args.scale)
    print(f"dashboard: {link}  (store {args.results.resolve() / 'mlflow.db'}; Ctrl-C stops)", flush=True)
    return serve(cmd, env)


def dashboard_link(results: Path, port: int, scale: str) -> str:
    """The page a user should land on: the runs table of this scale's experiment (model training), in the shared
    view with the quality columns (tracking.set_dashboard_view)."""
    base = f"http://127.0.0.1:{port}"
    os.environ.update(TELEMETRY_OFF)
    from mlflow.tracking import MlflowClient

    experiment = MlflowClient(f"sqlite:///{Path(results).resolve() / 'mlflow.db'}").get_experiment_by_name(
        f"avatarlab-{scale}")
    if experiment is None:
        print(f"note: no experiment avatarlab-{scale} in the store yet; opening the home page", file=sys.stderr)
        return base
    return f"{base}/#/experiments/{experiment.experiment_id}/runs?viewStateShareKey={VIEW_KEY}"


if __name__ == "__main__":
    sys.exit(main())
