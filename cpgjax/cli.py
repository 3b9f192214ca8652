"""The ``cpgjax`` command line: one argparse tree builds every command (walk, study, optimize, show, demo, deploy and
deploy calibrate); each command's function takes the parsed options."""

from __future__ import annotations

import argparse
import dataclasses
import functools
import ipaddress
import os
import pathlib
import shlex
import signal
import sys
import time

import numpy as np

import cpgjax
from cpgjax import compile_cache, cpg, show
from cpgjax.deployment import calibrate, deploy
from cpgjax.deployment.options import CalibrateOptions, DeployOptions, RobotOptions, flag
from cpgjax.go1 import physics as physics_profiles
from cpgjax.go1 import terrain as terrains
from cpgjax.robot import cpu_dispatch, foot_force
from cpgjax.robot import safety as go1_safety
from cpgjax.robot import transport as go1_transport
from cpgjax.sim import backends, walk
from cpgjax.studies import driver as study_driver
from cpgjax.studies import gaits as study_gaits
from cpgjax.studies import launch as study_launch
from cpgjax.studies import optimize as study_optimize
from cpgjax.studies import options as study_options
from cpgjax.studies import video as study_video
from cpgjax.studies import viewer as study_viewer
from cpgjax.study import files as study_io
from cpgjax.study import placement as study_placement
from cpgjax.study import spec as study_spec
from cpgjax.trial import limits, protocol, tuned
from cpgjax.trial import params as param_space
from cpgjax.trial.condition import Condition

DEMO_OUT = pathlib.Path("results/demo_controller_ablation")
DEPLOY_RUNS = pathlib.Path("runs/deploy")  # each robot run gets a fresh timestamped folder below it by default
INTERRUPTED = 130  # the exit status of a run stopped by Ctrl-C (128 + SIGINT)


# ----------------------------------------------------------------------------------------------- option types
# Each checks its value when the command line is parsed: a refused value stops the command before anything runs
# (argparse prints "argument --x: <why>" and exits with 2). The ranges live in cpgjax.trial.limits, the robot's in
# cpgjax.robot.safety and cpgjax.robot.foot_force.


def _argument_type(convert):
    """An argparse type from ``convert(text)``, which raises ValueError with the message to show."""

    @functools.wraps(convert)
    def parse(text: str):
        try:
            return convert(text)
        except ValueError as err:
            raise argparse.ArgumentTypeError(str(err)) from None

    return parse


def _number(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"{text!r} is not a number") from None


def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise ValueError(f"{text!r} is not an integer") from None


_whole = _argument_type(_integer)  # an integer; its range is the typed options' check (cpgjax.studies.options)


def _in(allowed: limits.Range):
    """A number in ``allowed``."""
    return _argument_type(lambda text: allowed.check(_number(text)))


def _list_in(allowed: limits.Range):
    """A comma list of numbers, each in ``allowed``."""
    return _argument_type(lambda text: tuple(allowed.check(_number(v)) for v in text.split(",")))


def _count(
    minimum: int = limits.MIN_TRIALS,
    reason: str = "",
    maximum: int = limits.MAX_TRIALS,
    maximum_reason: str = limits.MAX_TRIALS_REASON,
):
    """An integer in ``minimum`` … ``maximum`` (default: a number of trials)."""
    return _argument_type(
        lambda text: limits.check_count(_integer(text), None, minimum, reason, maximum, maximum_reason)
    )


def _integer_in(allowed: range, what: str):
    def convert(text: str) -> int:
        value = _integer(text)
        if value not in allowed:
            raise ValueError(f"{value} is outside the allowed range {allowed.start} … {allowed.stop - 1} ({what})")
        return value

    return _argument_type(convert)


_power_level = _integer_in(go1_safety.POWER_LEVELS, "the SDK's power protection trips above 100 W per level")
_port = _integer_in(range(1, 65536), "a UDP port")
_seed = _integer_in(range(2**32), "a seed is a 32-bit unsigned integer")
_params_file = _argument_type(tuned.load)
_calibration_file = _argument_type(foot_force.FootForceCalibration.load)


@_argument_type
def _output_path(text: str) -> pathlib.Path:
    """A path to write, named on the command line: not empty, and in a folder that exists (cpgjax creates the
    default folders' parents, never a parent the user named)."""
    if not text.strip():
        raise ValueError("an empty path: name a folder or file to write")
    path = pathlib.Path(text)
    if not path.parent.is_dir():
        raise ValueError(f"{text}: its folder {path.parent} does not exist (create it first, or write elsewhere)")
    return path


@_argument_type
def _ip_address(text: str) -> str:
    try:
        return str(ipaddress.ip_address(text))
    except ValueError:
        raise ValueError(f"{text!r} is not an IP address") from None


@_argument_type
def _cpu(text: str) -> int:
    value = _integer(text)
    if not 0 <= value < (os.cpu_count() or 1):
        raise ValueError(f"{value} is outside this machine's CPUs 0 … {(os.cpu_count() or 1) - 1}")
    return value


class _Given(argparse.Action):
    """Stores an option's value as argparse's default action does, and adds its name to ``args.given``: the options
    the command line gave, which a parameter file's tuned-for values do not replace (:func:`_tuned`)."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, values)
        namespace.given = {*getattr(namespace, "given", ()), self.dest}


class _Parser(argparse.ArgumentParser):
    """A parser whose errors are the one line ``cpgjax <command>: error: <why>`` (the usage is on ``--help``); every
    subcommand's parser is one too."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}\n")


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Every option's help ends with its default; an option whose default is None says it in its help text."""

    def _get_help_string(self, action):
        return action.help if action.default is None else super()._get_help_string(action)


# ----------------------------------------------------------------------------------------------- commands


def _notice(line: str) -> None:
    """A line for the person at the terminal (stderr: stdout holds a command's results)."""
    print(line, file=sys.stderr, flush=True)


