"""Benchmark: the documented real-time rehearsal against the loopback simulated Go1 (127.0.0.1 only), end to end.

Runs each documented ``cpgjax deploy --robot sim`` example (docs/hardware.md) with its default pacing (real time)
``--repeats`` times, one after the other, each as its own process into a fresh folder, and counts the runs that
ended with a safety trip (exit status 2) and their reasons; a run that did not end cleanly keeps its folder (its
per-tick log, ``ticks.arrows``, shows what happened). Target (issue 13): no stale-state trip in at least 9
of 10 runs of each example. The machine's other load changes the result: the load average is printed per run.

    python benchmarks/rehearsal.py                      # 10 runs of each example
    python benchmarks/rehearsal.py --repeats 3          # fewer
    python benchmarks/rehearsal.py --examples replay    # one example

The last line of the output is one JSON object with the counts.
"""

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time

from cpgjax import provenance

EXAMPLES = {  # name: the command's arguments after `cpgjax` (docs/hardware.md); {out} is a fresh folder
    "replay": ["deploy", "--robot", "sim", "--duration-s", "10", "--log-dir", "{out}/run"],
    "optimize": ["deploy", "--robot", "sim", "--optimize", "--trials", "3", "--log-dir", "{out}/run"],
    "calibrate": ["deploy", "calibrate", "--robot", "sim", "--out", "{out}/calibration.json"],
}
_TRIP = re.compile(r"(?:safety trip|stopped): ([^;\n]*)")


def run_once(name: str, timeout_s: float) -> dict:
    """One run of an example in a fresh folder, kept when the run did not end cleanly (its per-tick log shows why):
    exit status, wall time, the trip reason (None: clean end), load average, the folder kept."""
    out = tempfile.mkdtemp(prefix=f"rehearsal-{name}-")
    argv = [sys.executable, "-m", "cpgjax.cli", *(a.format(out=out) for a in EXAMPLES[name])]
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(
            argv, capture_output=True, text=True, timeout=timeout_s, env=dict(os.environ, JAX_PLATFORMS="cpu")
        )
        code, text = proc.returncode, proc.stdout + proc.stderr
    except subprocess.TimeoutExpired as e:
        code, text = -1, f"timed out after {timeout_s} s\n{e.stderr or ''}"
    wall_s = time.perf_counter() - t0
    trips = _TRIP.findall(text)
    reason = trips[-1].strip() if trips else (None if code == 0 else text.strip().splitlines()[-1])
    if code == 0:
        shutil.rmtree(out)
    return {
        "example": name,
        "exit": code,
        "wall_s": round(wall_s, 1),
        "trip": reason,
        "stale": reason is not None and "stale state" in reason,
        "load_avg_1min": round(load, 2),
        "kept": None if code == 0 else out,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=10, help="runs of each example (default 10)")
    parser.add_argument("--examples", default=",".join(EXAMPLES), help=f"comma list of {', '.join(EXAMPLES)}")
    parser.add_argument("--timeout-s", type=float, default=600.0, help="give up on a run after this long")
    args = parser.parse_args()
    names = args.examples.split(",")
    if not set(names) <= set(EXAMPLES) or args.repeats < 1:
        parser.error(f"--examples {args.examples!r}: each of {', '.join(EXAMPLES)}; --repeats ≥ 1")
    runs = []
    for i in range(args.repeats):
        for name in names:
            r = run_once(name, args.timeout_s)
            runs.append(r)
            kept = f" (kept {r['kept']})" if r["kept"] else ""
            print(
                f"{name:9s} run {i + 1}/{args.repeats}: exit {r['exit']}, {r['wall_s']:5.1f} s, load "
                f"{r['load_avg_1min']:.2f}: {r['trip'] or 'clean end'}{kept}",
                flush=True,
            )
    figures = {"benchmark": "rehearsal", "machine": provenance.machine(), "repeats": args.repeats}
    print("\n| example | runs | clean | tripped | stale-state trips | load avg (min–max) |\n|---|---|---|---|---|---|")
    for name in names:
        mine = [r for r in runs if r["example"] == name]
        clean = sum(r["exit"] == 0 for r in mine)
        stale = sum(r["stale"] for r in mine)
        loads = [r["load_avg_1min"] for r in mine]
        print(f"| {name} | {len(mine)} | {clean} | {len(mine) - clean} | {stale} | {min(loads):.2f}–{max(loads):.2f} |")
        figures.update(
            {
                f"{name}_runs": len(mine),
                f"{name}_clean": clean,
                f"{name}_stale_trips": stale,
                f"{name}_reasons": sorted({r["trip"] for r in mine if r["trip"]}),
            }
        )
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
