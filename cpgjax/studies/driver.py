"""Running a study: a study file (or a paper study by name) or a :class:`~cpgjax.study.spec.StudySpec`, into a folder
of results (docs/studies.md, docs/outputs.md).

:func:`run_spec` is the Python API: it runs a ``StudySpec`` with the lockstep engine (``cpgjax.ablation``), writes
every output file and returns a :class:`StudyRun`. :func:`run_file` runs what a study file defines, with its report
(a hand-written one of ``registry.REPORTS``, or the generic one, ``cpgjax.studies.generic``); ``cpgjax study`` calls
it. :func:`find` turns a paper study's name or a file's path into the file.
"""

from __future__ import annotations

import pathlib
import sys
import tomllib
from collections.abc import Callable
from typing import Any, NamedTuple

import jax

from cpgjax import ablation, outputs
from cpgjax.sim import backends
from cpgjax.studies import figures as study_figures
from cpgjax.studies import gaits as study_gaits
from cpgjax.studies import generic, registry, transfer
from cpgjax.studies import video as study_video
from cpgjax.study import files as study_io
from cpgjax.study import scene as study_scene
from cpgjax.study import spec as study_spec


def _study_folder() -> pathlib.Path:
    """Where the paper's study files are: the source checkout's ``studies/`` (a checkout or an editable install),
    else where a wheel installs them (pyproject.toml's data-files: ``<environment>/share/cpgjax/studies``)."""
    checkout = pathlib.Path(__file__).resolve().parents[2] / "studies"
    return checkout if checkout.is_dir() else pathlib.Path(sys.prefix) / "share" / "cpgjax" / "studies"


STUDY_FOLDER = _study_folder()  # the paper's studies, one file each


class StudyRun(NamedTuple):
    """What a study run left: its table (the text of table.md; a dry run's plan), its folder, and the engine's result
    (None after a dry run, and in every process of a multi-process run but the first)."""

    table: str
    out: pathlib.Path
    result: Any  # ablation.StudyResult (transfer: the arms' results by arm name)


BEYOND_THE_PAPER = ("gaits", "rough_terrain")
"""The shipped studies that go past the paper, its future work (docs/REPRODUCTION.md "Beyond the paper")."""


def shipped_studies() -> list[str]:
    """The names of the studies shipped in ``studies/`` (each ``<name>.toml``)."""
    return sorted(p.stem for p in STUDY_FOLDER.glob(f"*{study_spec.STUDY_FILE_SUFFIX}"))


def quick_sizes() -> tuple[list[int], list[int]]:
    """The seeds and the trials the shipped studies' ``[quick]`` tables give (sorted, distinct), read from the files
    without running their checks (``study --help`` states them)."""
    seeds, trials = set(), set()
    for name in shipped_studies():
        data = tomllib.loads((STUDY_FOLDER / f"{name}{study_spec.STUDY_FILE_SUFFIX}").read_text())
        quick = data.get("quick", {})
        seeds.add(quick.get("seeds", data.get("seeds")))
        trials.add(quick.get("trials", data.get("trials")))
    return sorted(seeds - {None}), sorted(trials - {None})


def paper_studies() -> list[str]:
    """The shipped studies that reproduce the paper (all but :data:`BEYOND_THE_PAPER`)."""
    return [name for name in shipped_studies() if name not in BEYOND_THE_PAPER]


def find(name_or_path) -> pathlib.Path:
    """The study file of a shipped study's name (``studies/<name>.toml``) or of a path.

    Raises:
      StudyError: no such file (the message lists the shipped studies).
    """
    text = str(name_or_path)
    path = pathlib.Path(text)
    if path.suffix == study_spec.STUDY_FILE_SUFFIX or "/" in text:
        if not path.is_file():
            raise study_spec.StudyError(f"study file {path} does not exist")
        return path
    if (STUDY_FOLDER / f"{text}{study_spec.STUDY_FILE_SUFFIX}").is_file():
        return STUDY_FOLDER / f"{text}{study_spec.STUDY_FILE_SUFFIX}"
    raise study_spec.StudyError(f"unknown study {text!r}: the paper's studies are {', '.join(paper_studies())}, the "
                                f"ones beyond it {', '.join(BEYOND_THE_PAPER)}; or give a study file "
                                f"(PATH{study_spec.STUDY_FILE_SUFFIX}, docs/studies.md)")


