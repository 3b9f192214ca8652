"""The typed options of a study run (cpgjax/studies/options.py): each rule checked once, on construction, with the
one line that names the option, its value and what is allowed; and the command line refusing through them before any
compute."""

import os

import pytest

from cpgjax import cli
from cpgjax.studies import driver as study_driver
from cpgjax.studies import options as study_options
from cpgjax.study import spec as study_spec
from cpgjax.trial import limits


def _refused(match: str, kind=study_options.StudyOptions, **given) -> None:
    with pytest.raises(study_spec.StudyError, match=match):
        kind(**given)


def test_resume_and_overwrite_exclude_each_other():
    _refused("--resume and --overwrite exclude each other", study_options.RunOptions, resume=True, overwrite=True)
    assert study_options.RunOptions(resume=True).resume and study_options.RunOptions(overwrite=True).overwrite


def test_seeds_between_1_and_the_most_seeds():
    _refused(r"--seeds = 0: need an integer >= 1", seeds=0)
    _refused(rf"--seeds = {limits.MAX_SEEDS + 1}: need an integer <= {limits.MAX_SEEDS}", seeds=limits.MAX_SEEDS + 1)
    assert study_options.StudyOptions(seeds=limits.MAX_SEEDS).seeds == limits.MAX_SEEDS


def test_a_studys_trials_and_max_trials_in_their_range():
    low = limits.MIN_STUDY_TRIALS
    for option, key in (("--trials", "trials"), ("--max-trials", "max_trials")):
        _refused(rf"{option} = {low - 1}: need an integer >= {low}", **{key: low - 1})
        _refused(
            rf"{option} = {limits.MAX_TRIALS + 1}: need an integer <= {limits.MAX_TRIALS}",
            **{key: limits.MAX_TRIALS + 1},
        )
        assert getattr(study_options.StudyOptions(**{key: low}), key) == low


def test_processes_within_this_machines_cpus_and_not_with_distributed():
    cpus = os.cpu_count() or 1
    _refused(rf"--processes 0 is outside the allowed range 1 … {cpus}", processes=0)
    _refused(rf"--processes {cpus + 1} is outside the allowed range 1 … {cpus}", processes=cpus + 1)
    _refused("--processes and --distributed exclude each other", processes=1, distributed=True)


def test_an_optimizations_trials_and_max_trials():
    kind = study_options.OptimizeOptions
    _refused(
        rf"--trials = {limits.MIN_TRIALS - 1}: need an integer >= {limits.MIN_TRIALS}",
        kind,
        trials=limits.MIN_TRIALS - 1,
    )
    _refused(r"--max-trials 4: need at least --trials \(8\)", kind, trials=8, max_trials=4)
    spec = kind(trials=8, max_trials=12, friction=0.9, controller="tegotae").spec()
    assert (spec.num_trials, spec.max_trials, spec.friction, spec.controllers) == (8, 12, (0.9,), ("tegotae",))


def test_the_overrides_are_the_study_file_readers_keywords():
    given = study_options.StudyOptions(
        quick=True, seeds=3, trials=12, physics="soft", safe=True, max_trials=20, startup="lean_ramp", gaits=("trot",)
    )
    assert given.overrides() == dict(
        quick=True, seeds=3, trials=12, physics="soft", safe=True, max_trials=20, startup="lean_ramp", gaits=("trot",)
    )
    study = study_spec.read(study_driver.find("friction"), **given.overrides())
    assert (len(study.spec.seeds), study.spec.num_trials, study.spec.max_trials) == (3, 12, 20)


@pytest.mark.parametrize(
    "argv, said",
    [
        (["study", "friction", "--trials", "3"], "cpgjax study: --trials = 3: need an integer >= "),
        (["study", "friction", "--seeds", "0"], "cpgjax study: --seeds = 0: need an integer >= 1"),
        (["study", "friction", "--processes", "0"], "cpgjax study: --processes 0 is outside the allowed range 1 … "),
        (["study", "friction", "--processes", "1", "--distributed"], "cpgjax study: --processes and --distributed"),
        (["optimize", "--trials", "8", "--max-trials", "4"], "cpgjax optimize: --max-trials 4: need at least --trials"),
    ],
)
def test_the_command_line_refuses_through_the_options(argv, said, capsys, tmp_path):
    assert cli.main([*argv, "--out", str(tmp_path / "never")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(said) and err.count("\n") == 1 and not (tmp_path / "never").exists()