def _tuned(args, many: bool = False) -> tuple[dict, str | None]:
    """With ``--params FILE``: the file's value of every option it records a tuned-for value of
    (:data:`tuned.TUNED_FOR`) and the command line did not give (``many``: as a one-value list, walk's grid), and
    the line that says what the run was tuned for and which given options override it; ``({}, None)`` without a
    file."""
    if args.params is None:
        return {}, None
    given = getattr(args, "given", set())
    values, overrides = {}, []
    for name, value in args.params.tuned_for.items():
        dest = {"controller": "controllers", "gait": "gaits"}.get(name, name) if many else name
        wanted = (value,) if many and name != "target_velocity_mps" else value
        if dest not in given:
            values[dest] = wanted
        elif getattr(args, dest) != wanted:
            overrides.append(f"{flag(dest)} {_shown(getattr(args, dest))} overrides it")
    recorded = (
        f"tuned for {tuned.describe(args.params.tuned_for)}"
        if args.params.tuned_for
        else "records nothing it was tuned for"
    )
    return values, f"cpgjax {args.command}: {args.params.path} {recorded}" + "".join(f"; {o}" for o in overrides)


def _shown(value) -> str:
    """An option's value as a command line writes it (a list comma-separated)."""
    if isinstance(value, tuple):
        return ",".join(map(_shown, value))
    return f"{value:g}" if isinstance(value, float) else str(value)


def _walk_video(args) -> int:
    """``cpgjax walk --video FILE``: the walk's one combination, after a settling trial, filmed for --video-s."""
    combos = [
        (name, len(v))
        for name, v in (
            ("--controllers", args.controllers),
            ("--gaits", args.gaits),
            ("--friction", args.friction),
            ("--slope-deg", args.slope_deg),
            ("--payload-kg", args.payload_kg),
            ("--physics", args.physics),
        )
        if len(v) != 1
    ]
    if combos:
        print(
            f"cpgjax walk: --video films one walk; {combos[0][0]} has {combos[0][1]} values (give one)", file=sys.stderr
        )
        return 2
    ground = _ground(args)
    if ground is None:
        return 2
    try:
        path = study_io.claim_file(args.video, overwrite=args.overwrite)
    except study_spec.StudyError as err:
        print(f"cpgjax walk: {err}", file=sys.stderr)
        return 2
    code = _walk(args)
    trial = protocol.TrialConfig()  # the walk's trials, the paper's
    condition = Condition(
        friction=args.friction[0],
        slope_deg=args.slope_deg[0],
        payload_kg=args.payload_kg[0],
        target_velocity_mps=args.target_velocity_mps,
        gait=args.gaits[0],
        foot_friction=-1.0 if args.foot_friction is None else args.foot_friction,
        ground=ground,
    )
    gait = study_video.Gait(
        group=path.stem,
        params=param_space.midpoint() if args.params is None else np.asarray(args.params.params),
        controller=args.controllers[0],
        physics=args.physics[0],
        condition=condition,
        transition_steps=trial.transition_steps,
        steady_steps=trial.steady_steps,
    )
    try:
        info = study_gaits.film(path, gait, args.backend, args.video_s)
    except (study_video.RenderUnavailable, RuntimeError) as err:
        print(f"cpgjax walk: {err}", file=sys.stderr)
        return code or 1
    _notice(
        f"{path}: {info['rollout_s']:.1f} s after a settling trial, {info['frames']} frames rendered in "
        f"{info['render_s']:.1f} s ({info['backend']})"
    )
    return code


def _walk(args) -> int:
    if args.out is not None:
        try:
            study_io.claim_folder(args.out, overwrite=args.overwrite, resumable=False)
        except study_spec.StudyError as err:
            print(f"cpgjax walk: {err}", file=sys.stderr)
            return 2
    elif args.overwrite and args.video is None:
        print("cpgjax walk: error: --overwrite applies to --out and --video only", file=sys.stderr)
        return 2
    values, notice = _tuned(args, many=True)
    vars(args).update(values)  # walk --video films the same walk
    if notice:
        _notice(notice)
    ground = _ground(args)
    if ground is None:
        return 2
    options = walk.WalkOptions(
        controllers=args.controllers,
        gaits=args.gaits,
        friction=args.friction,
        slope_deg=args.slope_deg,
        payload_kg=args.payload_kg,
        physics=args.physics,
        num_trials=args.trials,
        params=None if args.params is None else args.params.params,
        target_velocity_mps=args.target_velocity_mps,
        backend=args.backend,
        startup=args.startup,
        ground=ground,
        foot_friction=-1.0 if args.foot_friction is None else args.foot_friction,
        out=args.out,
        command_line=args.command_line,
    )
    walk.run_walk(options, progress=_notice)  # progress to stderr: stdout holds the table
    return 0


class _CtrlC:
    """Ctrl-C that always stops a study: Python raises KeyboardInterrupt wherever the main thread is, and one raised
    inside a callback whose exceptions Python ignores (JAX's garbage-collection callback: "Exception ignored in
    _xla_gc_callback") is lost. This handler also keeps the request, and :meth:`check`, after every trial (its
    checkpoint written), raises it again. It replaces only Python's own handler: a command started with Ctrl-C
    ignored keeps ignoring it."""

    def __init__(self):
        self.requested = False
        self._previous = None

    def __enter__(self):
        self._previous = signal.getsignal(signal.SIGINT)
        if self._previous is signal.default_int_handler:
            try:
                signal.signal(signal.SIGINT, self._handler)
            except ValueError:  # not the main thread: Python's handler stays
                self._previous = None
        return self

    def __exit__(self, *exc) -> None:
        if self._previous is signal.default_int_handler:
            signal.signal(signal.SIGINT, self._previous)

    def _handler(self, signum, frame):
        self.requested = True
        raise KeyboardInterrupt

    def check(self) -> None:
        if self.requested:
            raise KeyboardInterrupt

    @property
    def installed(self) -> bool:
        return self._previous is signal.default_int_handler