def read(name_or_path, **overrides) -> study_spec.StudyFile:
    """The study file of ``name_or_path`` (:func:`find`) read with ``cpgjax study``'s overrides
    (:func:`cpgjax.study.spec.read`), and its report's name checked.

    Raises:
      StudyError: the file, the key and what is allowed.
    """
    study = study_spec.read(find(name_or_path), **overrides)
    known = (*registry.REPORTS, transfer.NAME)
    if study.report and study.report not in known:
        raise study_spec.StudyError(f"{study.path}: report: {study.report!r} is not a report; allowed: "
                                    f"{', '.join(known)}, or leave it out for the generic report")
    if (study.report == transfer.NAME) != bool(study.arms):
        raise study_spec.StudyError(f"{study.path}: a [transfer] table with its arms goes with report = "
                                    f"{transfer.NAME!r}, and only with it")
    if study.arms and (overrides.get("physics") is not None or overrides.get("max_trials") is not None):
        raise study_spec.StudyError(f"{study.path}: its arms set their own physics and are not extended: drop "
                                    "--physics and --max-trials")
    return study


def notify_stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def write_outputs(result, out: pathlib.Path, backend: str, report: registry.Report | None = None,
                  command: str | None = None, notify: Callable[[str], None] = notify_stderr,
                  metadata: dict | None = None) -> str:
    """Every file of a finished study; returns the table text. The trial table, the metadata and each group's best
    gait (``best_params/<group>.json``, ``gaits.save_best_gaits``; a line to ``notify`` for a group none of whose
    trials walked) first (they cannot fail but for the disk), then table.md (``report``'s text; by default the
    generic report's), then the study's figures (the ablation's table then gains the attitude rows its figure
    walks; ``registry.notes`` under the tables say how to read their figures), the recording, and last the gaits'
    figures and videos (``best_<group>.mp4``, :mod:`cpgjax.studies.video`), with a line to ``notify`` per video,
    or one saying why there is none.

    Raises:
      study_io.OutputError: a file could not be written; the message names it and what was kept.
    """
    out.mkdir(parents=True, exist_ok=True)
    with study_io.writing(out, outputs.TRIALS):
        study_io.write_trials(result, out / outputs.TRIALS)
    with study_io.writing(out, outputs.METADATA):
        study_io.write_metadata(result, out / outputs.METADATA, metadata, command=command)
    with study_io.writing(out, f"{study_io.BEST_PARAMS}/"):
        gaits = study_gaits.save_best_gaits(out, result)
    for gait in gaits:
        if not gait.walked:
            notify(f"best gait of {gait.group}: no trial of the group walked (every one fell or stood still); its "
                   "file holds the best of its final phase")
    study = report or generic.report_for()
    report = study.report(result, backend)
    tail = (f"{registry.safety_summary(result)}{registry.notes(result)}\nRun: "
            f"{study_figures.run_line(result, study_io.run_figures(result))}\n")
    with study_io.writing(out, study_io.TABLE):
        text = f"# {result.spec.name}\n\n{report}{tail}"
        (out / study_io.TABLE).write_text(text)
    with study_io.writing(out, "the study's figures"):
        extra = study.figures(result, out, backend)
        study_figures.optimization_progress(out / "optimization_progress.png", result,
                                            list(study_gaits.group_names(result)))
    if extra:
        with study_io.writing(out, study_io.TABLE):
            text = f"# {result.spec.name}\n\n{report}{extra}{tail}"
            (out / study_io.TABLE).write_text(text)
    logs = study_gaits.gait_rollouts(gaits, backend)
    with study_io.writing(out, study_io.RECORDING):
        study_io.write_recording(result, out / study_io.RECORDING, [
            study_scene.Rollout(log=log, group=g.group, controller=g.controller,
                                seed=result.labels[g.instance]["seed"], condition=g.condition)
            for g, log in zip(gaits, logs, strict=True)])
    with study_io.writing(out, "the best gaits' figures and videos"):
        study_figures.attitude_by_group(out / "attitude_best_gaits.png", gaits, logs)
        filmed = study_video.write_videos(out, gaits, logs, notify)
        # filmed: the videos written, for a prefix of the gaits (none where no OpenGL backend works)
        strips = {g.group: list(info["strip"]) for g, info in zip(gaits, filmed, strict=False)}
        study_figures.summary(out / study_figures.SUMMARY, result, text, gaits, strips,
                              study.paper_marks(result))
    return text


