"""The ``cpgjax`` command line: one argparse tree builds every command (walk, study, optimize, show, demo, deploy and
deploy calibrate); each command's function takes the parsed options."""

from __future__ import annotations

import argparse
import functools
import json
import os
import pathlib
import shutil
import subprocess
import sys

from cpgjax import ablation, cpg
from cpgjax.go1 import physics as physics_profiles
from cpgjax.robot import calibrate, cpu_dispatch, deploy
from cpgjax.robot import transport as go1_transport
from cpgjax.sim import backends, walk
from cpgjax.study import files as study_io
from cpgjax.study import launch as study_launch
from cpgjax.study import registry as studies
from cpgjax.study import spec as study_spec
from cpgjax.study import transfer
from cpgjax.trial import params as param_space

DEMO_OUT = pathlib.Path("results/demo_controller_ablation")


def _floats(text: str) -> tuple[float, ...]:
    return tuple(float(v) for v in text.split(","))


# ----------------------------------------------------------------------------------------------- commands

def _walk(args) -> int:
    rows, timing = walk.walk(controllers=args.controllers.split(","), friction=args.friction,
                             slope_deg=args.slope, payload_kg=args.payload, num_trials=args.trials,
                             target_velocity_mps=args.target, backend=args.backend, physics=args.physics)
    print(walk.markdown_table(rows))
    print(timing)
    return 0


def _progress_printer(stream=None):
    """The live progress display: trial, best J per group, env-steps/s, ETA (one rewritten line on a terminal)."""
    stream = stream or sys.stderr
    tty = stream.isatty()

    def show(p) -> None:
        best = ", ".join(f"{k} {v:.3f}" for k, v in p.best_by_group.items())
        line = (f"trial {p.trial}/{p.num_trials} | best J: {best} | {p.env_steps_per_s:,.0f} env-steps/s | "
                f"ETA {p.eta_s / 60:.1f} min")
        stream.write(("\r\033[K" + line + ("\n" if p.trial == p.num_trials else "")) if tty else line + "\n")
        stream.flush()
    return show


def _run_study(name: str, **options) -> int:
    """``studies.run`` with the progress display; prints its table and output folder, or its StudyError (then 2)."""
    try:
        run = transfer.run if name == transfer.NAME else functools.partial(studies.run, name)
        text, out = run(progress=_progress_printer(), **options)
    except study_spec.StudyError as err:
        print(f"cpgjax study: {err}", file=sys.stderr)
        return 2
    print(text)
    print(f"outputs in {out}/")
    return 0


def _without_processes(argv: list[str]) -> list[str]:
    """``argv`` without ``--processes N`` (or ``--processes=N``, or an abbreviation of it)."""
    out, skip = [], False
    for token in argv:
        head = token.split("=", 1)[0]
        if skip:
            skip = False
        elif len(head) >= 4 and "--processes".startswith(head):
            skip = "=" not in token
        else:
            out.append(token)
    return out


def _study(args) -> int:
    if args.processes is not None or args.distributed:
        problem = ("--processes and --distributed exclude each other (--processes starts --distributed processes)"
                   if args.processes is not None and args.distributed else
                   f"--processes {args.processes}: need at least 1" if args.processes is not None and args.processes < 1
                   else f"{transfer.NAME} runs its arms one after another in one process: drop --processes / "
                   "--distributed" if args.name == transfer.NAME else None)
        if problem:
            print(f"cpgjax study: {problem}", file=sys.stderr)
            return 2
    if args.processes is not None and args.processes > 1:
        command = [sys.executable, "-m", "cpgjax.cli", *_without_processes(args.argv), "--distributed"]
        outcome = study_launch.run(command, args.processes)
        if outcome.returncode:
            print(f"cpgjax study: {outcome.message}; `--resume` continues from the last checkpoint", file=sys.stderr)
        return outcome.returncode
    if args.distributed:
        ablation.initialize_distributed()
    try:
        return _run_study(args.name, seeds=args.seeds, trials=args.trials, quick=args.quick, out=args.out,
                          resume=args.resume, backend=args.backend, physics=args.physics)
    except ablation.ProcessLost as err:
        print(f"cpgjax study: {err}", file=sys.stderr, flush=True)
        sys.stdout.flush()
        os._exit(3)  # not through jax.distributed's shutdown barrier, which would wait for the lost process