def _progress_printer(stream=None, ctrl_c: _CtrlC | None = None):
    """The live progress display: trials done, best J per group, env-steps/s, ETA (one rewritten line on a
    terminal). The first trial of a run compiles, so the pace and the ETA come from the trials after it. After each
    line, a Ctrl-C that was lost since (:class:`_CtrlC`) stops the run."""
    stream = stream or sys.stderr
    tty = stream.isatty()

    def show(p) -> None:
        best = ", ".join(f"{k} {v:.3f}" for k, v in p.best_by_group.items())
        eta = "ETA after the next trial" if p.eta_s is None else f"ETA {p.eta_s / 60:.1f} min"
        line = f"{p.trial}/{p.num_trials} trials done | best J: {best} | {p.env_steps_per_s:,.0f} env-steps/s | {eta}"
        stream.write(("\r\033[K" + line + ("\n" if p.trial == p.num_trials else "")) if tty else line + "\n")
        stream.flush()
        if ctrl_c is not None:
            ctrl_c.check()

    return show


def _interrupted(command: str, args, out: pathlib.Path | None) -> int:
    """After Ctrl-C: what the checkpoint holds and how to resume (exit status 130)."""
    try:
        meta = study_io.checkpoint_meta(out) if out is not None else None
    except study_spec.StudyError:
        meta = None
    if meta is None:
        print(f"\ncpgjax {args.command}: interrupted before the first trial was saved", file=sys.stderr)
    else:
        again = command if "--resume" in shlex.split(command) else f"{command} --resume"
        print(
            f"\ncpgjax {args.command}: interrupted; trials 0…{meta['trial'] - 1} are saved in "
            f"{out / study_io.CHECKPOINT}\nresume with: {again}",
            file=sys.stderr,
        )
    return INTERRUPTED


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


def _study_template(args) -> int:
    """``cpgjax study --template PATH``: a commented study file of every key, to copy and edit."""
    try:
        path = study_io.claim_file(args.template, overwrite=args.overwrite)
    except study_spec.StudyError as err:
        print(f"cpgjax study: {err}", file=sys.stderr)
        return 2
    path.write_text(study_spec.template())
    print(f"wrote {path}: edit it, then run `cpgjax study {shlex.quote(str(path))}` (docs/studies.md)")
    return 0


def _study_options(args) -> study_options.StudyOptions:
    return study_options.StudyOptions(
        out=args.out,
        resume=args.resume,
        overwrite=args.overwrite,
        backend=args.backend,
        dry_run=args.dry_run,
        command=args.command_line,
        progress=_progress_printer(ctrl_c=args.ctrl_c),
        notify=_notice,
        quick=args.quick,
        seeds=args.seeds,
        trials=args.trials,
        max_trials=args.max_trials,
        physics=args.physics,
        safe=args.safe,
        startup=args.startup,
        gaits=args.gaits,
        processes=args.processes,
        distributed=args.distributed,
    )


def _study(args) -> int:
    if args.template is not None:
        return _study_template(args)
    if args.name is None:
        print(
            "cpgjax study: name a shipped study (the paper's: "
            + ", ".join(study_driver.paper_studies())
            + "; beyond it: "
            + ", ".join(study_driver.BEYOND_THE_PAPER)
            + ") or a study file "
            "(PATH.toml), or write one with --template PATH",
            file=sys.stderr,
        )
        return 2
    try:
        options = _study_options(args)
        definition = study_driver.read(args.name, **options.overrides())
        if args.print:
            print(definition.source, end="")
            return 0
        study = study_driver.of_file(definition)
        study_driver.check_processes(study, options)
    except study_spec.StudyError as err:
        print(f"cpgjax study: {err}", file=sys.stderr)
        return 2
    if options.processes is not None and options.processes > 1 and not options.dry_run:
        command = [sys.executable, "-m", "cpgjax.cli", *_without_processes(args.argv), "--distributed"]
        outcome = study_launch.run(command, options.processes)
        if outcome.returncode:
            print(f"cpgjax study: {outcome.message}; `--resume` continues from the last checkpoint", file=sys.stderr)
        return outcome.returncode
    if options.distributed and not options.dry_run:
        study_placement.initialize_distributed()
    out = study_io.output_folder(study.name, options.out)
    try:
        text, out, _ = study_driver.run(study, options)
    except study_spec.StudyError as err:
        print(f"cpgjax study: {err}", file=sys.stderr)
        return 2
    except study_io.OutputError as err:
        print(f"cpgjax study: {err}", file=sys.stderr)
        return 1
    except study_placement.ProcessLost as err:
        print(f"cpgjax study: {err}", file=sys.stderr, flush=True)
        sys.stdout.flush()
        os._exit(3)  # not through jax.distributed's shutdown barrier, which would wait for the lost process
    except KeyboardInterrupt:
        return _interrupted(args.command_line, args, study_driver.resumable_folder(study, out))
    print(text)
    print("nothing computed (--dry-run)" if options.dry_run else f"outputs in {out}/")
    return 0


def _demo(args) -> int:
    """``make demo``: the paper's controller ablation — online optimization of the four CPG controllers.

    Runs the ``--quick`` variant (4 controllers × 2 seeds × 12 trials of 1.5 s + 3 s, about a minute on 2 CPU cores)
    because the full study (20 seeds × 40 trials, ``cpgjax study controller_ablation``) takes about ten minutes there
    (docs/REPRODUCTION.md). Prints its table beside the paper's; outputs go to ``results/demo_controller_ablation/``,
    replaced every time.
    """
    print(
        "cpgjax demo: online optimization (contextual GP-UCB, Algorithm 1) of the four CPG controllers at "
        "v* = 0.5 m/s, all runs batched in lockstep on the CPU (quick variant: 2 seeds × 12 trials; the first "
        f"trial compiles). Outputs replace those in {DEMO_OUT}/.",
        flush=True,
    )
    try:
        text, out, _ = study_driver.run_file(
            study_driver.read(study_driver.DEMO_STUDY, quick=True),
            study_options.RunOptions(
                out=DEMO_OUT, overwrite=True, command=args.command_line, progress=_progress_printer(ctrl_c=args.ctrl_c)
            ),
        )
    except KeyboardInterrupt:
        print("\ncpgjax demo: interrupted", file=sys.stderr)
        return INTERRUPTED
    print(text)
    print(f"outputs in {out}/")
    return 0