def run_spec(spec: study_spec.StudySpec, out=None, *, report: registry.Report | None = None, backend: str = "auto",
             resume: bool = False, overwrite: bool = False, progress=None, command: str | None = None,
             notify: Callable[[str], None] | None = None, dry_run: bool = False,
             metadata: dict | None = None) -> StudyRun:
    """Run (or resume) the study ``spec`` into ``out`` (default ``results/<spec.name>``) and write its outputs.

    Args:
      report: the table's report (default: the generic one of ``cpgjax.studies.generic``).
      backend: the simulation backend (``cpgjax.sim.backends``).
      resume, overwrite: a non-empty ``out`` needs one of them (``cpgjax.study.files.open_run``).
      progress: called after every trial (``cpgjax.ablation.Engine.run``).
      command: the command line, recorded in ``metadata.json``.
      notify: gets the line where a resume starts and one per video.
      dry_run: every check, then the run's plan as the text; nothing computed or written.
      metadata: more keys for ``metadata.json`` (a study file's path and text).

    Raises:
      StudyError: the study or the folder cannot run (before any compute).
      OutputError: a file could not be written (the checkpoint keeps every trial).
    """
    study_spec.validate(spec)
    out = study_io.output_folder(spec.name, out)
    backend_name = backends.resolve_backend(backend)
    start = study_io.open_run(out, spec, backend_name, resume=resume, overwrite=overwrite, dry_run=dry_run)
    if dry_run:
        return StudyRun(study_io.run_plan(spec, out, backend_name, start), out, None)
    if start and notify is not None and jax.process_index() == 0:
        notify(study_io.resume_notice(out, start, spec.num_trials))
    engine = ablation.Engine(spec, backend=backend)
    result = engine.run(out, resume=resume, progress=progress)
    if jax.process_index() > 0:  # one process writes the study's files (docs/scaling.md)
        return StudyRun(f"process {jax.process_index()}: instances {result.rows[0]}–{result.rows[1] - 1} done", out,
                        None)
    return StudyRun(write_outputs(result, out, engine.backend_name, report, command, notify or notify_stderr,
                                  metadata), out, result)


def report_of(study: study_spec.StudyFile) -> registry.Report:
    """A study file's report: the hand-written one it names, or the generic one with its comparisons."""
    return registry.REPORTS.get(study.report) or generic.report_for(study.contrasts, study.paper, study.description)


def run_file(study: study_spec.StudyFile, out=None, **options) -> StudyRun:
    """Run what the study file ``study`` (:func:`read`) defines, with its report; ``options`` as :func:`run_spec`'s
    (without ``report``). A study with arms (the transfer study) runs each arm in its own folder below ``out``."""
    if study.arms:
        return StudyRun(*transfer.run(study, out=out, notify=options.pop("notify", None) or notify_stderr,
                                      **options), None)
    return run_spec(study.spec, out, report=report_of(study), metadata=study.metadata(), **options)
