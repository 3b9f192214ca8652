"""``cpgjax show DIR --web``: rerun's web viewer serving a study's recording on one port, bound to 127.0.0.1 only.
Over plain HTTP, the plain address leads to the viewer told where the recording is, and that address serves the
recording file. Loaded in headless Chromium through the DevTools protocol from the plain address, the recording the
viewer holds (saved through its own handle and read back) has the robot's entities, and a screenshot is not blank;
``ss`` shows nothing of it listening on another address. Idle, the viewer's processes use almost no CPU."""

import base64
import json
import os
import pathlib
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.parse
import urllib.request

import imageio.v3 as iio
import numpy as np
import pytest
import rerun as rr
from rerun.chunk import RrdReader
from websockets.sync.client import connect

from cpgjax.studies import launch as study_launch
from cpgjax.studies import viewer
from cpgjax.study import scene
from cpgjax.trial.condition import Condition
from tests.study.test_scene import _synthetic_log

REPO = pathlib.Path(__file__).resolve().parents[2]
LOAD_S = 90.0  # the viewer's WebAssembly compiles in a software-rendered browser: allow for a loaded machine
IDLE_PERCENT = 5.0  # of one core, the viewer's processes together (the recording loaded into rerun's gRPC server: 100)


def _descendants(pid: int) -> set[int]:
    children = {pid}
    for _ in range(4):
        for entry in os.listdir("/proc"):
            if entry.isdigit():
                try:
                    ppid = int(open(f"/proc/{entry}/stat").read().rsplit(")", 1)[1].split()[1])
                except (OSError, IndexError, ValueError):
                    continue
                if ppid in children:
                    children.add(int(entry))
    return children


def _running(pid: int) -> bool:
    """The process exists and is not a zombie (ended, its status not yet collected)."""
    try:
        return open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[0] not in "ZX"
    except OSError:
        return False


class _DevTools:
    """The least of the Chrome DevTools protocol: numbered calls on one websocket, events skipped."""

    def __init__(self, ws):
        self.ws = ws
        self.n = 0

    def call(self, method: str, session: str | None = None, **params):
        self.n += 1
        self.ws.send(
            json.dumps(
                {"id": self.n, "method": method, "params": params, **({"sessionId": session} if session else {})}
            )
        )
        while True:
            answer = json.loads(self.ws.recv(timeout=60))
            if answer.get("id") == self.n:
                return answer.get("result", answer)


def _record(folder) -> str:
    """``folder/recording.rrd``: one rollout; returns its entity path."""
    rollout = scene.Rollout(
        log=_synthetic_log(),
        group="vmc_tegotae",
        controller="vmc_tegotae",
        seed=0,
        condition=Condition(friction=0.6, slope_deg=5.0, payload_kg=0.0),
    )
    rec = rr.RecordingStream("cpgjax_web_test")
    rec.save(str(folder / "recording.rrd"))
    base = "/" + scene.log_rollout(rec, rollout)
    rec.flush()
    rec.disconnect()
    return base


class _NoRedirect(urllib.request.HTTPRedirectHandler):
    def redirect_request(self, *args):
        return None