def _optimize(args) -> int:
    try:
        options = study_options.OptimizeOptions(
            out=pathlib.Path(args.out),
            resume=args.resume,
            overwrite=args.overwrite,
            backend=args.backend,
            command=args.command_line,
            progress=_progress_printer(ctrl_c=args.ctrl_c),
            notify=_notice,
            controller=args.controller,
            gait=args.gait,
            seed=args.seed,
            trials=args.trials,
            max_trials=args.max_trials,
            friction=args.friction,
            slope_deg=args.slope_deg,
            payload_kg=args.payload_kg,
            target_velocity_mps=args.target_velocity_mps,
            foot_friction=args.foot_friction,
            physics=args.physics,
            safe=args.safe,
            startup=args.startup,
        )
        text, out, _ = study_driver.run(study_optimize.study(options), options)
    except study_spec.StudyError as err:
        print(f"cpgjax optimize: {err}", file=sys.stderr)
        return 2
    except study_io.OutputError as err:
        print(f"cpgjax optimize: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # every trial is in the checkpoint: --resume writes the outputs
        return _interrupted(args.command_line, args, pathlib.Path(args.out))
    print(text)
    print(f"outputs in {out}/ ({tuned.replay_hint(out / tuned.FILE_NAME)})")
    return 0


WRITES_RESULTS = ("study", "optimize", "demo", "walk")  # the commands whose Ctrl-C after the last trial is news


def _options_of(kind: type[RobotOptions], args, **values) -> RobotOptions:
    """``kind``'s options (:mod:`cpgjax.deployment.options`) from the parsed ``args``: each field takes the parsed
    option of its name or its value in ``values``, and ``given`` the options the command line gave.

    Raises:
      ValueError: a rule of ``kind`` broken (the message to show).
    """
    taken = {
        field.name: getattr(args, field.name)
        for field in dataclasses.fields(kind)
        if field.name not in values and field.name != "given"
    }
    return kind(**taken, **values, given=frozenset(getattr(args, "given", ())))


def _deploy_options(args) -> tuple[DeployOptions, str | None]:
    """``deploy``'s options from its parsed ``args``, and with ``--params FILE`` the line that says what the file was
    tuned for and which given options override it (None without a file): the file's parameters, and its tuned-for
    values (:func:`_tuned`) in each option the command line did not give.

    Raises:
      ValueError: a rule of :class:`DeployOptions` broken (the message to show).
    """
    if args.params is None:
        return _options_of(DeployOptions, args, params=None, params_path=None), None
    kept, notice = _tuned(args)
    return _options_of(
        DeployOptions, args, **kept, params=args.params.params, params_path=str(args.params.path)
    ), notice


def _deploy(parser: argparse.ArgumentParser, args) -> int:
    """``cpgjax deploy`` after its options' checks (``parser.error`` exits with 2) and the choice of its folder:
    every option is checked at parsing, the rules that span them in :class:`DeployOptions` and the folder here,
    before anything is sent to a robot."""
    try:
        options, tuned_notice = _deploy_options(args)
    except ValueError as err:
        parser.error(str(err))
    try:
        log_dir = study_io.claim_folder(
            options.log_dir or fresh_run_folder(DEPLOY_RUNS), overwrite=options.overwrite, resumable=False
        )
    except study_spec.StudyError as err:
        print(f"cpgjax deploy: {err}", file=sys.stderr)
        return 2
    if tuned_notice:
        _notice(tuned_notice)
    _notice(f"cpgjax deploy: writing to {log_dir}/")
    return deploy.run(dataclasses.replace(options, log_dir=log_dir))


def fresh_run_folder(parent: pathlib.Path) -> pathlib.Path:
    """``parent/<date>-<time>`` (with ``-2``, ``-3``… when that exists): a new folder for each robot run."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    folder, k = parent / stamp, 1
    while folder.exists():
        k += 1
        folder = parent / f"{stamp}-{k}"
    return folder


def _calibrate(args) -> int:
    """``cpgjax deploy calibrate`` after its options' checks (:class:`CalibrateOptions`) and the claim of the files
    it writes, before anything is sent to a robot."""
    try:
        options = _options_of(CalibrateOptions, args)
    except ValueError as err:
        print(f"cpgjax deploy calibrate: error: {err}", file=sys.stderr)
        return 2
    try:
        for path in (options.out, *calibrate.tick_log_paths(options.out).values()):
            study_io.claim_file(path, overwrite=options.overwrite)
    except study_spec.StudyError as err:
        print(f"cpgjax deploy calibrate: {err}", file=sys.stderr)
        return 2
    return calibrate.run(options)


# ----------------------------------------------------------------------------------------------- shared options


def _add_output_args(p: argparse.ArgumentParser, default: str | None, shown: str | None = None) -> None:
    """``--out`` (the folder a study or an optimization writes, with its checkpoint), ``--resume``, ``--overwrite``."""
    p.add_argument(
        "--out",
        type=_output_path,
        default=default and pathlib.Path(default),
        help=f"output folder{f' (default: {shown})' if shown else ''}",
    )
    how = p.add_mutually_exclusive_group()
    how.add_argument(
        "--resume", action="store_true", help="continue from the folder's checkpoint (an error without one)"
    )
    how.add_argument(
        "--overwrite", action="store_true", help="replace the files of a non-empty output folder and start afresh"
    )


def _add_scenario_args(p: argparse.ArgumentParser, many: bool = False, robot: bool = False) -> None:
    """``--friction``, ``--slope-deg`` and ``--payload-kg``, one name, unit and range in every command
    (``many``: comma lists, every combination is run; ``robot``: deploy's, which only the simulated Go1 simulates),
    and ``--foot-friction`` but on deploy."""
    kind, what = (_list_in, "comma list of ") if many else (_in, "")
    for name, allowed, default, text, on_robot in (
        ("--friction", limits.FRICTION, 0.6, "Coulomb friction", "sim only: "),
        ("--slope-deg", limits.SLOPE_DEG, 0.0, "slope [deg], uphill along +x", "sim only: "),
        ("--payload-kg", limits.PAYLOAD_KG, 0.0, "payload [kg]", "counts in CoT; sim: simulated; "),
    ):
        # a string default goes through the type like a typed value (and shows as typed in the help)
        p.add_argument(
            name,
            type=kind(allowed),
            default=f"{default:g}" if many else default,
            action=_Given,
            help=f"{on_robot if robot else ''}{what}{text} in {allowed}",
        )
    if not robot:
        p.add_argument(
            "--foot-friction",
            type=_in(limits.FRICTION),
            default=None,
            help=f"the feet's Coulomb friction in {limits.FRICTION}: a contact takes the smaller of floor's "
            "and feet's, as the paper's Gazebo does (default: the physics profile's own, 0.6 under paper; "
            "none under soft and go1, where the floor's holds)",
        )


def _add_terrain_args(p: argparse.ArgumentParser) -> None:
    """``--terrain``, ``--terrain-amplitude``, ``--terrain-seed`` and ``--terrain-step``: the ground of every walk
    (docs/physics.md, "Terrain")."""
    p.add_argument(
        "--terrain",
        choices=terrains.TERRAINS,
        default=terrains.FLAT,
        help="sim only: the ground, flat (the plane), rough (a periodic height field of random heights) or "
        "blocks (square blocks of random heights)",
    )
    p.add_argument(
        "--terrain-amplitude",
        type=_in(limits.TERRAIN_AMPLITUDE_M),
        default=None,
        help=f"--terrain rough or blocks: peak-to-peak height [m] in {limits.TERRAIN_AMPLITUDE_M} "
        "(required with them; default: none, the plane)",
    )
    p.add_argument(
        "--terrain-seed",
        type=_integer_in(range(2**32), "the stream of the random heights"),
        default=0,
        help="--terrain rough or blocks: the seed of its heights (the same seed, the same ground)",
    )
    p.add_argument(
        "--terrain-step",
        type=_in(limits.BLOCK_DEPTH_M),
        default=None,
        help=f"--terrain blocks: the blocks' depth [m] in {limits.BLOCK_DEPTH_M} (required with blocks)",
    )


def _ground(args) -> terrains.Ground | None:
    """The ground of ``args``, or None after saying in one line why the options do not make one."""
    if args.terrain == terrains.FLAT:
        if args.terrain_amplitude is not None:
            print(
                f"cpgjax {args.command}: --terrain-amplitude applies to --terrain rough or blocks only", file=sys.stderr
            )
            return None
        return terrains.FLAT_GROUND
    if args.terrain_amplitude is None:
        print(
            f"cpgjax {args.command}: --terrain {args.terrain} needs --terrain-amplitude (peak-to-peak [m] in "
            f"{limits.TERRAIN_AMPLITUDE_M})",
            file=sys.stderr,
        )
        return None
    if (args.terrain == terrains.BLOCKS) != (args.terrain_step is not None):
        need = (
            f"--terrain blocks needs --terrain-step (the blocks' depth [m] in {limits.BLOCK_DEPTH_M})"
            if args.terrain == terrains.BLOCKS
            else "--terrain-step applies to --terrain blocks only"
        )
        print(f"cpgjax {args.command}: {need}", file=sys.stderr)
        return None
    return terrains.Ground(args.terrain, args.terrain_amplitude, args.terrain_seed, args.terrain_step or 0.0)


def _add_target_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--target-velocity-mps",
        type=_in(limits.TARGET_VELOCITY_MPS),
        default=0.5,
        action=_Given,
        help=f"target velocity v_x* [m/s] of the objective J, in {limits.TARGET_VELOCITY_MPS}",
    )


def _names_in(allowed, what: str):
    """The argparse type of a comma list of names, each one of ``allowed`` (a ``what``: "controller", ...)."""

    def names(text: str) -> tuple[str, ...]:
        given = tuple(text.split(","))
        for name in given:
            if name not in allowed:
                raise argparse.ArgumentTypeError(f"unknown {what} {name!r}; allowed: {', '.join(allowed)}")
        return given

    return names


def _add_physics_arg(p: argparse.ArgumentParser, default: str | None, many: bool = False) -> None:
    """``--physics``: the physics profile(s) of the simulated Go1 (docs/physics.md)."""
    allowed = ", ".join(physics_profiles.PROFILES)
    if many:
        p.add_argument(
            "--physics",
            type=_names_in(tuple(physics_profiles.PROFILES), "physics profile"),
            default=default,
            action=_Given,
            help=f"comma list of physics profiles ({allowed})",
        )
    else:
        p.add_argument(
            "--physics",
            choices=tuple(physics_profiles.PROFILES),
            default=default,
            action=_Given,
            help="physics profile" + ("" if default else " (default: the study's own)"),
        )


def _add_gait_arg(p: argparse.ArgumentParser, default: str | None, many: bool = False, help_suffix: str = "") -> None:
    """``--gait`` (``--gaits``: a comma list): the CPG's coupling pattern, ``cpg.GAITS`` (docs/gaits.md)."""
    allowed = ", ".join(cpg.GAITS)
    what = (
        f"the CPG's gait (coupling phase lags, docs/gaits.md): {allowed}"
        + ("" if default else "; default: the study's own")
        + help_suffix
    )
    if many:
        p.add_argument(
            "--gaits",
            type=_names_in(tuple(cpg.GAITS), "gait"),
            default=default if default is None else (default,),
            action=_Given,
            help=f"comma list of gaits; {what}",
        )
    else:
        p.add_argument("--gait", choices=tuple(cpg.GAITS), default=default, action=_Given, help=what)


def _add_startup_arg(p: argparse.ArgumentParser, default: str | None) -> None:
    """``--startup``: how the controller starts from standing (docs/decisions.md §18)."""
    p.add_argument(
        "--startup",
        choices=tuple(cpg.STARTUPS),
        default=default,
        help="how the robot starts from standing, at the first trial and after a fall: paper (the "
        "paper's start) or lean_ramp (stand leaning into the slope, amplitude ramped over "
        f"{cpg.STARTUPS['lean_ramp']['start_ramp_s']:g} s)" + ("" if default else " (default: the study's own)"),
    )


def _add_robot_args(p: argparse.ArgumentParser, robot_required: bool = True) -> None:
    """The options that choose and reach the robot (``cpgjax deploy`` and ``cpgjax deploy calibrate``)."""
    p.add_argument_group("required").add_argument(
        "--robot",
        choices=("sim", "go1"),
        required=robot_required,
        help="required; sim: start the simulated Go1 on 127.0.0.1; go1: the robot (low-level mode, EDU)",
    )
    p.add_argument("--transport", choices=("udp", "sdk"), help="(default: sdk for go1, udp for sim)")
    p.add_argument("--robot-ip", type=_ip_address, default=go1_transport.GO1_ROBOT_IP, action=_Given, help="go1 only")
    p.add_argument("--robot-port", type=_port, default=go1_transport.GO1_ROBOT_PORT, action=_Given, help="go1 only")
    p.add_argument("--local-port", type=_port, default=go1_transport.GO1_LOCAL_PORT, action=_Given, help="go1 only")
    levels = go1_safety.POWER_LEVELS
    p.add_argument(
        "--power-level",
        type=_power_level,
        default=9,
        help=f"power protection level {levels.start}…{levels.stop - 1} (trips above 100 W each)",
    )
    p.add_argument(
        "--sim-pacing",
        choices=("realtime", "lockstep"),
        default="realtime",
        action=_Given,
        help="lockstep: one physics step per command, the loop waits for each answer (not real time)",
    )
    _add_scenario_args(p, robot=True)
    p.add_argument(
        "--physics",
        choices=tuple(physics_profiles.PROFILES),
        default=physics_profiles.ROBOT_PROFILE,
        action=_Given,
        help="sim only: the simulated Go1's physics profile (docs/physics.md)",
    )
    p.add_argument("--no-realtime", action="store_true", help="do not ask for SCHED_FIFO")
    p.add_argument(
        "--cpu",
        type=_cpu,
        help="pin the loop to this CPU (the optimizer and the log writer run on the "
        "others; a simulated Go1 in real time shares the loop's CPU; default: the last CPU, none in "
        "lockstep)",
    )
    p.add_argument(
        "--busy-wait",
        action="store_true",
        help="spin through each period instead of sleeping (on the loop's CPU; with --no-realtime unless "
        "the kernel's real-time throttling is off); fewer overruns on a VM (docs/hardware.md)",
    )
    p.add_argument(
        "--idle-halt",
        action="store_true",
        help="let idle CPUs halt between ticks: saves power (a robot's battery), but the loop's ticks run "
        "slower after each halt (default: idle CPUs poll while the loop runs, docs/hardware.md)",
    )
    p.add_argument(
        "--overwrite", action="store_true", help="write into a non-empty output folder or over an existing file"
    )


# ----------------------------------------------------------------------------------------------- the parser


def _add_walk(sub) -> None:
    w = sub.add_parser(
        "walk", help="walk with fixed parameters and print the trial figures", formatter_class=_HelpFormatter
    )
    w.add_argument(
        "--controllers",
        type=_names_in(cpg.CONTROLLERS, "controller"),
        default=",".join(cpg.CONTROLLERS),
        action=_Given,
        help="comma list of controllers",
    )
    _add_gait_arg(w, cpg.DEFAULT_GAIT, many=True)
    _add_scenario_args(w, many=True)
    _add_terrain_args(w)
    w.add_argument("--trials", type=_count(), default=2, help="back-to-back trials of 1.5 s + 3 s")
    _add_target_arg(w)
    _add_physics_arg(w, physics_profiles.DEFAULT_PROFILE, many=True)
    _add_startup_arg(w, cpg.DEFAULT_STARTUP)
    w.add_argument(
        "--out",
        type=_output_path,
        help="write walk.parquet (every trial) and metadata.json into this "
        "folder, missing or empty (default: print the table only)",
    )
    w.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the files of a previous walk in --out and an existing --video file",
    )
    w.add_argument(
        "--params",
        type=_params_file,
        help="walk with these parameters: a best_params.json (of optimize, "
        "deploy --optimize or a study), whose controller, physics, scenario and target are used unless "
        "given here, or a JSON list of 8 numbers (default: the middle of the paper's ranges)",
    )
    backends.add_backend_argument(w)
    w.add_argument(
        "--video",
        type=pathlib.Path,
        help="also film the walk (one combination, the paper's trial as "
        "settling, then --video-s) into this MP4 (docs/visualization.md; default: no video)",
    )
    _add_video_length_arg(w)
    w.set_defaults(func=lambda args: _walk_video(args) if args.video else _walk(args))


SAFE_HELP = (
    "safe optimization: a second GP learns each trial's safety margin (trunk height and tilt against the fall "
    "and tilt-stop thresholds) and proposals stay where it is certified >= 0 (docs/decisions.md §17)"
)


MAX_TRIALS_HELP = (
    "the trials the run can later be extended to with --resume --trials N, N <= this, with the "
    "results of a run of N (the optimizers hold this many; default: --trials)"
)


def _add_study(sub) -> None:
    s = sub.add_parser(
        "study",
        help="run a study file (PATH.toml) or a paper study by name and write results/<study>/",
        formatter_class=_HelpFormatter,
    )
    s.add_argument(
        "name",
        nargs="?",
        help="a study file (PATH.toml, docs/studies.md) or a paper study: "
        + ", ".join(study_driver.paper_studies())
        + "; or one beyond it: "
        + ", ".join(study_driver.BEYOND_THE_PAPER)
        + " (each the file studies/<name>.toml)",
    )
    s.add_argument("--print", action="store_true", help="print the study's file (to copy and edit) and stop")
    s.add_argument(
        "--template",
        type=pathlib.Path,
        help="write a commented study file of every key, its default, "
        "unit and range to this path and stop (with --overwrite: replace an existing file)",
    )
    s.add_argument(
        "--seeds",
        type=_whole,
        default=None,
        help="seeds 0 … N-1 per group (default: the file's seeds; --quick its [quick] seeds)",
    )
    s.add_argument(
        "--trials",
        type=_whole,
        default=None,
        help=f"trials per run, at least {limits.MIN_STUDY_TRIALS}; condition changes scale with it "
        "(default: the file's trials; --quick its [quick] trials)",
    )
    seeds, trials = study_driver.quick_sizes()
    s.add_argument(
        "--quick",
        action="store_true",
        help="the file's [quick] values: fewer seeds and trials (the "
        f"shipped studies: {'/'.join(map(str, seeds))} seeds, {trials[0]} to {trials[-1]} trials; "
        "`--print` shows a study's)",
    )
    s.add_argument("--max-trials", type=_whole, default=None, help=MAX_TRIALS_HELP)
    s.add_argument("--safe", action="store_true", help=SAFE_HELP)
    s.add_argument(
        "--dry-run",
        action="store_true",
        help="check every input and the output folder, print what "
        "the run would compute (instances, trials, env-steps, where it writes) and stop: nothing is "
        "computed, written or deleted",
    )
    _add_output_args(s, None, "results/<study>")
    s.add_argument(
        "--distributed",
        action="store_true",
        help="one of several cooperating processes: "
        "jax.distributed.initialize() first (coordinator, count and rank from the environment or Slurm; "
        "docs/scaling.md)",
    )
    s.add_argument(
        "--processes",
        type=_whole,
        default=None,
        help="run as N cooperating local processes "
        "(coordinator on 127.0.0.1), e.g. to check a multi-process run before a cluster (default: one "
        "process)",
    )
    _add_physics_arg(s, None)
    _add_startup_arg(s, None)
    _add_gait_arg(s, None, many=True)
    backends.add_backend_argument(s)
    s.set_defaults(func=_study)


def _add_optimize(sub) -> None:
    o = sub.add_parser(
        "optimize",
        help="one online optimization (Algorithm 1) with a controller, scenario, target",
        formatter_class=_HelpFormatter,
    )
    o.add_argument("--controller", choices=cpg.CONTROLLERS, default="vmc_tegotae", help="the CPG controller")
    _add_gait_arg(o, cpg.DEFAULT_GAIT)
    _add_scenario_args(o)
    _add_target_arg(o)
    o.add_argument("--trials", type=_whole, default=40, help="trials of 1.5 s + 3 s")
    o.add_argument("--max-trials", type=_whole, default=None, help=MAX_TRIALS_HELP)
    o.add_argument("--seed", type=_seed, default=0, help="the optimizer's random seed")
    o.add_argument("--safe", action="store_true", help=SAFE_HELP)
    _add_output_args(o, "results/optimize")
    _add_physics_arg(o, physics_profiles.DEFAULT_PROFILE)
    _add_startup_arg(o, cpg.DEFAULT_STARTUP)
    backends.add_backend_argument(o)
    o.set_defaults(func=_optimize)


def _add_video_length_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--video-s",
        type=_in(study_video.DURATION_S),
        default=3.0,
        help=f"length of the filmed gait [s] after its settling trial, in {study_video.DURATION_S}",
    )


