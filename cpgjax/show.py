"""``cpgjax show``: a results folder (or a calibration file) listed, each file with what it holds and what is wrong
with it, its table, metadata and next step, and its rerun recording opened; ``--video`` films a study's best gaits
again, ``--web`` serves the recording in rerun's web viewer."""

from __future__ import annotations

import json
import os
import pathlib
import shutil
import signal
import subprocess
import sys

from cpgjax import outputs
from cpgjax.deployment import calibrate, deploy, tick_log, trials
from cpgjax.go1 import constants
from cpgjax.robot import foot_force
from cpgjax.sim import walk
from cpgjax.studies import figures as study_figures
from cpgjax.studies import gaits as study_gaits
from cpgjax.studies import transfer
from cpgjax.studies import video as study_video
from cpgjax.studies import viewer as study_viewer
from cpgjax.study import files as study_io
from cpgjax.study import spec as study_spec
from cpgjax.trial import tuned

VIEWER_START_S = 2.0  # a viewer still running after this long counts as started


def _notice(line: str) -> None:
    """A line for the person at the terminal (stderr: stdout holds the listing)."""
    print(line, file=sys.stderr, flush=True)


def _has_display() -> bool:
    """Whether a viewer window can open here: macOS and Windows have a desktop; elsewhere X11 or Wayland must be
    named in the environment."""
    return sys.platform in ("darwin", "win32") or bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _viewer() -> str | None:
    """The rerun viewer: the venv's, also when the venv is not activated, else the one on PATH."""
    beside = pathlib.Path(sys.executable).parent / "rerun"
    return str(beside) if beside.exists() else shutil.which("rerun")


def catalogue() -> tuple[outputs.OutputFile, ...]:
    """Every file a cpgjax command writes, each as its writer declares it (docs/outputs.md documents the same)."""
    return (
        *outputs.OUTPUTS,
        *study_io.OUTPUTS,
        *tuned.OUTPUTS,
        *walk.OUTPUTS,
        *study_figures.OUTPUTS,
        *study_video.OUTPUTS,
        *transfer.OUTPUTS,
        *tick_log.OUTPUTS,
        *deploy.OUTPUTS,
        *trials.OUTPUTS,
        *calibrate.OUTPUTS,
    )


def _file_kind(path: pathlib.Path) -> str:
    entry = outputs.entry_of(path.name, catalogue())
    if entry is not None:
        return entry.meaning
    if path.is_dir() and (path / outputs.METADATA).exists():
        return f"an arm of the study (cpgjax show {path})"
    return "not written by cpgjax"


def _damage(path: pathlib.Path) -> str | None:
    """What is wrong with a file cpgjax wrote (empty, truncated, corrupt: its catalogue entry's check), None if it
    reads back or is no file of the catalogue."""
    entry = outputs.entry_of(path.name, catalogue())
    try:
        if path.is_dir() or entry is None:
            return None
        if path.stat().st_size == 0:
            return "empty"
        return entry.check(path)
    except Exception as err:  # each reader raises its own kinds for a damaged file
        return f"corrupt or truncated ({type(err).__name__}: {err})"


def _files_listing(out: pathlib.Path) -> tuple[list[str], int]:
    """One line per entry of ``out``: its name, what it is, and what is wrong with it; and the count of damaged
    ones."""
    lines, damaged = [], 0
    for path in sorted(out.iterdir()):
        problem = _damage(path)
        damaged += problem is not None
        shown = path.name + ("/" if path.is_dir() else "")
        lines.append(f"  {shown:<20} {_file_kind(path)}" + (f"  [{path.name}: {problem}]" if problem else ""))
    return lines, damaged


def _metadata_line(path: pathlib.Path) -> str:
    try:
        m = json.loads(path.read_text())
        if not isinstance(m, dict):
            raise ValueError("not a JSON object")
    except (OSError, UnicodeDecodeError, ValueError) as err:
        return f"{path}: corrupt or truncated ({err})"
    parts = [f"{m['instances']} instances × {m['trials']} trials"] if "instances" in m and "trials" in m else []
    for key, label, unit in (
        ("backend", "on", ""),
        ("wall_s", "wall", " s"),
        ("env_steps_per_s", "", " env-steps/s"),
        ("real_time_factor", "real-time factor", "×"),
        ("git_commit", "commit", ""),
        ("command", "command:", ""),
    ):
        if m.get(key) is not None:
            parts.append(f"{label} {m[key]}{unit}".strip())
    return f"{m.get('study', '(no study name)')}: " + ", ".join(parts)


