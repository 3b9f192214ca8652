"""Running a study of any kind into a folder of results (docs/studies.md "One protocol", docs/outputs.md).

Every study is a ``registry.Study``: the engine's runs (its specs), one evaluate step (the only one that simulates
after the engine), a pure report and its files. :func:`run` runs any of them: a study file's (:func:`of_file`: a
hand-written report of ``registry.REPORTS``, the generic one of ``cpgjax.studies.generic``, or the transfer study's
arms), a ``StudySpec``'s (:func:`one_folder`) and ``cpgjax optimize``'s (``cpgjax.studies.optimize``).
:func:`run_spec` and :func:`run_file` are the Python API's shorthands; :func:`find` turns a shipped study's name or a
file's path into the file.
"""

from __future__ import annotations

import pathlib
import sys
import tomllib
from collections.abc import Callable
from typing import NamedTuple

import jax

from cpgjax import ablation, outputs
from cpgjax.sim import backends
from cpgjax.studies import figures as study_figures
from cpgjax.studies import gaits as study_gaits
from cpgjax.studies import generic, registry, transfer
from cpgjax.studies import options as study_options
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
    result: ablation.StudyResult | dict[str, ablation.StudyResult] | None  # several runs: by run name


BEYOND_THE_PAPER = ("gaits", "rough_terrain")
DEMO_STUDY = "controller_ablation"  # what ``cpgjax demo`` runs (its --quick variant)
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
    raise study_spec.StudyError(
        f"unknown study {text!r}: the paper's studies are {', '.join(paper_studies())}, the "
        f"ones beyond it {', '.join(BEYOND_THE_PAPER)}; or give a study file "
        f"(PATH{study_spec.STUDY_FILE_SUFFIX}, docs/studies.md)"
    )


def read(name_or_path, **overrides) -> study_spec.StudyFile:
    """The study file of ``name_or_path`` (:func:`find`) read with ``cpgjax study``'s overrides
    (:func:`cpgjax.study.spec.read`), and its report's name checked.

    Raises:
      StudyError: the file, the key and what is allowed.
    """
    study = study_spec.read(find(name_or_path), **overrides)
    known = (*registry.REPORTS, transfer.NAME)
    if study.report and study.report not in known:
        raise study_spec.StudyError(
            f"{study.path}: report: {study.report!r} is not a report; allowed: "
            f"{', '.join(known)}, or leave it out for the generic report"
        )
    if (study.report == transfer.NAME) != bool(study.arms):
        raise study_spec.StudyError(
            f"{study.path}: a [transfer] table with its arms goes with report = {transfer.NAME!r}, and only with it"
        )
    if study.arms and (overrides.get("physics") is not None or overrides.get("max_trials") is not None):
        raise study_spec.StudyError(
            f"{study.path}: its arms set their own physics and are not extended: drop --physics and --max-trials"
        )
    return study