def _add_show(sub) -> None:
    v = sub.add_parser(
        "show", help="print a results folder's tables and open its rerun recording", formatter_class=_HelpFormatter
    )
    v.add_argument("results", help="e.g. results/controller_ablation")
    v.add_argument("--no-viewer", action="store_true", help="do not open the recording")
    v.add_argument(
        "--video",
        action="store_true",
        help="(re)render the study's best_<group>.mp4 from its best_params/<group>.json first, replacing them",
    )
    _add_video_length_arg(v)
    backends.add_backend_argument(v)
    v.add_argument(
        "--web",
        action="store_true",
        help="serve the recording in rerun's web viewer on 127.0.0.1 (for "
        "a browser here or through an ssh tunnel) until Ctrl-C",
    )
    v.add_argument(
        "--port",
        type=_integer_in(range(1024, 65536), "an unprivileged TCP port"),
        default=study_viewer.DEFAULT_WEB_PORT,
        help="--web: the viewer's port (the page and the recording)",
    )
    v.set_defaults(func=show.command)


def _add_demo(sub) -> None:
    d = sub.add_parser(
        "demo",
        help=f"`make demo`: the controller ablation's quick variant, afresh, into {DEMO_OUT}/",
        description="The paper's controller ablation, quick variant: online optimization of the "
        "four CPG controllers at v* = 0.5 m/s, 2 seeds × 12 trials, batched on the CPU, written afresh "
        f"into {DEMO_OUT}/ (the full study: cpgjax study controller_ablation).",
        formatter_class=_HelpFormatter,
    )
    d.set_defaults(func=_demo)