def _read_json(path: pathlib.Path) -> dict | None:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _folder_kind(out: pathlib.Path) -> str | None:
    """Which command wrote ``out``: "deploy", "optimize", "walk", "study", "calibrate", or None (not a result). Its
    metadata.json says so (``written_by``); a folder without one (a robot run, a calibration's stands, an unfinished
    run, a run from before metadata.json named its command) is told by its files."""
    names = {p.name for p in out.iterdir()}
    meta = _read_json(out / outputs.METADATA) or {}
    if meta.get("written_by"):
        return meta["written_by"]
    if names & {tick_log.RUN_FILE, tick_log.FILE_NAME}:
        return "deploy"
    if meta.get("study") in ("optimize", "walk"):
        return meta["study"]
    gaits = study_io.BEST_PARAMS in names or any(study_video.VIDEO.matches(n) for n in names)
    if (
        names & {study_io.TABLE, outputs.TRIALS, outputs.METADATA, study_io.RECORDING}
        or gaits
        or (study_io.checkpoint_files(out))
        or any((out / n / outputs.METADATA).exists() or study_io.checkpoint_files(out / n) for n in names)
    ):
        return "optimize" if tuned.FILE_NAME in names else "study"
    if any(_air_log(n) for n in names):
        return "calibrate"
    return None


def _air_log(name: str) -> bool:
    """Whether the file called ``name`` is a calibration's first stand's per-tick log."""
    return calibrate.STAND_LOGS[calibrate.STANDS[0]].matches(name)


def _next_step(out: pathlib.Path, kind: str) -> str:
    """What to run next with a result folder."""
    meta = _read_json(out / outputs.METADATA)
    if kind in ("study", "optimize") and meta is None and (out / outputs.METADATA).exists():
        return "next: metadata.json is damaged: the command that wrote the folder, again with --resume, rewrites it"
    if kind in ("study", "optimize") and meta is None and study_io.checkpoint_files(out):
        try:
            done = (study_io.checkpoint_meta(out) or {}).get("trial")
        except study_spec.StudyError:
            return "next: its checkpoint is damaged: start afresh with --overwrite"
        return (
            f"next: unfinished ({done} trials done, no metadata.json yet): run the command that started it again "
            f"with --resume"
        )
    if kind == "optimize" or (kind == "deploy" and (out / tuned.FILE_NAME).exists()):
        return f"next: {tuned.replay_hint(out / tuned.FILE_NAME)}"
    groups = sorted((out / study_io.BEST_PARAMS).glob("*.json"))
    if groups:
        return f"next: {tuned.replay_hint(groups[0])} (one file per group in {out / study_io.BEST_PARAMS}/)"
    if kind == "calibrate":
        found = sorted(p for p in out.iterdir() if _air_log(p.name))
        return f"next: cpgjax deploy --robot go1 --calibration {calibrate.calibration_file(found[0])}"
    if kind == "deploy":
        return (
            f"next: the per-tick log in Python: pyarrow.ipc.open_stream({str(out / tick_log.FILE_NAME)!r})"
            ".read_all().to_pandas()"
        )
    data = out / (walk.TABLE if kind == "walk" else outputs.TRIALS)
    return f"next: its trials in Python: pandas.read_parquet({str(data)!r})"


def _calibration_file_summary(path: pathlib.Path) -> int:
    """``cpgjax show`` of a calibration file: its values and its stands' per-tick logs."""
    try:
        calibration = foot_force.FootForceCalibration.load(path)
    except ValueError as err:
        print(f"cpgjax show: {err}", file=sys.stderr)
        return 2
    print(
        f"foot-force calibration {path}: offsets {calibration.offset_counts.tolist()} counts, "
        f"{calibration.newton_per_count.tolist()} N/count"
    )
    damaged = 0
    for stand, log in calibrate.tick_log_paths(path).items():
        problem = _damage(log) if log.exists() else "missing"
        damaged += problem is not None
        print(f"  {log.name:<20} the per-tick log of the {stand} stand" + (f"  [{problem}]" if problem else ""))
    print(f"next: cpgjax deploy --robot go1 --calibration {path}")
    return 1 if damaged else 0


