"""Workflow steps started from a process that has already imported the heavy libraries.

    python -m avatarlab.runtime.forkserver avatarlab.avatar.finetune finetune.subject=... threads=1

does what `python -m avatarlab.avatar.finetune ...` does - same arguments, working directory, environment, standard
streams, exit code - but about 6 s sooner: at smoke scale a step is mostly the import of torch (with `torch._dynamo`,
which torch.optim and torchvision pull in), MLflow with its SQL store, Hydra, kornia and scipy, and the workflow runs
~135 of them. The first step of a run starts a server in the background (and runs itself the plain way); later steps
ask the server for a fork of itself, which runs the step.

What the server imports is third-party code only (`PRELOAD`): avatarlab's own modules are imported afresh by every
step, so an edit of the code is seen by the next step. It imports and computes nothing else (no tensor op has run, so
no OpenMP pool exists to be copied by the fork - the way DataLoader workers fork after `import torch`), listens on a
user-only Unix socket in /tmp whose name hashes the interpreter, `sys.path` and the installed packages (another
checkout or an upgraded environment gets its own server), and exits after `IDLE_SECONDS` without a request.

Per step, the server forks a supervisor, which forks the step. The supervisor sends the step's exit status to the
client and, if the client goes away (killed, a cancelled workflow), terminates the step; SIGTERM/SIGINT/SIGHUP sent to
the client are passed on to the step. `AVATARLAB_FORKSERVER=0` (or a server that cannot be reached) runs the step as a
plain `python -m`; `python -m avatarlab.runtime.forkserver --stop` ends the server at once.
"""
from __future__ import annotations

import array
import contextlib
import fcntl
import hashlib
import importlib
import json
import os
import select
import signal
import socket
import stat
import struct
import subprocess
import sys
import time
from pathlib import Path

#: imported once by the server: third-party packages whose import is most of a smoke step's time (cv2 is left out: its
#: import starts a worker thread that a fork would not copy)
PRELOAD = ("numpy", "torch", "torch._dynamo", "torch.optim", "torchvision", "omegaconf", "hydra", "hydra.main",
           "mlflow", "mlflow.tracking", "mlflow.store.tracking.sqlalchemy_store", "kornia", "scipy.spatial",
           "scipy.interpolate", "scipy.optimize", "scipy.ndimage", "PIL.Image", "dlib", "yaml", "jsonschema")
IDLE_SECONDS = 120
ENV_SWITCH = "AVATARLAB_FORKSERVER"
ENV_IDLE = "AVATARLAB_FORKSERVER_IDLE"  # seconds without a request before the server exits (IDLE_SECONDS)
_HEADER = struct.Struct("!I")


def enabled(env=os.environ) -> bool:
    """On unless AVATARLAB_FORKSERVER says 0/false/no/off; off by default inside a SLURM job (one step per job: a
    server would only cost its start)."""
    value = env.get(ENV_SWITCH, "0" if "SLURM_JOB_ID" in env else "1")
    return value.strip().lower() not in ("0", "false", "no", "off")


def socket_path() -> Path:
    """One server per interpreter, import path and set of installed packages (their folders' modification times)."""
    paths = [p for p in sys.path[1:] if p]
    stamps = []
    for p in paths:
        with contextlib.suppress(OSError):
            stamps.append(os.stat(p).st_mtime_ns)
    key = json.dumps([sys.executable, paths, stamps, PRELOAD, os.stat(__file__).st_mtime_ns])
    folder = Path(f"/tmp/avatarlab-forkserver-{os.getuid()}")
    return folder / (hashlib.sha256(key.encode()).hexdigest()[:20] + ".sock")


# ---------------------------------------------------------------------------------------------------- messages
def _send(conn: socket.socket, message: dict, fds: list[int] | None = None) -> None:
    data = json.dumps(message).encode()
    payload = _HEADER.pack(len(data)) + data
    if fds:
        conn.sendmsg([payload], [(socket.SOL_SOCKET, socket.SCM_RIGHTS, array.array("i", fds))])
    else:
        conn.sendall(payload)


def _read_exact(conn: socket.socket, size: int, data: bytes = b"") -> bytes | None:
    """`data` completed to `size` bytes from the connection (None if it ends first)."""
    while len(data) < size:
        more = conn.recv(size - len(data))
        if not more:
            return None
        data += more
    return data


