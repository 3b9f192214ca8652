"""A study's recording in a browser: rerun's web viewer on one port, ``web_port``, bound to 127.0.0.1 only.

Two servers make it, both on 127.0.0.1:

* the front server on ``web_port``, a thread of this process: ``/`` without a ``url`` query redirects to the viewer
  told where its recording is (``/?url=http://<the address asked>/recording.rrd``), ``/recording.rrd`` is the recording
  file, and every other request is passed on to rerun's viewer server;
* rerun's viewer server (``rerun --serve-web`` given that http address: rerun then hosts only the viewer's page and
  its WebAssembly, no gRPC server) on a free port of its own, which only the front server talks to.

The viewer reads the .rrd over HTTP, once. Given the file itself (``rerun --serve-web FILE``), rerun-sdk 0.41's gRPC
server keeps one of its threads at a whole core after loading it, for as long as it runs (benchmarks/viewer_idle.py).
From another machine, tunnel ``web_port`` (:func:`tunnel_line`) and open :func:`url` there.
"""

from __future__ import annotations

import getpass
import http.server
import os
import pathlib
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.parse
import urllib.request

from cpgjax.studies import launch as study_launch
from cpgjax.study.spec import StudyError

HOST = "127.0.0.1"
DEFAULT_WEB_PORT = 9090
START_S = 20.0  # how long rerun's viewer server may take to listen
RECORDING_PATH = "/recording.rrd"  # where the front server serves the recording
CHUNK_BYTES = 1 << 16
LOOPBACK_NAMES = (HOST, "localhost")  # the host names a browser here or at a tunnel's local end asks for


def rerun_executable() -> str | None:
    """The rerun command: the venv's, also when the venv is not activated, else the one on PATH."""
    beside = pathlib.Path(sys.executable).parent / "rerun"
    return str(beside) if beside.exists() else shutil.which("rerun")


def url(web_port: int) -> str:
    """The address to open: the front server redirects it to the viewer with the recording."""
    return f"http://{HOST}:{web_port}/"


def viewer_location(host: str, query: str) -> str:
    """Where ``/`` redirects a browser that asked for ``host`` (the Host header: through a tunnel, the local end):
    the viewer's page with the recording's address added to the query's other parameters."""
    recording = urllib.parse.urlencode({"url": f"http://{host}{RECORDING_PATH}"})
    return f"/?{query}&{recording}" if query else f"/?{recording}"


def tunnel_line(web_port: int) -> str:
    """The ssh command that makes a remote server's viewer reachable on the local machine's same port."""
    return f"ssh -N -L {web_port}:{HOST}:{web_port} {getpass.getuser()}@{socket.gethostname()}"


def _listening(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.settimeout(0.2)
        return s.connect_ex((HOST, port)) == 0


def _front_handler(recording: pathlib.Path, viewer_port: int) -> type[http.server.BaseHTTPRequestHandler]:
    """The front server's requests: the redirect of ``/``, the recording, and rerun's viewer files passed on."""

    class Front(http.server.BaseHTTPRequestHandler):
        # HTTP/1.0 (the default): one request per connection, a body without a length ends with the connection
        def do_GET(self):  # noqa: N802 (http.server's name)
            path, _, query = self.path.partition("?")
            host = self.headers.get("Host", f"{HOST}:{self.server.server_port}")
            if urllib.parse.urlsplit(f"http://{host}").hostname not in LOOPBACK_NAMES:
                # a page of another site that renamed itself to 127.0.0.1 (DNS rebinding) reads nothing
                self.send_error(403, f"this viewer answers requests for {', '.join(LOOPBACK_NAMES)} only")
            elif path == "/" and "url" not in urllib.parse.parse_qs(query):
                self.send_response(302)
                self.send_header("Location", viewer_location(host, query))
                self.end_headers()
            elif path == RECORDING_PATH:
                self.send_response(200)
                self.send_header("Content-Type", "application/octet-stream")
                self.send_header("Content-Length", str(recording.stat().st_size))
                self.end_headers()
                with recording.open("rb") as f:
                    shutil.copyfileobj(f, self.wfile, CHUNK_BYTES)
            else:
                self._pass_on()

        def _pass_on(self):
            try:
                answer = urllib.request.urlopen(f"http://{HOST}:{viewer_port}{self.path}", timeout=START_S)
            except urllib.error.HTTPError as err:
                answer = err
            except urllib.error.URLError as err:  # rerun's viewer server not (or no longer) listening
                self.send_error(502, f"rerun's viewer server: {err.reason}")
                return
            with answer:
                self.send_response(answer.status)
                for name in ("Content-Type", "Content-Length"):
                    if answer.headers.get(name):
                        self.send_header(name, answer.headers[name])
                self.end_headers()
                shutil.copyfileobj(answer, self.wfile, CHUNK_BYTES)

        def log_message(self, *args):  # the terminal shows the command's own lines only
            pass

    return Front


class Served:
    """The running viewer: rerun's viewer server (``proc``, in a process group of its own) and the front server."""

    def __init__(self, proc: subprocess.Popen, front: http.server.ThreadingHTTPServer):
        self.proc = proc
        self.front = front
        self.pid = proc.pid

    def wait(self) -> int:
        """Until rerun's viewer server ends: its exit status."""
        return self.proc.wait()


def serve(recording, web_port: int = DEFAULT_WEB_PORT) -> Served:
    """Serve the recording in rerun's web viewer on 127.0.0.1 only; returns once both servers listen.

    Raises:
      StudyError: no rerun command, the port in use or out of range, or a viewer server that exits or never listens;
        the message names the port or the cause.
    """
    if not 1024 <= web_port <= 65535:
        raise StudyError(f"--port {web_port} is outside the allowed range 1024 … 65535 (an unprivileged TCP port)")
    rerun = rerun_executable()
    if rerun is None:
        raise StudyError("the rerun viewer is not installed (pip install rerun-sdk)")
    viewer_port = study_launch.free_port()
    try:
        front = http.server.ThreadingHTTPServer((HOST, web_port), _front_handler(pathlib.Path(recording), viewer_port))
    except OSError:
        raise StudyError(f"--port {web_port} is in use on {HOST}: pass another --port") from None
    threading.Thread(target=front.serve_forever, name="viewer-front", daemon=True).start()
    # its own process group: the rerun command is a launcher whose server is a child, and stop() ends both
    proc = subprocess.Popen(
        [
            rerun,
            "--serve-web",
            "--bind",
            HOST,
            "--web-viewer-port",
            str(viewer_port),
            "--hide-welcome-screen",
            f"http://{HOST}:{web_port}{RECORDING_PATH}",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    served = Served(proc, front)
    deadline = time.monotonic() + START_S
    while not _listening(viewer_port):
        if proc.poll() is not None:
            stop(served)
            raise StudyError(f"the rerun web viewer exited at once (status {proc.returncode})")
        if time.monotonic() > deadline:
            stop(served)
            raise StudyError(f"the rerun web viewer did not listen on {HOST}:{viewer_port} within {START_S:g} s")
        time.sleep(0.1)
    return served


def stop(served: Served) -> None:
    """End the web viewer started by :func:`serve`: the front server, rerun's launcher and its server."""
    served.front.shutdown()
    served.front.server_close()
    try:
        os.killpg(served.proc.pid, signal.SIGTERM)
    except ProcessLookupError:
        return
    try:
        served.proc.wait(10)
    except subprocess.TimeoutExpired:
        os.killpg(served.proc.pid, signal.SIGKILL)
        served.proc.wait()