def _demo(args) -> int:
    """``make demo``: the paper's controller ablation — online optimization of the four CPG controllers.

    Runs the ``--quick`` variant (4 controllers × 2 seeds × 12 trials of 1.5 s + 3 s: 41 s on the shared 2-core
    development machine) because the full study (5 seeds × 40 trials, ``cpgjax study controller_ablation``) took 3.7
    to 7.7 minutes there depending on the other jobs' load (docs/REPRODUCTION.md). Prints its table beside the
    paper's; outputs go to ``results/demo_controller_ablation/``, computed afresh every time.
    """
    print("cpgjax demo: online optimization (contextual GP-UCB, Algorithm 1) of the four CPG controllers at "
          "v* = 0.5 m/s, all runs batched in lockstep on the CPU (quick variant: 2 seeds × 12 trials; the first "
          "trials compile).", flush=True)
    (DEMO_OUT / study_io.CHECKPOINT).unlink(missing_ok=True)
    return _run_study("controller_ablation", quick=True, out=DEMO_OUT)


def _trials_table(trials) -> str:
    """Markdown table of one optimization's trials (instance 0)."""
    lines = ["| trial | J | v_x [m/s] | CoT | c_load [N] | c_slope [rad] | β | fell |", "|---" * 8 + "|"]
    for t in range(trials.objective.shape[0]):
        lines.append(f"| {t} | {trials.objective[t, 0]:.3f} | {trials.velocity_xy_mps[t, 0, 0]:.3f} | "
                     f"{trials.cot[t, 0]:.3f} | {trials.context[t, 0, 0]:.1f} | {trials.context[t, 0, 1]:.3f} | "
                     f"{trials.beta[t, 0]:.3g} | {int(trials.fell[t, 0])} |")
    return "\n".join(lines)


def _optimize(args) -> int:
    spec = study_spec.StudySpec("optimize", num_trials=args.trials, controllers=(args.controller,), seeds=(args.seed,),
                                friction=(args.friction,), slope_deg=(args.slope,), payload_kg=(args.payload,),
                                target_velocity_mps=(args.target,), physics=(args.physics,))
    out = pathlib.Path(args.out)
    try:
        if not args.resume and (out / study_io.CHECKPOINT).exists():
            raise study_spec.StudyError(f"{out} already holds a checkpoint: pass --resume, or another --out")
        engine = ablation.Engine(spec, backend=args.backend)
        result = engine.run(out, resume=args.resume, progress=_progress_printer())
    except study_spec.StudyError as err:
        print(f"cpgjax optimize: {err}", file=sys.stderr)
        return 2
    tr = result.trials
    print(_trials_table(tr))
    best = int(tr.objective[:, 0].argmax())
    print(f"best J {tr.objective[best, 0]:.3f} at trial {best}: {param_space.as_dict(tr.params[best, 0])}")
    study_io.write_trials(result, out / "trials.parquet")
    study_io.write_recording(result, out / "recording.rrd")
    study_io.write_metadata(result, out / "metadata.json")
    print(f"outputs in {out}/")
    return 0


