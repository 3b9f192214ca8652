"""``cpgjax show DIR --web``: rerun's web viewer serving a study's recording, bound to 127.0.0.1 only, loaded in
headless Chromium through the DevTools protocol: the recording the viewer holds (saved through its own handle and read
back) has the robot's entities, and a screenshot is not blank; ``ss`` shows nothing of it listening on another
address."""

import base64
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time

import imageio.v3 as iio
import numpy as np
import pytest
import rerun as rr
from rerun.chunk import RrdReader
from websockets.sync.client import connect

from cpgjax.studies import viewer
from cpgjax.study import scene
from tests.test_scene import _synthetic_log

pytestmark = pytest.mark.skipif(shutil.which("chromium") is None or shutil.which("ss") is None,
                                reason="needs Debian's chromium (headless) and ss (iproute2); .ci/run installs them")
LOAD_S = 90.0  # the viewer's WebAssembly compiles in a software-rendered browser: allow for a loaded machine


def _free_port_pair() -> int:
    for _ in range(50):
        port = int(np.random.default_rng().integers(20000, 60000))
        if viewer._free(port) and viewer._free(port + 1):
            return port
    raise RuntimeError("no free port pair")


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


class _DevTools:
    """The least of the Chrome DevTools protocol: numbered calls on one websocket, events skipped."""

    def __init__(self, ws):
        self.ws = ws
        self.n = 0

    def call(self, method: str, session: str | None = None, **params):
        self.n += 1
        self.ws.send(json.dumps({"id": self.n, "method": method, "params": params,
                                 **({"sessionId": session} if session else {})}))
        while True:
            answer = json.loads(self.ws.recv(timeout=60))
            if answer.get("id") == self.n:
                return answer.get("result", answer)


@pytest.fixture
def served(tmp_path):
    rollout = scene.Rollout(_synthetic_log(), "vmc_tegotae", "vmc_tegotae", 0, 0.6, 5.0, 0.0)
    rec = rr.RecordingStream("cpgjax_web_test")
    rec.save(str(tmp_path / "recording.rrd"))
    base = "/" + scene.log_rollout(rec, rollout)
    rec.flush()
    rec.disconnect()
    port = _free_port_pair()
    proc = subprocess.Popen([sys.executable, "-m", "cpgjax.cli", "show", str(tmp_path), "--web", "--port", str(port)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=dict(os.environ, JAX_PLATFORMS="cpu"))
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


def test_show_web_serves_the_recording_on_loopback_only(served, tmp_path):
    port, proc, printed, base = served
    url = viewer.url(port, port + 1)
    assert f"  {url}\n" in printed
    assert f"ssh -N -L {port}:127.0.0.1:{port} -L {port + 1}:127.0.0.1:{port + 1}" in printed
    # what listens, and where: every socket of the command's processes is on 127.0.0.1, both ports among them
    ours = _descendants(proc.pid)
    listening = [line for line in subprocess.run(["ss", "-Hltnup"], capture_output=True, text=True).stdout.splitlines()
                 if any(int(p) in ours for p in re.findall(r"pid=(\d+)", line))]
    local = {line.split()[4] for line in listening}
    assert {f"127.0.0.1:{port}", f"127.0.0.1:{port + 1}"} <= local, listening
    assert all(address.startswith("127.0.0.1:") for address in local), listening
    with socket.socket() as s:  # and not reachable through another of this machine's addresses
        s.settimeout(1)
        other = socket.gethostbyname(socket.gethostname())
        assert other.startswith("127.") or s.connect_ex((other, port)) != 0

    log = open(tmp_path / "chromium.log", "w")
    browser = subprocess.Popen(
        ["chromium", "--headless=new", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader",
         "--enable-unsafe-swiftshader", "--window-size=1280,800", "--remote-debugging-address=127.0.0.1",
         "--remote-debugging-port=0", f"--user-data-dir={tmp_path / 'profile'}", "about:blank"],
        stdout=subprocess.DEVNULL, stderr=log)
    try:
        deadline = time.monotonic() + 30
        found = None
        while found is None and time.monotonic() < deadline:
            time.sleep(0.2)
            found = re.search(r"DevTools listening on (ws://\S+)", (tmp_path / "chromium.log").read_text())
        assert found is not None, (tmp_path / "chromium.log").read_text()[-2000:]
        with connect(found[1], max_size=2 ** 28, open_timeout=30) as ws:
            _look_at_the_viewer(_DevTools(ws), url, base, tmp_path)
    finally:
        browser.terminate()
        browser.wait(20)
        log.close()


def _look_at_the_viewer(devtools: _DevTools, url: str, base: str, tmp_path) -> None:
    """Open the viewer page; its handle must hold our recording, and the page must be drawn."""
    target = devtools.call("Target.createTarget", url=url)["targetId"]
    session = devtools.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
    # The viewer's handle (window._handle, rerun's WebHandle) saves the recording it has loaded.
    state = ("(() => { try { const h = window._handle; if (!h) return 'no viewer yet';"
             " if (h.has_panicked()) return 'panicked: ' + h.panic_message();"
             " const b = h.save_recording(); let s = '';"
             " for (let i = 0; i < b.length; i += 8192) s += String.fromCharCode(...b.subarray(i, i + 8192));"
             " return btoa(s); } catch (e) { return String(e); } })()")
    saved, entities, deadline = "", set(), time.monotonic() + LOAD_S
    wanted = {f"{base}/world/robot/trunk", f"{base}/world/robot/FR_calf/spheres", f"{base}/world/contact_force/RL",
              f"{base}/world/floor", f"{base}/cpg/phase_rad/FL"}
    while time.monotonic() < deadline and not wanted <= entities:
        saved = devtools.call("Runtime.evaluate", session, expression=state, returnByValue=True)["result"]["value"]
        if saved.startswith("panicked"):
            break
        if len(saved) > 1000:  # a recording: read it back as rerun does
            (tmp_path / "held.rrd").write_bytes(base64.b64decode(saved))
            entities = {chunk.entity_path for chunk in RrdReader(tmp_path / "held.rrd").stream()}
        time.sleep(1.0)
    assert wanted <= entities, (saved[:300], sorted(entities)[:20])
    time.sleep(2.0)  # let it draw
    shot = base64.b64decode(devtools.call("Page.captureScreenshot", session, format="png")["data"])
    (tmp_path / "viewer.png").write_bytes(shot)
    pixels = iio.imread(shot).astype(float)
    assert pixels.shape[1] == 1280 and pixels.shape[0] > 600 and pixels[..., :3].std() > 20  # drawn, not blank
    assert len(np.unique(pixels[::8, ::8, :3].reshape(-1, 3), axis=0)) > 200