def test_the_plain_address_leads_to_the_viewer_with_the_recording(tmp_path):
    """``/`` answers with a redirect to the viewer's page told the recording's address (the Host asked for, as a
    tunnel's local end would be); that address is the recording file; the viewer's own files are passed on; a request
    naming another host is refused."""
    _record(tmp_path)
    served = viewer.serve(tmp_path / "recording.rrd", study_launch.free_port())
    try:
        port = served.front.server_port
        plain = viewer.url(port)
        assert plain == f"http://127.0.0.1:{port}/"
        with pytest.raises(urllib.error.HTTPError) as redirect:
            urllib.request.build_opener(_NoRedirect).open(plain, timeout=30)
        assert redirect.value.code == 302
        location = redirect.value.headers["Location"]
        recording_url = urllib.parse.parse_qs(urllib.parse.urlsplit(location).query)["url"]
        assert recording_url == [f"http://127.0.0.1:{port}/recording.rrd"]
        with urllib.request.urlopen(recording_url[0], timeout=30) as answer:
            assert answer.read() == (tmp_path / "recording.rrd").read_bytes()
        with urllib.request.urlopen(plain, timeout=30) as page:  # followed: rerun's viewer page
            assert page.url == urllib.parse.urljoin(plain, location) and b"re_viewer.js" in page.read()
        through_a_tunnel = urllib.request.Request(plain + "?renderer=webgl", headers={"Host": "localhost:8000"})
        with pytest.raises(urllib.error.HTTPError) as redirect:
            urllib.request.build_opener(_NoRedirect).open(through_a_tunnel, timeout=30)
        assert redirect.value.headers["Location"] == (
            "/?renderer=webgl&url=" + urllib.parse.quote("http://localhost:8000/recording.rrd", safe="")
        )
        for path in ("", "recording.rrd"):  # another site's name for this address gets nothing
            with pytest.raises(urllib.error.HTTPError) as refused:
                urllib.request.urlopen(
                    urllib.request.Request(plain + path, headers={"Host": f"evil.example:{port}"}), timeout=30
                )
            assert refused.value.code == 403
        with urllib.request.urlopen(urllib.parse.urljoin(plain, "re_viewer_bg.wasm"), timeout=60) as wasm:
            assert wasm.headers["Content-Type"] == "application/wasm" and wasm.read(4) == b"\0asm"
    finally:
        viewer.stop(served)
    assert served.proc.poll() is not None


def test_the_idle_viewer_uses_almost_no_cpu():
    """benchmarks/viewer_idle.py over a few seconds: `cpgjax show --web` and every process it started, idle."""
    done = subprocess.run(
        [sys.executable, str(REPO / "benchmarks" / "viewer_idle.py"), "--seconds", "6", "--settle-s", "3"],
        capture_output=True,
        text=True,
        timeout=180,
        cwd=REPO,
        env=dict(os.environ, JAX_PLATFORMS="cpu"),
    )
    assert done.returncode == 0, done.stderr[-2000:]
    figures = json.loads(done.stdout.splitlines()[-1])
    assert len(figures["processes"]) >= 2, figures  # the command and rerun's viewer server at least
    assert figures["total_percent_of_a_core"] < IDLE_PERCENT, figures


# Python keeps SIGINT ignored in a child of a shell that ignores it (a background job): give the command Python's own
# Ctrl-C handler, as a terminal would.
_WITH_CTRL_C = (
    "import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
    "sys.argv = ['cpgjax', *sys.argv[1:]]; runpy.run_module('cpgjax.cli', run_name='__main__')"
)


def test_ctrl_c_stops_the_viewer_and_says_so(tmp_path):
    """Ctrl-C on a running `cpgjax show --web`: exit 0, "the viewer is stopped" (not a study's "its outputs are
    written"), and no process of it left."""
    _record(tmp_path)
    proc = subprocess.Popen(
        [sys.executable, "-c", _WITH_CTRL_C, "show", str(tmp_path), "--web", "--port", str(study_launch.free_port())],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPO,
        env=dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(REPO)),
    )
    try:
        printed = ""
        while "Ctrl-C stops it" not in printed:
            line = proc.stdout.readline()
            assert line, printed + proc.stderr.read()
            printed += line
        ours = _descendants(proc.pid) - {proc.pid}
        assert ours  # rerun's launcher and its server
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert "cpgjax show: the viewer is stopped" in err and "outputs are written" not in err and "Traceback" not in err
    assert not [pid for pid in ours if _running(pid)]


@pytest.fixture
def served(tmp_path):
    base = _record(tmp_path)
    port = study_launch.free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "cpgjax.cli", "show", str(tmp_path), "--web", "--port", str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=dict(os.environ, JAX_PLATFORMS="cpu"),
    )
    lines = []
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not any("ssh -N" in line for line in lines):
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line)
    try:
        yield port, proc, "".join(lines), base
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()