def _summarize(args) -> int:
    out = pathlib.Path(args.results)
    if out.is_file() and out.suffix == ".json":
        return _calibration_file_summary(out)
    if not out.is_dir():
        print(f"cpgjax show: {out} is not a folder (or a calibration file)", file=sys.stderr)
        return 2
    kind = _folder_kind(out)
    if kind is None:
        print(
            f"cpgjax show: {out} holds no cpgjax results (no table.md, metadata.json, trials.parquet, recording, "
            f"best gait, checkpoint, run.json or {tick_log.FILE_NAME})",
            file=sys.stderr,
        )
        return 2
    listing, damaged = _files_listing(out)
    print(f"{out}: a `cpgjax {kind}` folder\n" + "\n".join(listing))
    if kind == "deploy":
        print(tick_log.summarize_run(out))
    table = out / study_io.TABLE
    if table.exists() and _damage(table) is None:
        print(table.read_text())
    if (out / outputs.METADATA).exists() and _damage(out / outputs.METADATA) is None:
        print(_metadata_line(out / outputs.METADATA))
    data = out / outputs.TRIALS
    if data.exists() and _damage(data) is None:
        import pyarrow.parquet as pq

        rows = pq.read_metadata(data).num_rows
        print(f"trial data ({rows} rows): pandas.read_parquet({str(data)!r}) or pyarrow.parquet.read_table(...)")
    print(_next_step(out, kind))
    status = 1 if damaged else 0
    recordings = (out / name for name in (study_io.RECORDING, trials.RECORDING))
    recording = next((path for path in recordings if path.exists()), None)
    if recording is None or _damage(recording) in ("empty", "not a rerun recording"):
        return status
    viewer = _viewer()
    elsewhere = f"copy it to a machine with a display and run `rerun {recording.name}` (pip install rerun-sdk)"
    if args.no_viewer:
        print(f"recording: {recording}")
    elif not _has_display():
        print(f"recording: {recording}; no display here (DISPLAY and WAYLAND_DISPLAY are unset): {elsewhere}")
    elif viewer is None:
        print(f"recording: {recording}; the rerun viewer is not installed (pip install rerun-sdk): {elsewhere}")
    else:
        proc = subprocess.Popen(
            [viewer, "--bind", "127.0.0.1", str(recording)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        try:
            code = proc.wait(VIEWER_START_S)
        except subprocess.TimeoutExpired:
            print(f"opened {recording} in the rerun viewer (pid {proc.pid}, serving on 127.0.0.1 only)")
            return status
        print(f"recording: {recording}; the rerun viewer exited at once (status {code}): {elsewhere}")
        return 1
    return status


def _film(args) -> int:
    """``cpgjax show DIR --video``: film each best_params/<group>.json of a study folder again."""
    out = pathlib.Path(args.results)
    try:
        gaits = study_video.load_gaits(out) if out.is_dir() else None
    except study_spec.StudyError as err:
        print(f"cpgjax show: {err}", file=sys.stderr)
        return 2
    if not gaits:
        print(
            f"cpgjax show: {out} has no {study_io.BEST_PARAMS}/<group>.json to film (a study writes them)",
            file=sys.stderr,
        )
        return 2
    for gait in gaits:
        if study_video.video_file(out, gait.group).exists():
            _notice(f"replacing {study_video.video_file(out, gait.group)}")
    logs = study_gaits.gait_rollouts(gaits, args.backend, steps=constants.ticks(args.video_s))
    return 0 if study_video.write_videos(out, gaits, logs, _notice) else 1


def _serve(args) -> int:
    """``cpgjax show DIR --web``: rerun's web viewer on the folder's recording, on 127.0.0.1, until Ctrl-C."""
    recording = pathlib.Path(args.results) / study_io.RECORDING
    if not recording.is_file():
        print(f"cpgjax show: {recording} does not exist (a study or `cpgjax optimize` writes it)", file=sys.stderr)
        return 2
    try:
        proc = study_viewer.serve(recording, args.port)
    except study_spec.StudyError as err:
        print(f"cpgjax show: {err}", file=sys.stderr)
        return 2
    print(
        f"serving {recording} in rerun's web viewer on 127.0.0.1 only (pid {proc.pid}); open\n"
        f"  {study_viewer.url(args.port)}\n"
        f"from another machine, tunnel its port first:\n  {study_viewer.tunnel_line(args.port)}\n"
        "Ctrl-C stops it.",
        flush=True,
    )
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))  # a kill, like Ctrl-C, stops the viewer first
    try:
        return proc.wait()
    except KeyboardInterrupt:
        _notice("cpgjax show: the viewer is stopped")
        return 0
    finally:
        study_viewer.stop(proc)


def command(args) -> int:
    """``cpgjax show``: with ``--video`` the study's best gaits filmed again first, then the folder's listing and
    its recording, in rerun's viewer or (``--web``) its web viewer."""
    if args.video:
        code = _film(args)
        if code:
            return code
    if args.web:
        args.no_viewer = True
        code = _summarize(args)
        return code or _serve(args)
    return _summarize(args)