def _show(args) -> int:
    out = pathlib.Path(args.results)
    if not out.is_dir():
        print(f"cpgjax show: {out} is not a folder", file=sys.stderr)
        return 2
    table = out / "table.md"
    print(table.read_text() if table.exists() else f"(no table.md in {out})")
    meta = out / "metadata.json"
    if meta.exists():
        m = json.loads(meta.read_text())
        print(f"{m['study']}: {m['instances']} instances × {m['trials']} trials on {m['backend']}, wall "
              f"{m['wall_s']} s, {m['env_steps_per_s']} env-steps/s, real-time factor {m['real_time_factor']}×")
    print("trial data: pyarrow.parquet.read_table / pandas.read_parquet / polars.read_parquet(" +
          repr(str(out / "trials.parquet")) + ")")
    recording = out / "recording.rrd"
    if recording.exists() and not args.no_viewer:
        beside = pathlib.Path(sys.executable).parent / "rerun"  # the venv's viewer, also when not activated
        viewer = str(beside) if beside.exists() else shutil.which("rerun")
        if viewer is None:
            print(f"recording: {recording} (install the rerun viewer to open it: `rerun {recording}`)")
        else:
            subprocess.Popen([viewer, str(recording)])
            print(f"opened {recording} in the rerun viewer")
    return 0


def _deploy(parser: argparse.ArgumentParser, args) -> int:
    """``cpgjax deploy`` after the checks that span options (``parser.error`` exits with 2)."""
    if args.robot is None:
        parser.error("the following arguments are required: --robot")
    if args.robot == "go1" and args.calibration is None:
        parser.error("--robot go1 needs --calibration FILE (run `cpgjax deploy calibrate` first, see docs/hardware.md)")
    return deploy.run(args)


# ----------------------------------------------------------------------------------------------- shared options

def _add_output_args(p: argparse.ArgumentParser, default: str | None, shown: str | None = None) -> None:
    """``--out`` (the folder a study or an optimization writes, with its checkpoint) and ``--resume``."""
    p.add_argument("--out", default=default, help=f"output folder (default {shown or default})")
    p.add_argument("--resume", action="store_true", help="continue from the folder's checkpoint")


def _physics_names(text: str) -> tuple[str, ...]:
    names = tuple(text.split(","))
    for name in names:
        if name not in physics_profiles.PROFILES:
            raise argparse.ArgumentTypeError(f"unknown physics profile {name!r}; allowed: "
                                             f"{', '.join(physics_profiles.PROFILES)}")
    return names


def _add_physics_arg(p: argparse.ArgumentParser, default: str | None, many: bool = False) -> None:
    """``--physics``: the physics profile(s) of the simulated Go1 (docs/physics.md)."""
    allowed = ", ".join(physics_profiles.PROFILES)
    if many:
        p.add_argument("--physics", type=_physics_names, default=(default,),
                       help=f"comma list of physics profiles ({allowed}; default {default})")
    else:
        shown = default or "the study's own"
        p.add_argument("--physics", choices=tuple(physics_profiles.PROFILES), default=default,
                       help=f"physics profile (default {shown})")


def _add_robot_args(p: argparse.ArgumentParser, robot_required: bool = True) -> None:
    """The options that choose and reach the robot (``cpgjax deploy`` and ``cpgjax deploy calibrate``)."""
    p.add_argument("--robot", choices=("sim", "go1"), required=robot_required,
                   help="sim: start the simulated Go1 on 127.0.0.1; go1: the robot (low-level mode, EDU)")
    p.add_argument("--transport", choices=("udp", "sdk"), help="default: sdk for go1, udp for sim")
    p.add_argument("--robot-ip", default=go1_transport.GO1_ROBOT_IP, help="go1 only")
    p.add_argument("--robot-port", type=int, default=go1_transport.GO1_ROBOT_PORT, help="go1 only")
    p.add_argument("--local-port", type=int, default=go1_transport.GO1_LOCAL_PORT, help="go1 only")
    p.add_argument("--power-level", type=int, default=9, help="power protection level 1…10 (100 W each)")
    p.add_argument("--sim-pacing", choices=("realtime", "lockstep"), default="realtime",
                   help="lockstep: one physics step per command, the loop waits for each answer (not real time)")
    p.add_argument("--payload-kg", type=float, default=0.0,
                   help="payload carried [kg] (counts in CoT; sim: simulated)")
    p.add_argument("--friction", type=float, default=0.6, help="sim only")
    p.add_argument("--slope-deg", type=float, default=0.0, help="sim only: slope [deg]")
    p.add_argument("--physics", choices=tuple(physics_profiles.PROFILES), default=physics_profiles.ROBOT_PROFILE,
                   help="sim only: the simulated Go1's physics profile (docs/physics.md)")
    p.add_argument("--no-realtime", action="store_true", help="do not ask for SCHED_FIFO")
    p.add_argument("--cpu", type=int, help="pin the loop to this CPU (sim: the simulated Go1 to the others)")
    p.add_argument("--busy-wait", action="store_true",
                   help="spin through each period instead of sleeping (with --cpu; with --no-realtime unless the "
                   "kernel's real-time throttling is off); fewer overruns on a VM (docs/hardware.md)")


