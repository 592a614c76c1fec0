"""The fork server runs a step as `python -m` would: arguments, working directory, environment, streams, exit code,
signals; and a step whose client is killed does not live on."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

STEP = '''
import os, sys, time
print("argv", sys.argv[1:])
print("cwd", os.getcwd())
print("env", os.environ.get("STEP_VALUE"))
print("preloaded", "torch" in sys.modules)
print("to stderr", file=sys.stderr)
if "--sleep" in sys.argv:
    open(sys.argv[-1], "w").write(str(os.getpid()))
    time.sleep(60)
if "--raise" in sys.argv:
    raise ValueError("a bad value")
sys.exit(int(sys.argv[1]))
'''


def _env(package_dir: Path, **extra) -> dict:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(package_dir), *sys.path[1:]]),
               AVATARLAB_FORKSERVER="1", AVATARLAB_FORKSERVER_IDLE="60", **extra)
    env.pop("SLURM_JOB_ID", None)
    return env


def _run(env, cwd, *args, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "avatarlab.runtime.forkserver", "fs_step_module", *args], env=env, cwd=cwd,
                          capture_output=True, text=True, timeout=120, **kw)


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """A module on its own import path (so its own server), the server started by a first plain run."""
    root = tmp_path_factory.mktemp("forkserver")
    (root / "fs_step_module.py").write_text(STEP)
    env = _env(root)
    first = _run(env, root, "3", "plain")
    where = subprocess.run([sys.executable, "-c", "from avatarlab.runtime.forkserver import socket_path; print(socket_path())"],
                           env=env, cwd=root, capture_output=True, text=True, check=True).stdout.strip()
    deadline = time.monotonic() + 90
    while not Path(where).exists() and time.monotonic() < deadline:
        time.sleep(0.2)
    assert Path(where).exists(), "the first step starts the server"
    yield root, env, first
    subprocess.run([sys.executable, "-m", "avatarlab.runtime.forkserver", "--stop"], env=env, cwd=root, timeout=30)


def test_a_forked_step_behaves_as_python_minus_m(served, tmp_path):
    root, env, first = served
    assert first.returncode == 3 and "preloaded False" in first.stdout, "the first step ran the plain way"
    plain = subprocess.run([sys.executable, "-m", "fs_step_module", "3", "a b", "c'd"], env=dict(env, STEP_VALUE="x y"),
                           cwd=tmp_path, capture_output=True, text=True, timeout=60)
    forked = _run(dict(env, STEP_VALUE="x y"), tmp_path, "3", "a b", "c'd")
    assert "preloaded True" in forked.stdout, forked.stdout + forked.stderr
    assert forked.returncode == plain.returncode == 3
    assert forked.stdout.replace("preloaded True", "preloaded False") == plain.stdout
    assert f"cwd {tmp_path}" in forked.stdout and "env x y" in forked.stdout
    assert forked.stderr == plain.stderr == "to stderr\n"


def test_an_exception_in_a_forked_step_is_exit_1_with_its_traceback(served):
    root, env, _ = served
    out = _run(env, root, "0", "--raise")
    assert out.returncode == 1 and "ValueError: a bad value" in out.stderr and "preloaded True" in out.stdout


def _wait_for(path: Path, seconds=30) -> int:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if path.exists() and path.read_text():
            return int(path.read_text())
        time.sleep(0.1)
    raise AssertionError(f"{path} was not written")


def _gone(pid: int, seconds=20) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        state = Path(f"/proc/{pid}/stat").read_text().split()[2] if Path(f"/proc/{pid}/stat").exists() else "X"
        if state == "Z":
            return True
        time.sleep(0.2)
    return False


def _sleeping_step(served, tmp_path) -> tuple[subprocess.Popen, int]:
    """A client whose forked step sleeps: the client's process and the step's pid."""
    root, env, _ = served
    pid_file = tmp_path / "pid"
    client = subprocess.Popen([sys.executable, "-m", "avatarlab.runtime.forkserver", "fs_step_module", "0", "--sleep",
                               str(pid_file)], env=env, cwd=root, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return client, _wait_for(pid_file)


def test_sigterm_to_the_client_ends_the_step(served, tmp_path):
    client, step = _sleeping_step(served, tmp_path)
    assert step != client.pid, "the step runs in a fork of the server"
    client.send_signal(signal.SIGTERM)
    assert client.wait(timeout=30) == 128 + signal.SIGTERM
    assert _gone(step)


def test_a_killed_client_takes_its_step_with_it(served, tmp_path):
    client, step = _sleeping_step(served, tmp_path)
    client.kill()
    client.wait(timeout=30)
    assert _gone(step), "the supervisor ends a step whose client is gone"


def test_switched_off_it_runs_the_plain_way(served, tmp_path):
    root, env, _ = served
    out = _run(dict(env, AVATARLAB_FORKSERVER="0"), tmp_path, "5")
    assert out.returncode == 5 and "preloaded False" in out.stdout
    inside_slurm = dict(env, SLURM_JOB_ID="7")
    inside_slurm.pop("AVATARLAB_FORKSERVER")
    assert "preloaded False" in _run(inside_slurm, tmp_path, "0").stdout, "off by default in a SLURM job"


def test_a_socket_folder_others_can_enter_is_not_used(tmp_path):
    from avatarlab.runtime.forkserver import connect, private_folder

    folder = tmp_path / "sockets"
    folder.mkdir(mode=0o700)
    assert private_folder(folder)
    folder.chmod(0o755)
    assert not private_folder(folder) and connect(folder / "x.sock") is None
    link = tmp_path / "link"
    link.symlink_to(folder)
    assert not private_folder(link), "a symlink is not the folder"
