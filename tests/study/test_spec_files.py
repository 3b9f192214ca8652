"""Study files (docs/studies.md): the paper's studies as files give the runs of the code they replaced, a bad file is
refused in one line naming the file and the key, a study in Python and the same study as a file give the same
outputs, the template and `--print`, and the generic report against references computed here.
"""

import dataclasses
import hashlib
import json
import pathlib
import types

import numpy as np
import pyarrow
import pytest
from scipy import stats as sp

from cpgjax import ablation, cli
from cpgjax.studies import driver as study_driver
from cpgjax.studies import generic, transfer
from cpgjax.studies import options as study_options
from cpgjax.study import files as study_io
from cpgjax.study import spec as study_spec

DATA = pathlib.Path(__file__).resolve().parents[1] / "data"
PAPER_STUDIES = (
    "controller_ablation",
    "friction",
    "load_adaptation",
    "multi_velocity",
    "paper_hardware",
    "slope_adaptation",
    "transfer",
)


def _nameless(spec: study_spec.StudySpec) -> study_spec.StudySpec:
    """The spec with its schedules' file names removed: the code the files replaced had none."""
    return dataclasses.replace(spec, schedules=tuple(s._replace(name="") for s in spec.schedules))


def test_the_paper_studies_are_the_files_of_the_studies_folder():
    assert tuple(study_driver.paper_studies()) == PAPER_STUDIES
    assert study_driver.shipped_studies() == sorted(PAPER_STUDIES + study_driver.BEYOND_THE_PAPER)
    assert study_driver.find("friction") == study_driver.STUDY_FOLDER / "friction.toml"


def test_each_paper_study_file_defines_the_study_of_the_code_it_replaced():
    """The specs of 54cbbd9's registry (its `make_spec` and `transfer.specs`) with the default options, --quick,
    --seeds and --trials, recorded as their repr before the definitions moved into files, against each file's. The
    hardware study's --trials runs are left out: its file's changes scale by rounding (the rule of every file), where
    the code's k·⌊n/4⌋ rounded down (a 30-trial run changes its target at 8, 15 and 22, not 7, 14 and 21)."""
    recorded = json.loads((DATA / "paper_study_specs.json").read_text())["specs"]
    assert {key.split(" ")[0] for key in recorded} == set(PAPER_STUDIES)
    for key, want in recorded.items():
        name, options = key.split(" ", 1)
        options = json.loads(options)
        if isinstance(want, str):  # the code refused these options
            with pytest.raises(study_spec.StudyError):
                study_driver.read(name, **options)
            continue
        study = study_driver.read(name, **options)
        specs = transfer.specs(study) if study.arms else [study.spec]
        later = (
            ", startup=None, switches=None, gaits=None, terrain_amplitude_m=None, terrain_seed=None, "
            "foot_friction=None)"
        )  # added since
        assert [repr(_nameless(s)).replace(later, ")") for s in specs] == want, key