def _recv(conn: socket.socket, with_fds: int = 0) -> tuple[dict | None, list[int]]:
    """One message (None at end of stream) and the file descriptors sent with it."""
    fds: list[int] = []
    if with_fds:
        data, fds, _, _ = socket.recv_fds(conn, _HEADER.size, with_fds)
    else:
        data = conn.recv(_HEADER.size)
    header = _read_exact(conn, _HEADER.size, data) if data else None
    body = header and _read_exact(conn, _HEADER.unpack(header)[0])
    return (None if body is None else json.loads(body)), fds


# ---------------------------------------------------------------------------------------------------- client
def run_plain(module: str, args: list[str]):
    """What the step would be without the server."""
    os.execv(sys.executable, [sys.executable, "-m", module, *args])


def start_server(path: Path) -> None:
    """Start the server in the background (one at a time: the others find the lock taken), detached from this
    step's streams and session."""
    path.parent.mkdir(mode=0o700, exist_ok=True)
    if not private_folder(path.parent):
        return
    lock = open(path.with_suffix(".lock"), "w")
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        lock.close()
        return  # another step is starting it
    subprocess.Popen([sys.executable, "-m", "avatarlab.runtime.forkserver", "--serve", str(path)], stdin=subprocess.DEVNULL,
                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, pass_fds=(lock.fileno(),),
                     start_new_session=True, env=dict(os.environ, AVATARLAB_FORKSERVER_LOCK=str(lock.fileno())))
    lock.close()


def private_folder(folder: Path) -> bool:
    """The socket folder is a real directory of this user that nobody else may enter (else: no server, the plain
    way; a folder planted by another user must not receive a step's environment and streams)."""
    try:
        info = os.lstat(folder)
    except OSError:
        return False
    return stat.S_ISDIR(info.st_mode) and info.st_uid == os.getuid() and not info.st_mode & 0o077


def connect(path: Path) -> socket.socket | None:
    if not private_folder(path.parent):
        return None
    conn = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        conn.connect(str(path))
    except OSError:
        conn.close()
        return None
    return conn


def run_client(module: str, args: list[str]) -> int:
    path, on = socket_path(), enabled()
    conn = connect(path) if on else None
    if conn is None:
        if on:
            with contextlib.suppress(OSError):
                start_server(path)
        run_plain(module, args)
    request = {"module": module, "args": args, "cwd": os.getcwd(), "env": dict(os.environ), "umask": _umask()}
    try:
        _send(conn, request, [0, 1, 2])
        started, _ = _recv(conn)
    except OSError:
        started = None
    if not started or "pid" not in started:  # the server went away in between: nothing has run yet
        conn.close()
        run_plain(module, args)

    def forward(signum, _frame):
        with contextlib.suppress(OSError):
            _send(conn, {"signal": signum})

    for signum in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
        signal.signal(signum, forward)
    while True:
        try:
            message, _ = _recv(conn)
        except InterruptedError:
            continue
        if message is None:
            print(f"avatarlab error: the step's supervisor (fork server {path}) ended without its exit status",
                  file=sys.stderr)
            return 1
        if "exit" in message:
            return int(message["exit"])


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


# ---------------------------------------------------------------------------------------------------- server
def serve(path: Path) -> None:
    # tracking.TELEMETRY_OFF, spelled out: importing avatarlab.runtime.tracking here would keep a stale copy of it for every step
    os.environ.update({"MLFLOW_DISABLE_TELEMETRY": "true", "DO_NOT_TRACK": "true"})
    for name in PRELOAD:
        with contextlib.suppress(Exception):
            importlib.import_module(name)
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    tmp = path.with_suffix(f".{os.getpid()}.tmp")
    with contextlib.suppress(FileNotFoundError):
        tmp.unlink()
    listener.bind(str(tmp))
    os.chmod(tmp, 0o600)
    listener.listen(64)
    os.replace(tmp, path)  # clients connect only once it listens
    inode = os.stat(path).st_ino
    lock_fd = os.environ.pop("AVATARLAB_FORKSERVER_LOCK", None)
    if lock_fd:
        with contextlib.suppress(OSError):
            os.close(int(lock_fd))
    signal.signal(signal.SIGCHLD, signal.SIG_IGN)  # supervisors are reaped by the kernel
    listener.settimeout(float(os.environ.get(ENV_IDLE) or IDLE_SECONDS))
    try:
        while True:
            try:
                conn, _ = listener.accept()
            except TimeoutError:
                break
            conn.settimeout(30)
            try:
                request, fds = _recv(conn, with_fds=3)
            except OSError:
                conn.close()
                continue
            if request is not None and request.get("stop"):
                conn.close()
                break
            if request is None or len(fds) != 3:
                for fd in fds:
                    os.close(fd)
                conn.close()
                continue
            sys.stdout.flush()
            sys.stderr.flush()
            if os.fork() == 0:
                listener.close()
                conn.settimeout(None)
                supervise(conn, request, fds)
            for fd in fds:
                os.close(fd)
            conn.close()
    finally:
        with contextlib.suppress(OSError):
            if os.stat(path).st_ino == inode:  # still ours (a newer server may have replaced it)
                path.unlink()
                path.with_suffix(".lock").unlink(missing_ok=True)
        listener.close()