# ----------------------------------------------------------------------------------------------- the parser

def _add_walk(sub) -> None:
    w = sub.add_parser("walk", help="walk with fixed parameters and print the trial figures")
    w.add_argument("--controllers", default=",".join(cpg.CONTROLLERS), help=f"comma list of {cpg.CONTROLLERS}")
    w.add_argument("--friction", type=_floats, default=(0.6,), help="comma list, e.g. 0.3,0.6,0.9")
    w.add_argument("--slope", type=_floats, default=(0.0,), help="comma list of slopes [deg], uphill along +x")
    w.add_argument("--payload", type=_floats, default=(0.0,), help="comma list of payloads [kg]")
    w.add_argument("--trials", type=int, default=2, help="back-to-back trials of 1.5 s + 3 s")
    w.add_argument("--target", type=float, default=0.5, help="target velocity v_x* [m/s] for J")
    _add_physics_arg(w, physics_profiles.PAPER_STUDIES_PROFILE, many=True)
    backends.add_backend_argument(w)
    w.set_defaults(func=_walk)


def _add_study(sub) -> None:
    s = sub.add_parser("study", help="run a paper study (batched online optimization) and write results/<study>/")
    descriptions = {k: v.description for k, v in studies.STUDIES.items()}
    descriptions[transfer.NAME] = transfer.DESCRIPTION
    s.add_argument("name", choices=sorted(descriptions), help="; ".join(f"{k}: {v}" for k, v in descriptions.items()))
    s.add_argument("--seeds", type=int, default=None, help=f"seeds per group (default {studies.DEFAULT_SEEDS}, "
                   f"--quick {studies.QUICK_SEEDS})")
    s.add_argument("--trials", type=int, default=None, help="trials per run (condition changes scale with it)")
    s.add_argument("--quick", action="store_true", help="fewer seeds and trials")
    _add_output_args(s, None, "results/<study>")
    s.add_argument("--distributed", action="store_true", help="one of several cooperating processes: "
                   "jax.distributed.initialize() first (coordinator, count and rank from the environment or Slurm; "
                   "docs/scaling.md)")
    s.add_argument("--processes", type=int, default=None, help="run as N cooperating local processes (coordinator "
                   "on 127.0.0.1), e.g. to check a multi-process run before a cluster")
    _add_physics_arg(s, None)
    backends.add_backend_argument(s)
    s.set_defaults(func=_study)


def _add_optimize(sub) -> None:
    o = sub.add_parser("optimize", help="one online optimization (Algorithm 1) with a controller, scenario, target")
    o.add_argument("--controller", choices=cpg.CONTROLLERS, default="vmc_tegotae")
    o.add_argument("--friction", type=float, default=0.6)
    o.add_argument("--slope", type=float, default=0.0, help="slope [deg], uphill")
    o.add_argument("--payload", type=float, default=0.0, help="payload [kg]")
    o.add_argument("--target", type=float, default=0.5, help="target velocity v_x* [m/s]")
    o.add_argument("--trials", type=int, default=40)
    o.add_argument("--seed", type=int, default=0)
    _add_output_args(o, "results/optimize")
    _add_physics_arg(o, physics_profiles.PAPER_STUDIES_PROFILE)
    backends.add_backend_argument(o)
    o.set_defaults(func=_optimize)


