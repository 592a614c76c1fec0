"""The metrics dashboard: the MLflow UI over the workflow's store, on 127.0.0.1 only.

`python -m avatarlab.dashboard [--results results] [--port 5000]` (what `make dashboard` runs). With
MLFLOW_TRACKING_URI set to a shared server (http...), open that server's UI instead: there is nothing to serve here.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path


def command(results: Path, port: int, host: str = "127.0.0.1") -> list[str]:
    db = Path(results).resolve() / "mlflow.db"
    if not db.is_file():
        raise FileNotFoundError(f"{db}: no MLflow store yet (run the workflow first: `make main`)")
    artifacts = Path(results).resolve() / "mlartifacts"
    return [sys.executable, "-m", "mlflow", "server", "--backend-store-uri", f"sqlite:///{db}",
            "--default-artifact-root", artifacts.as_uri(), "--host", host, "--port", str(port), "--workers", "1"]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--results", type=Path, default=Path("results"))
    parser.add_argument("--port", type=int, default=int(os.environ.get("PORT", 5000)))
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
    print(f"dashboard: http://127.0.0.1:{args.port}  (store {args.results.resolve() / 'mlflow.db'}; Ctrl-C stops)")
    return subprocess.call(cmd)


if __name__ == "__main__":
    sys.exit(main())
