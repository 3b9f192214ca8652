"""Ctrl-C at random moments: how often a `cpgjax optimize` stops cleanly.

Each repeat starts `cpgjax optimize --trials N --backend native` in a fresh folder and sends SIGINT at a uniformly
random moment after the first checkpoint, within 90 % of the time the remaining trials took in one
uninterrupted run measured first. A clean stop is exit status 130, a checkpoint that reads back, no traceback, and
either a `resume with:` line or, for a Ctrl-C after the last trial, every output written. A run that ended before
its signal was due, and one whose signal came as the finished process exited (exit 0, every output written: the
teardown ignores Ctrl-C), are counted apart. Prints one JSON line with the counts.

    JAX_PLATFORMS=cpu python benchmarks/ctrl_c.py --repeats 20
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import random
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from cpgjax import provenance  # noqa: E402
from cpgjax.study import files as study_io  # noqa: E402
from cpgjax.study.spec import StudyError  # noqa: E402

# Python keeps SIGINT ignored in a child of a shell that ignores it (a background job): give the command Python's own
# Ctrl-C handler, as a terminal would.
START = (
    "import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
    "sys.argv = ['cpgjax', *sys.argv[1:]]; runpy.run_module('cpgjax.cli', run_name='__main__')"
)


def start(out: pathlib.Path, trials: int) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "JAX_PLATFORMS": "cpu"}
    return subprocess.Popen(
        [sys.executable, "-c", START, "optimize", "--trials", str(trials), "--out", str(out), "--backend", "native"],
        env=env,
        cwd=ROOT,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )


def first_checkpoint_s(proc: subprocess.Popen, out: pathlib.Path, timeout_s: float = 600.0) -> float:
    t0 = time.monotonic()
    while proc.poll() is None and not (out / study_io.CHECKPOINT).exists():
        if time.monotonic() - t0 > timeout_s:
            raise RuntimeError("no checkpoint")
        time.sleep(0.02)
    return time.monotonic() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--trials", type=int, default=6)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rng = random.Random(args.seed)
    work = pathlib.Path(tempfile.mkdtemp(prefix="cpgjax-ctrl-c-"))
    try:
        probe = start(work / "probe", args.trials)
        t0 = time.monotonic()
        first = first_checkpoint_s(probe, work / "probe")
        probe.communicate(timeout=900)
        total = time.monotonic() - t0
        counts = {
            "stopped_resumable": 0,
            "stopped_outputs_written": 0,
            "exited_0_outputs_written": 0,
            "ended_before_the_signal": 0,
            "failed": 0,
            "lost_interrupt_messages": 0,
        }
        failures = []
        for k in range(args.repeats):
            out = work / f"run{k}"
            proc = start(out, args.trials)
            first_checkpoint_s(proc, out)
            delay = rng.uniform(0.0, 0.9 * (total - first))  # within the trials after the first (the probe's)
            time.sleep(delay)
            if proc.poll() is not None:
                counts["ended_before_the_signal"] += 1
                continue
            proc.send_signal(signal.SIGINT)
            _, err = proc.communicate(timeout=300)
            try:
                saved = study_io.checkpoint_meta(out)
            except StudyError:
                saved = None
            counts["lost_interrupt_messages"] += "Exception ignored" in err  # Python's own line, then stopped
            # Python's report of the KeyboardInterrupt it ignored in a callback is not the command's traceback
            traceback = "Traceback" in re.sub(r"Exception ignored in: .*?\nKeyboardInterrupt: ?\n", "", err, flags=re.S)
            if proc.returncode == 130 and saved and "resume with:" in err and not traceback:
                counts["stopped_resumable"] += 1
            elif proc.returncode == 130 and saved and (out / "recording.rrd").exists() and not traceback:
                counts["stopped_outputs_written"] += 1
            elif proc.returncode == 0 and (out / "recording.rrd").exists() and not traceback:
                counts["exited_0_outputs_written"] += 1  # the signal came as the finished process exited
            else:
                counts["failed"] += 1
                failures.append({"run": k, "status": proc.returncode, "stderr": err[-600:]})
        print(
            json.dumps(
                {
                    "benchmark": "ctrl_c",
                    "machine": provenance.machine(),
                    "load_avg": os.getloadavg(),
                    "repeats": args.repeats,
                    "trials": args.trials,
                    "first_checkpoint_s": round(first, 1),
                    "run_s": round(total, 1),
                    **counts,
                    "failures": failures,
                }
            )
        )
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