def supervise(conn: socket.socket, request: dict, fds: list[int]) -> None:
    """In the supervisor: fork the step, report its exit status, end it when the client goes away."""
    signal.signal(signal.SIGCHLD, signal.SIG_DFL)
    pid = os.fork()
    if pid == 0:
        conn.close()
        run_step(request, fds)
    for fd in fds:
        os.close(fd)
    code = None
    try:
        _send(conn, {"pid": pid})
        while code is None:
            readable, _, _ = select.select([conn], [], [], 0.2)
            if readable:
                message, _ = _recv(conn)
                if message is None:  # the client is gone: end the step as a killed job would end
                    _terminate(pid)
                    os._exit(0)
                if "signal" in message:
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(pid, int(message["signal"]))
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                code = os.waitstatus_to_exitcode(status)
        _send(conn, {"exit": code if code >= 0 else 128 - code})
    except OSError:
        _terminate(pid)
    os._exit(0)


def _terminate(pid: int, grace: float = 10.0) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGTERM)
    end = time.monotonic() + grace
    while time.monotonic() < end:
        with contextlib.suppress(ChildProcessError):
            if os.waitpid(pid, os.WNOHANG)[0]:
                return
        time.sleep(0.1)
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGKILL)


def run_step(request: dict, fds: list[int]) -> None:
    """In the step's process: the client's streams, directory, environment and umask, then `python -m module`."""
    import atexit
    import runpy
    import traceback

    code = 1
    try:
        for target, fd in enumerate(fds):
            os.dup2(fd, target)
            os.close(fd)
        for signum in (signal.SIGTERM, signal.SIGHUP, signal.SIGCHLD):
            signal.signal(signum, signal.SIG_DFL)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        os.chdir(request["cwd"])
        os.environ.clear()
        os.environ.update(request["env"])
        os.umask(int(request["umask"]))
        sys.path[0] = request["cwd"]
        sys.argv = [request["module"], *request["args"]]
        try:
            runpy.run_module(request["module"], run_name="__main__", alter_sys=True)
            code = 0
        except SystemExit as done:
            code = done.code if isinstance(done.code, int) else (0 if done.code is None else 1)
            if not isinstance(done.code, (int, type(None))):
                print(done.code, file=sys.stderr)
        except BaseException:
            traceback.print_exc()
            code = 1
        with contextlib.suppress(BaseException):
            atexit._run_exitfuncs()
    finally:
        with contextlib.suppress(BaseException):
            sys.stdout.flush()
            sys.stderr.flush()
        os._exit(code)


def stop_server() -> bool:
    """Ask this interpreter's server to exit (steps it started go on). -> whether one was running."""
    conn = connect(socket_path())
    if conn is None:
        return False
    with conn:
        _send(conn, {"stop": True})
    return True


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) == 2 and argv[0] == "--serve":
        serve(Path(argv[1]))
        return 0
    if argv == ["--stop"]:
        print("fork server stopped" if stop_server() else "no fork server was running")
        return 0
    if not argv or argv[0].startswith("-"):
        print("usage: python -m avatarlab.runtime.forkserver MODULE [ARGS...]", file=sys.stderr)
        return 2
    return run_client(argv[0], argv[1:])


if __name__ == "__main__":
    sys.exit(main())