def notify_stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def write_outputs(
    result: ablation.StudyResult,
    evaluation: registry.Evaluation,
    report_text: str,
    out: pathlib.Path,
    report: registry.Report,
    notify: Callable[[str], None] = notify_stderr,
) -> str:
    """The files of a finished one-folder study after its trial table and metadata; returns the table text. Each
    group's best gait (``best_params/<group>.json``, ``gaits.save_gaits``; a line to ``notify`` for a group none of
    whose trials walked) first, then table.md (``report_text``), then the study's figures (the ablation's table then
    gains the attitude rows of its figure; ``registry.notes`` under the tables say how to read their figures), the
    recording, and last the gaits' figures and videos (``best_<group>.mp4``, :mod:`cpgjax.studies.video`), with a
    line to ``notify`` per video, or one saying why there is none. ``evaluation`` holds the best gaits (``gaits``)
    and their per-step logs (``gait_logs``), and what ``report`` walked (:func:`one_folder`).

    Raises:
      study_io.OutputError: a file could not be written; the message names it and what was kept.
    """
    gaits, logs = evaluation["gaits"], evaluation["gait_logs"]
    with study_io.writing(out, f"{study_io.BEST_PARAMS}/"):
        study_gaits.save_gaits(out, result, gaits)
    for gait in gaits:
        if not gait.walked:
            notify(
                f"best gait of {gait.group}: no trial of the group walked (every one fell or stood still); its "
                "file holds the best of its final phase"
            )
    tail = (
        f"{registry.safety_summary(result)}{registry.notes(result)}\nRun: "
        f"{study_figures.run_line(result, study_io.run_figures(result))}\n"
    )
    with study_io.writing(out, study_io.TABLE):
        text = f"# {result.spec.name}\n\n{report_text}{tail}"
        (out / study_io.TABLE).write_text(text)
    with study_io.writing(out, "the study's figures"):
        extra = report.figures(result, evaluation, out)
        study_figures.optimization_progress(
            out / "optimization_progress.png", result, list(study_gaits.group_names(result))
        )
    if extra:
        with study_io.writing(out, study_io.TABLE):
            text = f"# {result.spec.name}\n\n{report_text}{extra}{tail}"
            (out / study_io.TABLE).write_text(text)
    with study_io.writing(out, study_io.RECORDING):
        study_io.write_recording(
            result,
            out / study_io.RECORDING,
            [
                study_scene.Rollout(
                    log=log,
                    group=g.group,
                    controller=g.controller,
                    seed=result.labels[g.instance]["seed"],
                    condition=g.condition,
                )
                for g, log in zip(gaits, logs, strict=True)
            ],
        )
    with study_io.writing(out, "the best gaits' figures and videos"):
        study_figures.attitude_by_group(out / "attitude_best_gaits.png", gaits, logs)
        filmed = study_video.write_videos(out, gaits, logs, notify)
        # filmed: the videos written, for a prefix of the gaits (none where no OpenGL backend works)
        strips = {g.group: list(info["strip"]) for g, info in zip(gaits, filmed, strict=False)}
        study_figures.summary(out / study_figures.SUMMARY, result, text, gaits, strips, report.paper_marks(result))
    return text


def one_folder(
    spec: study_spec.StudySpec, report: registry.Report | None = None, metadata: dict | None = None
) -> registry.Study:
    """The study of one engine run of ``spec`` with ``report`` (default: the generic one), written into one folder
    (:func:`write_outputs`). Its evaluate step walks each group's best gait (for the recording, the figures and
    the videos) and what ``report.evaluate`` asks for."""
    report = report or generic.report_for()

    def evaluate(results, backend: str) -> registry.Evaluation:
        result = registry.only(results)
        gaits = study_gaits.best_gaits(result)
        return {
            "gaits": gaits,
            "gait_logs": study_gaits.gait_rollouts(gaits, backend),
            **report.evaluate(result, backend),
        }

    return registry.Study(
        spec.name,
        (spec,),
        evaluate,
        lambda results, evaluation: report.report(registry.only(results), evaluation),
        lambda results, evaluation, text, out, notify: write_outputs(
            registry.only(results), evaluation, text, out, report, notify
        ),
        metadata,
    )


def of_file(study: study_spec.StudyFile) -> registry.Study:
    """What the study file ``study`` (:func:`read`) defines: the transfer study of its arms, or one folder with the
    hand-written report it names or the generic one with its comparisons."""
    if study.arms:
        return transfer.study(study)
    report = registry.REPORTS.get(study.report) or generic.report_for(study.contrasts, study.paper, study.description)
    return one_folder(study.spec, report, study.metadata())


def check_processes(study: registry.Study, options: study_options.StudyOptions) -> None:
    """Whether ``study`` can run as ``options`` ask: one of several processes (``--processes``, ``--distributed``)
    only where it is one engine run.

    Raises:
      StudyError: several runs (a transfer study's arms) with processes.
    """
    if len(study.specs) > 1 and (options.processes is not None or options.distributed):
        raise study_spec.StudyError(
            f"{study.name} runs its arms one after another in one process: drop --processes / --distributed"
        )


def resumable_folder(study: registry.Study, out: pathlib.Path) -> pathlib.Path | None:
    """The folder a stopped run of ``study`` into ``out`` resumes from: ``out``, or for several runs the last of
    their folders with a checkpoint (None: none has one)."""
    if len(study.specs) == 1:
        return out
    return next(
        (folder for folder in reversed(folders(study, out).values()) if study_io.checkpoint_files(folder)), None
    )