@pytest.mark.skipif(
    shutil.which("chromium") is None or shutil.which("ss") is None,
    reason="needs Debian's chromium (headless) and ss (iproute2); .ci/run installs them",
)
def test_show_web_serves_the_recording_on_loopback_only(served, tmp_path):
    port, proc, printed, base = served
    url = f"http://127.0.0.1:{port}/"  # the plain address
    assert f"  {url}\n" in printed
    assert f"ssh -N -L {port}:127.0.0.1:{port} " in printed
    # what listens, and where: every socket of the command's processes is on 127.0.0.1, its port among them
    ours = _descendants(proc.pid)
    listening = [
        line
        for line in subprocess.run(["ss", "-Hltnup"], capture_output=True, text=True).stdout.splitlines()
        if any(int(p) in ours for p in re.findall(r"pid=(\d+)", line))
    ]
    local = {line.split()[4] for line in listening}
    assert f"127.0.0.1:{port}" in local, listening
    assert all(address.startswith("127.0.0.1:") for address in local), listening
    with socket.socket() as s:  # and not reachable through another of this machine's addresses
        s.settimeout(1)
        other = socket.gethostbyname(socket.gethostname())
        assert other.startswith("127.") or s.connect_ex((other, port)) != 0

    log = open(tmp_path / "chromium.log", "w")
    browser = subprocess.Popen(
        [
            "chromium",
            "--headless=new",
            "--no-sandbox",
            "--disable-gpu",
            "--use-angle=swiftshader",
            "--enable-unsafe-swiftshader",
            "--window-size=1280,800",
            "--remote-debugging-address=127.0.0.1",
            "--remote-debugging-port=0",
            f"--user-data-dir={tmp_path / 'profile'}",
            "about:blank",
        ],
        stdout=subprocess.DEVNULL,
        stderr=log,
    )
    try:
        deadline = time.monotonic() + 30
        found = None
        while found is None and time.monotonic() < deadline:
            time.sleep(0.2)
            found = re.search(r"DevTools listening on (ws://\S+)", (tmp_path / "chromium.log").read_text())
        assert found is not None, (tmp_path / "chromium.log").read_text()[-2000:]
        with connect(found[1], max_size=2**28, open_timeout=30) as ws:
            _look_at_the_viewer(_DevTools(ws), url, base, tmp_path)
    finally:
        browser.terminate()
        browser.wait(20)
        log.close()


def _look_at_the_viewer(devtools: _DevTools, url: str, base: str, tmp_path) -> None:
    """Open the plain address; the page it leads to must be the viewer told the recording's address, its handle
    must hold our recording, and the page must be drawn."""
    target = devtools.call("Target.createTarget", url=url)["targetId"]
    session = devtools.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
    # The viewer's handle (window._handle, rerun's WebHandle) saves the recording it has loaded.
    state = (
        "(() => { try { const h = window._handle; if (!h) return 'no viewer yet';"
        " if (h.has_panicked()) return 'panicked: ' + h.panic_message();"
        " const b = h.save_recording(); let s = '';"
        " for (let i = 0; i < b.length; i += 8192) s += String.fromCharCode(...b.subarray(i, i + 8192));"
        " return btoa(s); } catch (e) { return String(e); } })()"
    )
    saved, entities, deadline = "", set(), time.monotonic() + LOAD_S
    wanted = {
        f"{base}/world/robot/trunk",
        f"{base}/world/robot/FR_calf/spheres",
        f"{base}/world/contact_force/RL",
        f"{base}/world/floor",
        f"{base}/cpg/phase_rad/FL",
    }
    while time.monotonic() < deadline and not wanted <= entities:
        saved = devtools.call("Runtime.evaluate", session, expression=state, returnByValue=True)["result"]["value"]
        if saved.startswith("panicked"):
            break
        if len(saved) > 1000:  # a recording: read it back as rerun does
            (tmp_path / "held.rrd").write_bytes(base64.b64decode(saved))
            entities = {chunk.entity_path for chunk in RrdReader(tmp_path / "held.rrd").stream()}
        time.sleep(1.0)
    assert wanted <= entities, (saved[:300], sorted(entities)[:20])
    location = devtools.call("Runtime.evaluate", session, expression="window.location.href", returnByValue=True)[
        "result"
    ]["value"]
    assert urllib.parse.parse_qs(urllib.parse.urlsplit(location).query)["url"] == [url + "recording.rrd"], location
    time.sleep(2.0)  # let it draw
    shot = base64.b64decode(devtools.call("Page.captureScreenshot", session, format="png")["data"])
    (tmp_path / "viewer.png").write_bytes(shot)
    pixels = iio.imread(shot).astype(float)
    assert pixels.shape[1] == 1280 and pixels.shape[0] > 600 and pixels[..., :3].std() > 20  # drawn, not blank
    assert len(np.unique(pixels[::8, ::8, :3].reshape(-1, 3), axis=0)) > 200
