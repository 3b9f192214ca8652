"""The idle web viewer's CPU: what `cpgjax show FOLDER --web` costs while nobody looks at it.

Starts the command on a results folder's recording (by default a fresh folder holding the recording of a standing
robot, 2 s at 1 kHz), waits until it prints its address and `--settle-s` more, then reads the CPU time (user + system,
/proc/<pid>/stat) of the command's process and of every process it started, over `--seconds`, and prints one JSON
line with the share of one core each used.

    JAX_PLATFORMS=cpu python benchmarks/viewer_idle.py --seconds 30
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from cpgjax import provenance  # noqa: E402
from cpgjax.go1 import model as go1_model  # noqa: E402
from cpgjax.studies import launch as study_launch  # noqa: E402
from cpgjax.trial import protocol  # noqa: E402

STANDING_TICKS = 2000


def standing_recording(folder: pathlib.Path) -> None:
    """``folder/recording.rrd``: one rollout of the robot standing still (no simulation: its standing pose held)."""
    import rerun as rr

    from cpgjax.study import scene
    from cpgjax.trial.condition import Condition

    qpos = np.tile(go1_model.standing_qpos(), (STANDING_TICKS, 1))
    zeros = {
        name: np.zeros((STANDING_TICKS, *shape))
        for name, shape in (
            ("qvel", (qpos.shape[1] - 1,)),
            ("torque_nm", (12,)),
            ("foot_force_n", (4,)),
            ("foot_pos_m", (4, 3)),
            ("amplitude", (4,)),
            ("phase_rad", (4,)),
            ("foot_target_m", (4, 3)),
            ("rpy_rad", (3,)),
        )
    }
    rollout = scene.Rollout(
        log=protocol.StepLog(qpos=qpos, **zeros),
        group="standing",
        controller="vmc_tegotae",
        seed=0,
        condition=Condition(friction=1.0),
    )
    rec = rr.RecordingStream("cpgjax_viewer_idle")
    rec.save(str(folder / "recording.rrd"))
    scene.log_rollout(rec, rollout)
    rec.flush()
    rec.disconnect()


def tree(pid: int) -> set[int]:
    """The process and every process below it."""
    below = {pid}
    grew = True
    while grew:
        grew = False
        for entry in os.listdir("/proc"):
            if entry.isdigit() and int(entry) not in below:
                try:
                    ppid = int(pathlib.Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()[1])
                except (OSError, IndexError, ValueError):
                    continue
                if ppid in below:
                    below.add(int(entry))
                    grew = True
    return below


def cpu_s(pids: set[int]) -> dict[int, tuple[str, float]]:
    """Each process's name and CPU time so far (utime + stime) [s]."""
    tick_s = 1.0 / os.sysconf("SC_CLK_TCK")
    times = {}
    for pid in pids:
        try:
            stat = pathlib.Path(f"/proc/{pid}/stat").read_text()
        except OSError:
            continue
        fields = stat.rsplit(")", 1)[1].split()
        times[pid] = (stat[stat.index("(") + 1 : stat.rindex(")")], (int(fields[11]) + int(fields[12])) * tick_s)
    return times


def measure(folder: pathlib.Path, seconds: float, settle_s: float) -> dict:
    port = study_launch.free_port()
    env = {**os.environ, "PYTHONPATH": str(ROOT), "JAX_PLATFORMS": "cpu"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "cpgjax.cli", "show", str(folder), "--web", "--port", str(port)],
        env=env,
        cwd=ROOT,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    try:
        printed = ""
        while "Ctrl-C stops it" not in printed:
            line = proc.stdout.readline()
            if not line:
                raise RuntimeError(f"`cpgjax show --web` ended: {printed[-800:]}")
            printed += line
        time.sleep(settle_s)
        pids = tree(proc.pid)
        before, t0 = cpu_s(pids), time.monotonic()
        time.sleep(seconds)
        after, wall_s = cpu_s(pids), time.monotonic() - t0
        shares = {
            f"{name} ({pid})": round(100 * (t - before[pid][1]) / wall_s, 2)
            for pid, (name, t) in after.items()
            if pid in before
        }
        return {
            "processes": shares,
            "total_percent_of_a_core": round(sum(shares.values()), 2),
            "wall_s": round(wall_s, 1),
        }
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--folder",
        type=pathlib.Path,
        help="a results folder with recording.rrd (default: a standing robot's recording in a temporary folder)",
    )
    parser.add_argument("--seconds", type=float, default=30.0, help="how long the CPU time is measured")
    parser.add_argument("--settle-s", type=float, default=5.0, help="the wait after the address is printed")
    args = parser.parse_args()
    work = pathlib.Path(tempfile.mkdtemp(prefix="cpgjax-viewer-idle-"))
    try:
        folder = args.folder
        if folder is None:
            folder = work
            standing_recording(folder)
        figures = measure(folder, args.seconds, args.settle_s)
        print(
            json.dumps(
                {
                    "benchmark": "viewer_idle",
                    "machine": provenance.machine(),
                    "load_avg": os.getloadavg(),
                    "commit": provenance.git_commit(),
                    "recording_bytes": (folder / "recording.rrd").stat().st_size,
                    "seconds": args.seconds,
                    **figures,
                }
            )
        )
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