def run(study: registry.Study, options: study_options.RunOptions | None = None) -> StudyRun:
    """Run (or resume) ``study`` and write its files (docs/outputs.md): every engine run into its folder (``out``,
    default ``results/<name>``; several runs each in ``out/<run name>``), each run's trial table and metadata, then
    the study's evaluate step, its report and its files (``study.write``).

    A resume (``options.resume``) continues a run from its checkpoint; of several runs, those with a checkpoint
    (the others start). A dry run makes every check and returns the runs' plans: nothing computed or written. In a
    multi-process run (docs/scaling.md) only the first process writes files.

    Raises:
      StudyError: the study or a folder cannot run (before any compute).
      OutputError: a file could not be written (the checkpoints keep every trial).
    """
    options = options or study_options.RunOptions()
    for spec in study.specs:
        study_spec.validate(spec)
    out = study_io.output_folder(study.name, options.out)
    backend_name = backends.resolve_backend(options.backend)
    notify = options.notify or notify_stderr
    several, run_folders = len(study.specs) > 1, folders(study, out)
    resumed = {spec.name: options.resume for spec in study.specs}
    if several:
        if options.resume:
            resumed = {name: (folder / study_io.CHECKPOINT).exists() for name, folder in run_folders.items()}
            if not any(resumed.values()):
                raise study_spec.StudyError(
                    f"--resume: no arm of {out} has a checkpoint; run without --resume to start"
                )
        study_io.claim_folder(out, overwrite=options.overwrite, resume=options.resume, dry_run=options.dry_run)
    plans = []
    for spec in study.specs:
        folder = run_folders[spec.name]
        start = study_io.open_run(
            folder, spec, backend_name, resume=resumed[spec.name], overwrite=options.overwrite, dry_run=options.dry_run
        )
        if options.dry_run:
            plans.append(study_io.run_plan(spec, folder, backend_name, start))
        elif start and jax.process_index() == 0:
            notify(study_io.resume_notice(folder, start, spec.num_trials))
    if options.dry_run:
        return StudyRun("\n".join([*plans, study.plan] if study.plan else plans), out, None)
    results = {}
    for spec in study.specs:
        engine = ablation.Engine(spec, backend=options.backend)
        results[spec.name] = engine.run(run_folders[spec.name], resume=resumed[spec.name], progress=options.progress)
    if jax.process_index() > 0:  # one process writes the study's files (docs/scaling.md)
        rows = registry.only(results).rows
        return StudyRun(f"process {jax.process_index()}: instances {rows[0]}–{rows[1] - 1} done", out, None)
    text = write_study(study, results, out, backend_name, notify, options.command)
    return StudyRun(text, out, results if several else registry.only(results))


def folders(study: registry.Study, out: pathlib.Path) -> dict[str, pathlib.Path]:
    """Each engine run's folder by its name: ``out`` for one run, ``out/<run name>`` for each of several."""
    several = len(study.specs) > 1
    return {spec.name: out / spec.name if several else out for spec in study.specs}


def write_study(
    study: registry.Study,
    results: dict[str, ablation.StudyResult],
    out: pathlib.Path,
    backend: str,
    notify: Callable[[str], None] = notify_stderr,
    command: str | None = None,
) -> str:
    """Every file of ``study``'s finished runs ``results`` into ``out``: each run's trial table and metadata (with
    ``command``, the command line) first, then the study's evaluate step (on ``backend``), its report and its files;
    returns the table text.

    Raises:
      study_io.OutputError: a file could not be written; the message names it and what was kept.
    """
    for name, folder in folders(study, out).items():
        with study_io.writing(folder, outputs.TRIALS):
            study_io.write_trials(results[name], folder / outputs.TRIALS)
        with study_io.writing(folder, outputs.METADATA):
            study_io.write_metadata(
                results[name], folder / outputs.METADATA, study.metadata, command=command, written_by=study.written_by
            )
    evaluation = study.evaluate(results, backend)
    return study.write(results, evaluation, study.report(results, evaluation), out, notify)


def run_spec(
    spec: study_spec.StudySpec, options: study_options.RunOptions | None = None, report: registry.Report | None = None
) -> StudyRun:
    """Run the study ``spec`` with ``report`` (default: the generic one) into one folder (:func:`one_folder`,
    :func:`run`): the Python API's study of a ``StudySpec``."""
    return run(one_folder(spec, report), options)


def run_file(study: study_spec.StudyFile, options: study_options.RunOptions | None = None) -> StudyRun:
    """Run what the study file ``study`` (:func:`read`) defines (:func:`of_file`, :func:`run`)."""
    return run(of_file(study), options)
