"""A study's recording in a browser: rerun's web viewer (``rerun --serve-web``) serving one ``.rrd``, bound to
127.0.0.1 only: the viewer page on ``web_port`` and the gRPC server it reads the recording from on ``grpc_port``.
From another machine, tunnel both ports (:func:`tunnel_line`) and open :func:`url` there.
"""

from __future__ import annotations

import getpass
import os
import pathlib
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.parse

from cpgjax.study.spec import StudyError

HOST = "127.0.0.1"
DEFAULT_WEB_PORT = 9090
START_S = 20.0  # how long the server may take to listen


def rerun_executable() -> str | None:
    """The rerun command: the venv's, also when the venv is not activated, else the one on PATH."""
    beside = pathlib.Path(sys.executable).parent / "rerun"
    return str(beside) if beside.exists() else shutil.which("rerun")


def url(web_port: int, grpc_port: int) -> str:
    """The viewer page, told where its recording is."""
    source = urllib.parse.quote(f"rerun+http://{HOST}:{grpc_port}/proxy", safe="")
    return f"http://{HOST}:{web_port}/?url={source}"


def tunnel_line(web_port: int, grpc_port: int) -> str:
    """The ssh command that makes a remote server's viewer reachable on the local machine's same ports."""
    return (f"ssh -N -L {web_port}:{HOST}:{web_port} -L {grpc_port}:{HOST}:{grpc_port} "
            f"{getpass.getuser()}@{socket.gethostname()}")


def _listening(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.settimeout(0.2)
        return s.connect_ex((HOST, port)) == 0


def _free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((HOST, port))
        except OSError:
            return False
    return True


def serve(recording, web_port: int = DEFAULT_WEB_PORT, grpc_port: int | None = None) -> subprocess.Popen:
    """Start rerun's web viewer on the recording, on 127.0.0.1 only; returns once both ports listen.

    Raises:
      StudyError: no rerun command, a port in use or out of range, or a server that exits or never listens; the
        message names the port or the cause.
    """
    grpc_port = web_port + 1 if grpc_port is None else grpc_port
    for name, port in (("--port", web_port), ("the recording's port (--port + 1)", grpc_port)):
        if not 1024 <= port <= 65535:
            raise StudyError(f"{name} {port} is outside the allowed range 1024 … 65535 (an unprivileged TCP port)")
        if not _free(port):
            raise StudyError(f"{name} {port} is in use on {HOST}: pass another --port")
    rerun = rerun_executable()
    if rerun is None:
        raise StudyError("the rerun viewer is not installed (pip install rerun-sdk)")
    # its own process group: the rerun command is a launcher whose server is a child, and stop() ends both
    proc = subprocess.Popen([rerun, "--serve-web", "--bind", HOST, "--web-viewer-port", str(web_port), "--port",
                             str(grpc_port), "--hide-welcome-screen", str(recording)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + START_S
    while not (_listening(web_port) and _listening(grpc_port)):
        if proc.poll() is not None:
            raise StudyError(f"the rerun web viewer exited at once (status {proc.returncode})")
        if time.monotonic() > deadline:
            stop(proc)
            raise StudyError(f"the rerun web viewer did not listen on {HOST}:{web_port} within {START_S:g} s")
        time.sleep(0.1)
    return proc


def stop(proc: subprocess.Popen) -> None:
    """End the web viewer started by :func:`serve` (its launcher and its server)."""
    try:
        os.killpg(proc.pid, signal.SIGTERM)
    except ProcessLookupError:
        return
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
