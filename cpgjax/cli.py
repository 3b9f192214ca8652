"""The ``cpgjax`` command line."""

from __future__ import annotations

import argparse
import sys

from cpgjax import cpg
from cpgjax.robot import cpu_dispatch
from cpgjax.sim import walk
from cpgjax.study import spec as study_spec


def _floats(text: str) -> tuple[float, ...]:
    return tuple(float(v) for v in text.split(","))


def _walk(args) -> None:
    rows, timing = walk.walk(controllers=args.controllers.split(","), friction=args.friction,
                             slope_deg=args.slope, payload_kg=args.payload, num_trials=args.trials,
                             target_velocity_mps=args.target)
    print(walk.markdown_table(rows))
    print(timing)


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


def _study(args) -> int:
    cpu_dispatch.request_inline()  # the native backend's per-tick controller call
    from cpgjax import ablation
    from cpgjax.study import registry as studies
    if args.distributed:
        ablation.initialize_distributed()
    try:
        text, out = studies.run(args.name, seeds=args.seeds, trials=args.trials, quick=args.quick, out=args.out,
                                resume=args.resume, backend=args.backend, progress=_progress_printer())
    except study_spec.StudyError as err:
        print(f"cpgjax study: {err}", file=sys.stderr)
        return 2
    print(text)
    print(f"outputs in {out}/")
    return 0


def _optimize(args) -> int:
    cpu_dispatch.request_inline()  # the native backend's per-tick controller call
    import pathlib

    from cpgjax import ablation
    from cpgjax.trial import params as param_space
    from cpgjax.study import files as study_io
    spec = study_spec.StudySpec("optimize", num_trials=args.trials, controllers=(args.controller,), seeds=(args.seed,),
                              friction=(args.friction,), slope_deg=(args.slope,), payload_kg=(args.payload,),
                              target_velocity_mps=(args.target,))
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
    print("| trial | J | v_x [m/s] | CoT | c_load [N] | c_slope [rad] | β | fell |\n|---|---|---|---|---|---|---|---|")
    for t in range(tr.objective.shape[0]):
        print(f"| {t} | {tr.objective[t, 0]:.3f} | {tr.velocity_xy_mps[t, 0, 0]:.3f} | {tr.cot[t, 0]:.3f} | "
              f"{tr.context[t, 0, 0]:.1f} | {tr.context[t, 0, 1]:.3f} | {tr.beta[t, 0]:.3g} | {int(tr.fell[t, 0])} |")
    best = int(tr.objective[:, 0].argmax())
    print(f"best J {tr.objective[best, 0]:.3f} at trial {best}: {param_space.as_dict(tr.params[best, 0])}")
    study_io.write_trials(result, out / "trials.parquet")
    study_io.write_recording(result, out / "recording.rrd")
    study_io.write_metadata(result, out / "metadata.json")
    print(f"outputs in {out}/")
    return 0


def _show(args) -> int:
    import json
    import pathlib
    import shutil
    import subprocess

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


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] == "deploy":  # its own parser: cpgjax deploy --help
        from cpgjax.robot import deploy
        return deploy.main(argv[1:])
    parser = argparse.ArgumentParser(prog="cpgjax", description="cpgjax: online-optimized CPG control for the Go1. "
                                     "Subcommands: walk, study, optimize, show, deploy (see `cpgjax deploy --help`).")
    sub = parser.add_subparsers(dest="command", required=True)
    w = sub.add_parser("walk", help="walk with fixed parameters and print the trial figures")
    w.add_argument("--controllers", default=",".join(cpg.CONTROLLERS), help=f"comma list of {cpg.CONTROLLERS}")
    w.add_argument("--friction", type=_floats, default=(0.6,), help="comma list, e.g. 0.3,0.6,0.9")
    w.add_argument("--slope", type=_floats, default=(0.0,), help="comma list of slopes [deg], uphill along +x")
    w.add_argument("--payload", type=_floats, default=(0.0,), help="comma list of payloads [kg]")
    w.add_argument("--trials", type=int, default=2, help="back-to-back trials of 1.5 s + 3 s")
    w.add_argument("--target", type=float, default=0.5, help="target velocity v_x* [m/s] for J")
    w.set_defaults(func=_walk)

    from cpgjax.sim import backends
    from cpgjax.study import registry as studies
    s = sub.add_parser("study", help="run a paper study (batched online optimization) and write results/<study>/")
    s.add_argument("name", choices=sorted(studies.STUDIES), help="; ".join(
        f"{k}: {v.description}" for k, v in studies.STUDIES.items()))
    s.add_argument("--seeds", type=int, default=None, help=f"seeds per group (default {studies.DEFAULT_SEEDS}, "
                   f"--quick {studies.QUICK_SEEDS})")
    s.add_argument("--trials", type=int, default=None, help="trials per run (condition changes scale with it)")
    s.add_argument("--quick", action="store_true", help="fewer seeds and trials")
    s.add_argument("--out", default=None, help="output folder (default results/<study>)")
    s.add_argument("--resume", action="store_true", help="continue from the folder's checkpoint")
    s.add_argument("--distributed", action="store_true", help="multi-host: jax.distributed.initialize() first")
    backends.add_backend_argument(s)
    s.set_defaults(func=_study)

    o = sub.add_parser("optimize", help="one online optimization (Algorithm 1) with a controller, scenario, target")
    o.add_argument("--controller", choices=cpg.CONTROLLERS, default="vmc_tegotae")
    o.add_argument("--friction", type=float, default=0.6)
    o.add_argument("--slope", type=float, default=0.0, help="slope [deg], uphill")
    o.add_argument("--payload", type=float, default=0.0, help="payload [kg]")
    o.add_argument("--target", type=float, default=0.5, help="target velocity v_x* [m/s]")
    o.add_argument("--trials", type=int, default=40)
    o.add_argument("--seed", type=int, default=0)
    o.add_argument("--out", default="results/optimize")
    o.add_argument("--resume", action="store_true")
    backends.add_backend_argument(o)
    o.set_defaults(func=_optimize)

    v = sub.add_parser("show", help="print a results folder's tables and open its rerun recording")
    v.add_argument("results", help="e.g. results/controller_ablation")
    v.add_argument("--no-viewer", action="store_true", help="do not open the recording")
    v.set_defaults(func=_show)

    args = parser.parse_args(argv)
    return args.func(args) or 0


if __name__ == "__main__":
    sys.exit(main())