def _add_show(sub) -> None:
    v = sub.add_parser("show", help="print a results folder's tables and open its rerun recording")
    v.add_argument("results", help="e.g. results/controller_ablation")
    v.add_argument("--no-viewer", action="store_true", help="do not open the recording")
    v.set_defaults(func=_show)


def _add_demo(sub) -> None:
    d = sub.add_parser("demo", help=f"`make demo`: the controller ablation's quick variant, afresh, into {DEMO_OUT}/")
    d.set_defaults(func=_demo)


def _add_deploy(sub) -> None:
    d = sub.add_parser("deploy", help="run the CPG at 1 kHz on a Go1 or the loopback simulated Go1 "
                       "(`cpgjax deploy calibrate`: the foot-force calibration)",
                       description="Run the CPG controller at 1 kHz on a Go1 or on the loopback simulated Go1; "
                       "replay parameters or optimize them online. `cpgjax deploy calibrate --help`: the foot-force "
                       "calibration.")
    _add_robot_args(d, robot_required=False)  # _deploy requires it: argparse would ask for it before `calibrate` too
    what = d.add_mutually_exclusive_group()
    what.add_argument("--params", type=pathlib.Path, help="replay these parameters (JSON from save_params / "
                      "best_params)")
    what.add_argument("--optimize", action="store_true", help="online optimization (Algorithm 1)")
    d.add_argument("--trials", type=int, default=10, help="trials of online optimization")
    d.add_argument("--optimizer", choices=("bo", "random"), default="bo")
    d.add_argument("--controller", choices=cpg.CONTROLLERS, default="vmc_tegotae")
    d.add_argument("--target-velocity", type=float, default=0.5, help="v_x* [m/s] of the objective")
    d.add_argument("--duration-s", type=float, default=10.0, help="run time when replaying parameters [s]")
    d.add_argument("--transition-s", type=float, default=1.5, help="each trial's parameter transition [s]")
    d.add_argument("--steady-s", type=float, default=3.0, help="each trial's steady phase T [s]")
    d.add_argument("--log-dir", type=pathlib.Path, default=pathlib.Path("runs/deploy"))
    d.add_argument("--calibration", type=pathlib.Path, help="foot-force calibration JSON from `cpgjax deploy "
                   "calibrate` (required with --robot go1; sim: the simulated sensor's exact calibration by default)")
    d.add_argument("--seed", type=int, default=0)
    d.set_defaults(func=functools.partial(_deploy, d))

    c = d.add_subparsers(title="subcommands").add_parser(
        "calibrate", help="measure the foot-force sensors and save their calibration",
        description="Measure the Go1's foot-force sensors (feet in the air, then standing) and save their "
        "calibration to raw counts → N.")
    _add_robot_args(c)
    c.add_argument("--out", type=pathlib.Path, default=pathlib.Path("go1_calibration.json"),
                   help="calibration JSON to write")
    c.add_argument("--air-s", type=float, default=2.0, help="measuring time with the feet in the air [s]")
    c.add_argument("--stand-s", type=float, default=3.0, help="measuring time standing still [s]")
    c.add_argument("--settle-s", type=float, default=1.0, help="time holding the pose before each measurement [s]")
    c.add_argument("--mass-kg", type=float, help="the robot's total mass [kg] (default: cpgjax's Go1 model + payload)")
    c.add_argument("--lift-m", type=float, default=0.3, help="sim only: how high the simulated Go1 is hung up [m]")
    c.set_defaults(func=calibrate.run)


def build_parser() -> argparse.ArgumentParser:
    """The ``cpgjax`` parser: every command, each with its function as ``func``."""
    parser = argparse.ArgumentParser(prog="cpgjax", description="cpgjax: online-optimized CPG control for the Go1.")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in (_add_walk, _add_study, _add_optimize, _add_show, _add_demo, _add_deploy):
        add(sub)
    return parser


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_args(argv)
    args.argv = argv  # `study --processes N` starts the same command line N times
    # Before any JAX computation: the native backend's and the robot loop's per-tick controller calls run inline.
    cpu_dispatch.request_inline()
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