def _add_deploy(sub) -> None:
    d = sub.add_parser(
        "deploy",
        help="run the CPG at 1 kHz on a Go1 or the loopback simulated Go1 "
        "(`cpgjax deploy calibrate`: the foot-force calibration)",
        description="Run the CPG controller at 1 kHz on a Go1 or on the loopback simulated Go1; "
        "replay parameters or optimize them online. `cpgjax deploy calibrate --help`: the foot-force "
        "calibration.",
        formatter_class=_HelpFormatter,
        # --robot is required, but argparse could only say so by asking for it before `calibrate` too
        usage="cpgjax deploy --robot {sim,go1} [options]\n       cpgjax deploy calibrate --robot {sim,go1} [options]",
    )
    _add_robot_args(d, robot_required=False)  # _deploy requires it: argparse would ask for it before `calibrate` too
    what = d.add_mutually_exclusive_group()
    what.add_argument(
        "--params",
        type=_params_file,
        help="replay these parameters: a best_params.json (of "
        "optimize, deploy --optimize or a study), whose controller, physics, scenario and target are "
        "used unless given here, or a JSON list of 8 numbers (default: the middle of the paper's "
        "ranges)",
    )
    what.add_argument("--optimize", action="store_true", help="online optimization (Algorithm 1)")
    d.add_argument(
        "--trials", type=_count(), default=10, action=_Given, help="--optimize only: trials of online optimization"
    )
    d.add_argument(
        "--optimizer",
        choices=("bo", "random"),
        default="bo",
        action=_Given,
        help="--optimize only: the online optimizer",
    )
    d.add_argument(
        "--safe",
        action="store_true",
        help=f"--optimize with bo only: {SAFE_HELP}; on the robot the margin is the tilt stop's, from the IMU",
    )
    d.add_argument(
        "--controller",
        choices=cpg.CONTROLLERS,
        default="vmc_tegotae",
        action=_Given,
        help="the CPG controller (with --params: the file's)",
    )
    _add_gait_arg(d, cpg.DEFAULT_GAIT, help_suffix=" (with --params: the file's)")
    _add_startup_arg(d, cpg.DEFAULT_STARTUP)
    _add_target_arg(d)
    d.add_argument(
        "--duration-s",
        type=_in(limits.RUN_DURATION_S),
        default=10.0,
        action=_Given,
        help=f"replay only: run time [s], in {limits.RUN_DURATION_S}",
    )
    d.add_argument(
        "--transition-s",
        type=_in(limits.TRANSITION_S),
        default=1.5,
        action=_Given,
        help=f"--optimize only: each trial's parameter transition [s], in {limits.TRANSITION_S}",
    )
    d.add_argument(
        "--steady-s",
        type=_in(limits.STEADY_S),
        default=3.0,
        action=_Given,
        help=f"--optimize only: each trial's steady phase T [s], in {limits.STEADY_S}",
    )
    d.add_argument(
        "--log-dir",
        type=_output_path,
        help=f"the run's folder (default: a new {DEPLOY_RUNS}/<date>-<time>"
        "; an existing non-empty one needs --overwrite)",
    )
    d.add_argument(
        "--calibration",
        type=_calibration_file,
        help="foot-force calibration JSON from `cpgjax deploy "
        "calibrate` (required with --robot go1; default with sim: the simulated sensor's exact one)",
    )
    d.add_argument(
        "--seed",
        type=_seed,
        default=0,
        help="the optimizer's random seed, and with --robot sim the simulated sensors' noise stream",
    )
    d.set_defaults(func=functools.partial(_deploy, d))

    c = d.add_subparsers(title="subcommands", prog="cpgjax deploy").add_parser(
        "calibrate",
        help="measure the foot-force sensors and save their calibration",
        description="Measure the Go1's foot-force sensors (feet in the air, then standing) and save their "
        "calibration to raw counts → N.",
        formatter_class=_HelpFormatter,
    )
    _add_robot_args(c)
    c.add_argument(
        "--out",
        type=_output_path,
        default=pathlib.Path("go1_calibration.json"),
        help="calibration JSON to write, each measuring stand's per-tick log next to it "
        "(NAME.air.ticks.arrows, NAME.standing.ticks.arrows; existing ones need --overwrite)",
    )
    c.add_argument(
        "--air-s", type=_in(limits.MEASURE_S), default=2.0, help="measuring time with the feet in the air [s]"
    )
    c.add_argument("--stand-s", type=_in(limits.MEASURE_S), default=3.0, help="measuring time standing still [s]")
    c.add_argument(
        "--settle-s", type=_in(limits.SETTLE_S), default=1.0, help="time holding the pose before each measurement [s]"
    )
    c.add_argument(
        "--mass-kg",
        type=_in(limits.ROBOT_MASS_KG),
        help=f"the robot's total mass [kg] in {limits.ROBOT_MASS_KG} (default: cpgjax's Go1 model + --payload-kg)",
    )
    c.add_argument(
        "--lift-m",
        type=_in(limits.LIFT_M),
        default=0.3,
        action=_Given,
        help="sim only: how high the simulated Go1 is hung up [m]",
    )
    c.set_defaults(func=_calibrate)