def _sha256(path: pathlib.Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.mark.slow
def test_each_quick_paper_study_writes_the_trials_of_the_reproductions_commit(tmp_path):
    """Each paper study run from its file at --quick writes a trials.parquet byte for byte the one written at the
    commit of the reproduction's runs (a03d360, `cpgjax study NAME --quick`; docs/REPRODUCTION.md): a change that
    moves any trial of the paper studies' default path shows here, and one that must not (the switches, a new
    profile) is checked not to. The parquet writer records its version in the file, so this compares files written
    by the same pyarrow."""
    recorded = json.loads((DATA / "quick_trials_sha256.json").read_text())
    if recorded["pyarrow"] != pyarrow.__version__:
        pytest.fail(
            f"the recorded files were written by pyarrow {recorded['pyarrow']}, this is "
            f"{pyarrow.__version__}: record them again at {recorded['commit']} with this pyarrow"
        )
    found = {}
    for name in PAPER_STUDIES:
        study = study_driver.read(name, quick=True)
        specs = transfer.specs(study) if study.arms else [study.spec]
        for spec in specs:
            key = f"{name}/{spec.name}" if study.arms else name
            out = tmp_path / key
            result = ablation.Engine(spec, backend="auto").run(out)
            found[key] = _sha256(study_io.write_trials(result, out / "trials.parquet"))
    assert found == recorded["sha256"]


# ----------------------------------------------------------------------------------------------- bad files

GOOD = """name = "sweep"
trials = 10
seeds = 2
group_by = ["controller", "friction"]

[grid]
controllers = ["open_loop", "tegotae"]
friction = [0.4, 0.8]
payload_kg = [10.0]

[[schedules]]
name = "load"
changes = [{ trial = 5, payload_kg = 12.0 }]
"""


@pytest.mark.parametrize(
    "edit, key, allowed",
    [
        (("seeds = 2", "seeds = 2\nseed = 3"), "unknown key 'seed' (did you mean 'seeds'?)", "allowed: name"),
        (("friction = [0.4, 0.8]", "frction = [0.4, 0.8]"), "unknown key 'grid.frction'", "allowed in grid"),
        (("trials = 10", 'trials = "10"'), "trials: need an integer, got a string", ""),
        (
            ("friction = [0.4, 0.8]", "friction = [0.4, 0.8, 2.0]"),
            "grid.friction[2] = 2.0 is outside the allowed range",
            "[0.1, 1.5]",
        ),
        (("friction = [0.4, 0.8]", "friction = [0.4, true]"), "grid.friction[1]: need a number, got a boolean", ""),
        (
            ("trial = 5, payload_kg", "trial = 10, payload_kg"),
            "schedules[0].changes[0].trial: 10 is outside the allowed",
            "trials are numbered 0 … 9",
        ),
        (
            ("trial = 5, payload_kg = 12.0", "trial = 5, payload_kg = 25.0"),
            "schedules[0].changes[0].payload_kg = 25.0 is outside the allowed range",
            "[0, 20]",
        ),
        (("friction = [0.4, 0.8]", "friction = []"), "grid.friction: empty", "at least one value"),
        (("friction = [0.4, 0.8]", "friction = [0.4, 0.4]"), "grid.friction[1]: 0.4 is already in the axis", ""),
        (
            ('group_by = ["controller", "friction"]', 'group_by = ["controller", "mass"]'),
            "group_by[1]: 'mass' is not allowed",
            "allowed: controller, gait, seed, friction",
        ),
        (
            ('controllers = ["open_loop", "tegotae"]', 'controllers = ["open_loop", "cpg"]'),
            "grid.controllers[1]: 'cpg' is not allowed",
            "open_loop, vmc, tegotae, vmc_tegotae",
        ),
        (
            (
                "changes = [{ trial = 5, payload_kg = 12.0 }]",
                "phases = [{ trials = 4 }, { trials = 5, payload_kg = 12.0 }]",
            ),
            "schedules[0].phases: the phases' trials add up to 9, the study has 10",
            "",
        ),
        (('name = "load"', 'name = "a load"'), "schedules[0].name: 'a load': need a word", "names files"),
        (("seeds = 2", "seeds = 2\n[comparisons]"), "comparisons: need a list", ""),
        (
            ("seeds = 2", 'comparisons = [{ axis = "friction", a = 0.4, b = 0.5 }]'),
            "comparisons[0].b: 0.5 is not a value of the study's friction axis",
            "allowed: 0.4, 0.8",
        ),
        (("seeds = 2", 'seeds = 2\nreport = "mine"'), "report: 'mine' is not a report", "controller_ablation"),
        (("[grid]", "[grid"), "not valid TOML", ""),
    ],
)
def test_a_bad_study_file_is_refused_in_one_line_before_anything_runs(
    edit, key, allowed, tmp_path, capsys, monkeypatch
):
    """One line naming the file, the key's path and what is allowed; exit 2; no engine built, no folder written."""
    old, new = edit
    assert old in GOOD
    path = tmp_path / "sweep.toml"
    path.write_text(GOOD.replace(old, new, 1))
    monkeypatch.setattr(ablation, "Engine", lambda *a, **k: pytest.fail("an engine was built"))
    out = tmp_path / "out"
    assert cli.main(["study", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"cpgjax study: {path}: ") and err.count("\n") == 1 and "Traceback" not in err, err
    assert key in err and allowed in err, err
    assert not out.exists()


def test_the_good_file_runs_its_checks(tmp_path, capsys):
    path = tmp_path / "sweep.toml"
    path.write_text(GOOD)
    assert cli.main(["study", str(path), "--dry-run", "--out", str(tmp_path / "out")]) == 0
    assert "sweep: 8 instances (2 controllers, 2 seeds, 2 friction) × 10 trials" in capsys.readouterr().out
    assert not (tmp_path / "out").exists()


def test_the_command_line_overrides_mean_what_they_mean_for_a_paper_study(tmp_path):
    """--seeds, --trials (with the changes scaled: round(t·n/N)), --quick, --safe, --physics, --max-trials."""
    path = tmp_path / "sweep.toml"
    path.write_text(GOOD + "\n[quick]\ntrials = 8\nseeds = 1\n")
    spec = study_spec.load(path, seeds=3, trials=30, safe=True, physics="go1", max_trials=40)
    assert spec.seeds == (0, 1, 2) and spec.num_trials == 30 and spec.safe and spec.physics == ("go1",)
    assert spec.max_trials == 40 and spec.schedules[0].changes == (study_spec.Change(15, "payload_kg", 12.0),)
    quick = study_spec.load(path, quick=True)
    assert quick.seeds == (0,) and quick.num_trials == 8
    assert quick.schedules[0].changes == (study_spec.Change(4, "payload_kg", 12.0),)  # round(5 · 8 / 10)


def test_phases_keep_fixed_lengths_and_share_the_rest():
    """Phases of 40, 20, 20 (scaled) and 3, 12 (fixed) trials in runs of 95 and 51: the scaled ones share n − 15 in
    proportion, by round(cumulative · (n − 15) / 80)."""
    text = """name = "p"
trials = 95
[[schedules]]
name = "s"
phases = [{ trials = 40 }, { trials = 20, slope_deg = 10.0 }, { trials = 20, slope_deg = 12.5 },
          { trials = 3, fixed = true, inference = true }, { trials = 12, fixed = true, ramp = true }]
[ramp]
start_deg = 10.0
end_deg = 15.0
length_m = 5.0
"""
    for n, starts in ((95, [40, 60, 80, 83]), (51, [18, 27, 36, 39])):
        changes = study_spec.read(_write(text), trials=n).spec.schedules[0].changes
        assert [c.trial for c in changes] == starts
        assert [c.field for c in changes] == ["slope_deg", "slope_deg", "inference", "ramp"]


def _write(text: str) -> pathlib.Path:
    import tempfile

    path = pathlib.Path(tempfile.mkdtemp()) / "study.toml"
    path.write_text(text)
    return path


# ----------------------------------------------------------------------------------------------- template, print


def test_the_template_lists_every_key_runs_as_written_and_is_not_overwritten(tmp_path, capsys):
    path = tmp_path / "mine.toml"
    assert cli.main(["study", "--template", str(path)]) == 0
    text = path.read_text()
    for key in (
        *study_spec.TOP_KEYS,
        *study_spec.GRID_AXES,
        *study_spec.Randomization._fields,
        *study_spec.Ramp._fields,
        "transition_s",
        "steady_s",
        "phases",
        "changes",
        "fixed",
    ):
        if key != "transfer":  # the transfer report's own table
            assert f"{key} =" in text or f"[{key}]" in text or f"{key}: " in text, key
    spec = study_spec.load(path)
    assert spec == study_spec.StudySpec("my_study", seeds=tuple(range(5)))  # StudySpec's defaults, 5 seeds
    capsys.readouterr()
    assert cli.main(["study", "--template", str(path)]) == 2  # exists: refused without --overwrite
    assert "exists" in capsys.readouterr().err


def test_print_gives_a_paper_study_file_to_copy(capsys):
    assert cli.main(["study", "load_adaptation", "--print"]) == 0
    assert capsys.readouterr().out == (study_driver.STUDY_FOLDER / "load_adaptation.toml").read_text()


# ----------------------------------------------------------------------------------------------- Python = file

TINY = """name = "tiny_file"
trials = 3
seeds = [0, 1]
group_by = ["controller"]

[grid]
controllers = ["open_loop", "tegotae"]
physics = ["paper"]

[trial]
transition_s = 0.1
steady_s = 0.2
"""


@pytest.mark.slow
def test_a_study_in_python_and_the_same_study_as_a_file_write_the_same_files(tmp_path):
    from cpgjax.trial import protocol

    path = tmp_path / "tiny.toml"
    path.write_text(TINY)
    python = study_spec.StudySpec(
        "tiny_file",
        num_trials=3,
        seeds=(0, 1),
        controllers=("open_loop", "tegotae"),
        physics=("paper",),
        trial=protocol.TrialConfig(transition_steps=100, steady_steps=200),
    )
    assert study_spec.load(path) == python

    def options(out):
        return study_options.RunOptions(out=out, backend="native", notify=lambda line: None)

    a = study_driver.run_spec(python, options(tmp_path / "python"))
    b = study_driver.run_file(study_driver.read(path), options(tmp_path / "file"))
    assert (a.out / "trials.parquet").read_bytes() == (b.out / "trials.parquet").read_bytes()
    for gait in sorted((a.out / study_io.BEST_PARAMS).glob("*.json")):
        assert gait.read_bytes() == (b.out / study_io.BEST_PARAMS / gait.name).read_bytes()
    without_run_line = [p.read_text().split("\nRun: ")[0] for p in (a.out / "table.md", b.out / "table.md")]
    assert without_run_line[0] == without_run_line[1] and "| open_loop | trials 0–2" in without_run_line[0]


# ----------------------------------------------------------------------------------------------- generic report


def _fake_result(spec, seed=0):
    """A finished study's result with random trial figures: what the generic report reads."""
    rng = np.random.default_rng(seed)
    cond = study_spec.conditions(spec)
    batch, n = cond.friction.shape
    trials = types.SimpleNamespace(
        objective=rng.uniform(-1.0, 2.3, (n, batch)),
        cot=rng.uniform(0.4, 1.2, (n, batch)),
        velocity_xy_mps=rng.uniform(0.0, 0.6, (n, batch, 2)),
        fell=(rng.random((n, batch)) < 0.15).astype(float),
    )
    return types.SimpleNamespace(
        spec=spec, trials=trials, conditions=cond, walked=cond, labels=study_spec.instances(spec)
    )


def test_the_generic_report_per_group_and_phase_matches_numpy_and_scipy():
    spec = study_spec.StudySpec(
        "g",
        num_trials=12,
        controllers=("open_loop", "tegotae"),
        seeds=(0, 1, 2),
        friction=(0.4, 0.8),
        group_by=("controller", "friction"),
        schedules=(study_spec.Schedule("load", (study_spec.Change(7, "payload_kg", 10.0),), "load"),),
    )
    result = _fake_result(spec)
    tr = result.trials
    table = generic.group_table(result)
    labels = result.labels
    runs = [b for b, lab in enumerate(labels) if lab["controller"] == "tegotae" and lab["friction"] == 0.8]
    final_j = tr.objective[2:7, runs].mean(axis=0)  # phase 0–6: its last 5 trials
    m, half = final_j.mean(), sp.t.ppf(0.975, len(runs) - 1) * final_j.std(ddof=1) / np.sqrt(len(runs))
    row = next(line for line in table.splitlines() if line.startswith("| tegotae_friction0.8 | trials 0–6"))
    assert f"{m:.3f} [{m - half:.3f}, {m + half:.3f}]" in row
    falls = tr.fell[2:7, runs].sum(axis=0)  # per seed, in the phase's last 5 trials: the t interval cut at 0
    low, high = sp.ttest_1samp(falls, 0.0).confidence_interval(0.95)
    cells = f"| {falls.mean():.3f} [{max(low, 0.0):.3f}, {high:.3f}] | {int(tr.fell[0:7, runs].sum())}/{7 * len(runs)}"
    assert cells in row
    # under paper (the default) the feet's μ 0.6 holds the 0.8 floor, and the table says so
    assert "| tegotae_friction0.8 | trials 7–11: μ 0.8 (0.6 in effect), 0°, 10 kg" in table
    # by default every pair of groups that differs in one label, per phase: 4 pairs × 2 phases
    pairs = generic.contrasts(result, ())
    assert sorted(name for name, _, _ in pairs) == sorted(
        [
            "open_loop_friction0.4 − open_loop_friction0.8",
            "open_loop_friction0.4 − tegotae_friction0.4",
            "open_loop_friction0.8 − tegotae_friction0.8",
            "tegotae_friction0.4 − tegotae_friction0.8",
        ]
    )
    text = generic.comparison_table(result, ())
    assert text.count("\n| ") == 1 + 8
    a = [b for b, lab in enumerate(labels) if lab["controller"] == "tegotae" and lab["friction"] == 0.4]
    b = [b for b, lab in enumerate(labels) if lab["controller"] == "open_loop" and lab["friction"] == 0.4]
    given = (study_spec.Contrast("controller", "tegotae", "open_loop"),)
    (name, got_a, got_b), _ = generic.contrasts(result, given)
    assert name == "tegotae_friction0.4 − open_loop_friction0.4" and list(got_a) == a and list(got_b) == b
    ja, jb = tr.objective[7:12, a].mean(axis=0), tr.objective[7:12, b].mean(axis=0)
    welch = sp.ttest_ind(ja, jb, equal_var=False).pvalue
    row = next(
        line
        for line in generic.comparison_table(result, given).splitlines()
        if line.startswith(f"| {name} | trials 7–11")
    )
    assert f"Δ = {ja.mean() - jb.mean():+.3f}" in row and f"Welch p = {welch:.2g}" in row


def test_a_study_with_arms_refuses_one_physics_and_an_extension():
    """The transfer study's arms set their own physics and are not extended: --physics and --max-trials are refused
    in one line, from the command line and the Python API alike."""
    for overrides in (dict(physics="go1"), dict(max_trials=50)):
        with pytest.raises(study_spec.StudyError, match="its arms set their own physics and are not extended"):
            study_driver.read("transfer", **overrides)