def build_parser() -> argparse.ArgumentParser:
    """The ``cpgjax`` parser: every command, each with its function as ``func``."""
    parser = _Parser(prog="cpgjax", description="cpgjax: online-optimized CPG control for the Go1.")
    parser.add_argument("--version", action="version", version=f"cpgjax {cpgjax.__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in (_add_walk, _add_study, _add_optimize, _add_show, _add_demo, _add_deploy):
        add(sub)
    return parser


def main(argv=None) -> int:
    as_command = argv is None  # the `cpgjax` process itself, not a call from Python
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_args(argv)
    args.command_line = "cpgjax " + shlex.join(argv)  # metadata.json and the resume hint
    args.argv = argv  # `study --processes N` starts the same command line N times
    # Before any JAX computation: the native backend's and the robot loop's per-tick controller calls run inline, and
    # XLA's CPU pool leaves the cores to the native backend's physics threads (all but an explicit MJX run).
    cpu_dispatch.request_inline()
    if getattr(args, "backend", "auto") != "mjx":
        cpu_dispatch.request_one_pool_thread()
    if as_command:  # the next run loads this one's compiled programs (a caller from Python decides for its process)
        compile_cache.enable()
    with _CtrlC() as args.ctrl_c:  # study, optimize, demo: check it after every trial
        code = args.func(args)
    if args.ctrl_c.requested and code == 0 and args.command in WRITES_RESULTS:
        # lost after the last trial's check: the outputs are written
        _notice(f"cpgjax {args.command}: interrupted as it finished; its outputs are written")
        code = INTERRUPTED
    if as_command and args.ctrl_c.installed:
        # The command is done and its outputs written. Python's teardown resets a Python-level handler to the
        # default, and a Ctrl-C then kills the exiting process by the signal; ignored, the exit status stays the
        # command's.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    return code


if __name__ == "__main__":
    sys.exit(main())
