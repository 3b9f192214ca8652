"""The paper's studies: their specifications, their analyses against hand-computed references, and every output
file of a tiny controller ablation (table, figures, parquet, rerun recording, metadata); the CLI's failure paths.
"""

import dataclasses
import json
import pathlib

import imageio.v3 as iio
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import cpgjax
from cpgjax import ablation, cli, cpg
from cpgjax.studies import driver as study_driver
from cpgjax.studies import figures as study_figures
from cpgjax.studies import gaits as study_gaits
from cpgjax.studies import options as study_options
from cpgjax.studies import registry
from cpgjax.studies import video as study_video
from cpgjax.study import files as study_io
from cpgjax.study import spec as study_spec
from cpgjax.trial import params as param_space
from cpgjax.trial import protocol, tuned
from tests.test_ablation import small_optimizer
from tests.test_outputs import undocumented

# ----------------------------------------------------------------------------------------------- specifications


def _spec(name, **overrides):
    return study_driver.read(name, **overrides).spec


PAPER_STUDIES = [n for n in study_driver.paper_studies() if n != "transfer"]
TRANSFER_ARMS = study_driver.read("transfer").arms
ABLATION_REPORT = registry.REPORTS["controller_ablation"]


def _write_ablation(result, out, **kwargs) -> str:
    """Every file of the ablation's finished run, as ``cpgjax study`` writes them."""
    return study_driver.write_study(
        study_driver.one_folder(result.spec, ABLATION_REPORT), {result.spec.name: result}, out, "native", **kwargs
    )


def test_specs_follow_the_paper():
    spec = _spec("controller_ablation")
    assert spec.controllers == cpg.CONTROLLERS and spec.seeds == tuple(range(20)) and spec.num_trials == 40
    assert spec.target_velocity_mps == (0.5,) and spec.trial == protocol.TrialConfig()  # 1.5 s + 3 s at 1 kHz
    assert len(study_spec.instances(spec)) * spec.num_trials * 4.5 == 14400.0  # robot-seconds: 20 seeds, not 5
    cond = study_spec.conditions(_spec("load_adaptation"))
    np.testing.assert_array_equal(registry.phase_starts(cond.payload_kg[0]), [0, 36, 58])  # paper: trials 36, 58
    np.testing.assert_array_equal(cond.payload_kg[0, [0, 36, 58]], [0.0, 7.5, 15.0])
    cond = study_spec.conditions(_spec("multi_velocity"))
    assert cond.target_velocity_mps.shape[1] == 140
    np.testing.assert_array_equal(np.unique(cond.target_velocity_mps[0]), [0.3, 0.6, 0.8])
    spec = _spec("slope_adaptation")
    cond = study_spec.conditions(spec)
    learn = int(np.argmax(cond.inference[0]))
    assert [cond.slope_deg[0, t] for t in registry.phase_starts(cond.slope_deg[0, :learn])] == [0.0, 10.0, 12.5]
    assert sorted(set(cond.slope_deg[0, learn:])) == [10.0, 12.5, 15.0, 17.5] and cond.inference[0, learn:].all()
    ramp = int(np.argmax(cond.ramp[0]))  # then the continuous ramp, 10° → 17.5°, 12 trials in inference mode
    assert ramp == learn + 12 == spec.num_trials - 12 and cond.ramp[0, ramp:].all() and not cond.ramp[0, :ramp].any()
    assert spec.ramp.start_deg == 10.0 and spec.ramp.end_deg == 17.5
    assert _spec("friction").friction == (0.3, 0.6, 0.9)
    spec = _spec("paper_hardware")  # the paper's hardware experiments under the go1 profile
    cond = study_spec.conditions(spec)
    labels = [lab["schedule"] for lab in study_spec.instances(spec)]
    assert spec.physics == ("go1",) and len(set(labels)) == 5
    by = {label: labels.index(label) for label in labels}
    assert np.all(cond.target_velocity_mps[by["flat 0.4 m/s"]] == 0.4)
    assert np.all(cond.friction[by["flat 0.4 m/s"]] == 0.6)
    assert np.all(cond.friction[by["taped feet 0.4 m/s"]] == 0.3)
    v = cond.target_velocity_mps[by["0.6→0.3→0.5→0.6 m/s"]]
    assert [v[t] for t in registry.phase_starts(v)] == [0.6, 0.3, 0.5, 0.6]
    slope = cond.slope_deg[by["flat → 10°"]]
    assert registry.phase_starts(slope) == [0, 30] and slope[-1] == 10.0
    load = cond.payload_kg[by["0→5→10→15 kg"]]
    assert [load[t] for t in registry.phase_starts(load)] == [0.0, 5.0, 10.0, 15.0]
    assert registry.phase_starts(load)[1] == 30
    for name in PAPER_STUDIES:  # every quick variant is a valid, smaller study
        quick = _spec(name, quick=True)
        assert quick.num_trials < _spec(name).num_trials and len(quick.seeds) == 2


@pytest.mark.parametrize(
    "name, message",
    [
        ("nope", "unknown study 'nope': the paper's studies are controller_ablation, friction"),
        ("nope.toml", "study file nope.toml does not exist"),
    ],
)
def test_bad_study_names(name, message):
    with pytest.raises(study_spec.StudyError, match=message):
        study_driver.read(name)


# ----------------------------------------------------------------------------------------------- analyses


def test_trials_to_track_counts_from_the_change():
    v = np.array([0.1, 0.2, 0.79, 0.5, 0.35, 0.31, 0.3])
    target = np.array([0.8, 0.8, 0.8, 0.3, 0.3, 0.3, 0.3])
    fell = np.array([0, 0, 0, 0, 0, 1, 0])
    assert registry.trials_to_track(v, target, fell, 0, 3) == 3.0
    assert registry.trials_to_track(v, target, fell, 3, 7) == 2.0  # 0.35 is within 0.05 of 0.3
    assert registry.trials_to_track(v, target, fell, 3, 4) == 2.0  # never within the 1-trial phase: its length + 1
    assert registry.trials_to_track(v, target, np.array([0, 0, 0, 0, 1, 1, 0]), 3, 7) == 4.0  # falls don't count


def test_last_mean_and_phase_starts():
    values = np.arange(20.0).reshape(10, 2)
    np.testing.assert_allclose(registry.last_mean(values, 10), [14.0, 15.0])  # trials 5..9
    np.testing.assert_allclose(registry.last_mean(values, 3), [2.0, 3.0])  # fewer than 5 available
    assert registry.phase_starts(np.array([0, 0, 7.5, 7.5, 15])) == [0, 2, 4]


# ----------------------------------------------------------------------------------------------- outputs


@pytest.fixture(scope="module")
def tiny_ablation(tmp_path_factory):
    spec = dataclasses.replace(
        _spec("controller_ablation", seeds=1, trials=4),
        optimizer=small_optimizer(4),
        trial=protocol.TrialConfig(transition_steps=100, steady_steps=200),
    )
    out = tmp_path_factory.mktemp("controller_ablation")
    engine = ablation.Engine(spec, backend="native")
    result = engine.run(out)
    text = _write_ablation(result, out)
    return result, out, text


def test_a_machine_without_video_still_gets_every_other_output(tiny_ablation, tmp_path, monkeypatch):
    """No OpenGL backend (an unknown MUJOCO_GL fails MuJoCo's import in the renderer, as a missing OSMesa does): one
    line says so, and the summary page, the table and the rest are written without the filmstrips."""
    result, _, _ = tiny_ablation
    monkeypatch.setenv("MUJOCO_GL", "no-such-backend")
    lines = []
    _write_ablation(result, tmp_path, notify=lines.append)
    (said,) = [line for line in lines if line.startswith("no video")]
    assert "'no-such-backend' OpenGL backend" in said and "RuntimeError" in said and "\n" not in said
    assert (tmp_path / "summary.png").read_bytes()[:4] == b"\x89PNG" and (tmp_path / "table.md").exists()
    assert not list(tmp_path.glob("*.mp4"))


def test_ablation_outputs(tiny_ablation):
    result, out, text = tiny_ablation
    for c in cpg.CONTROLLERS:  # our row beside the paper's
        row = next(line for line in text.splitlines() if line.startswith(f"| {c} |"))
        paper = registry.PAPER_CONTROLLER_TABLE[c]
        assert f"{paper[1][0]:.3f} ± {paper[1][1]:.3f}" in row
        j = result.trials.objective[:, [lab["controller"] == c for lab in result.labels]]
        assert f"| {np.mean(j[-5:].mean(axis=0)):.3f} |" in row  # mean of the last 5, then over 1 seed: no CI
    assert "- 1 seed: no interval or test below 3 seeds." in text.splitlines()
    assert (out / "table.md").read_text().startswith("# controller_ablation")
    assert "Roll–pitch of the best parameters" in (out / "table.md").read_text()  # the attitude figure's rows
    for png in (
        "learning_curves.png",
        "attitude.png",
        "attitude_best_gaits.png",
        "summary.png",
        "optimization_progress.png",
    ):
        assert (out / png).read_bytes()[:4] == b"\x89PNG"
    table = pq.read_table(out / "trials.parquet").to_pydict()
    assert len(table["objective"]) == 4 * 4
    for col in (
        "controller",
        "seed",
        "trial",
        "c_load_n",
        "c_slope_rad",
        "objective",
        "velocity_x_mps",
        "cost_of_transport",
        "fell",
        "payload_kg",
        *param_space.PARAM_NAMES,
    ):
        assert col in table, col
    b, t = 2, 3
    row = table["instance"].index(b) + t
    assert table["controller"][row] == result.labels[b]["controller"] and table["trial"][row] == t
    assert table["objective"][row] == pytest.approx(float(result.trials.objective[t, b]))
    assert table["amplitude_mu"][row] == pytest.approx(float(result.trials.params[t, b, 4]))
    recording = (out / "recording.rrd").read_bytes()
    assert len(recording) > 10_000 and b"rollout/best_vmc_tegotae" in recording
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["instances"] == 4 and meta["env_steps"] == 4 * 4 * 300 and meta["real_time_factor"] > 0
    assert {"jax", "mujoco", "devices"} <= set(meta["environment"])
    assert meta["cpgjax_version"] == cpgjax.__version__ and meta["optimizer"]["num_random_proposals"] == 2
    assert meta["git_commit"] is None or len(meta["git_commit"].split("-")[0]) == 40
    for c in cpg.CONTROLLERS:  # each group's best gait, and its video where this machine can render
        (gait,) = [g for g in study_video.load_gaits(out) if g.group == c]
        b = [i for i, lab in enumerate(result.labels) if lab["controller"] == c][0]
        np.testing.assert_allclose(gait.params, result.trials.params[gait.trial, b])
        assert gait.objective == pytest.approx(float(result.trials.objective[gait.trial, b]))
        assert gait.objective == pytest.approx(float(result.trials.objective[:, b].max()))  # one phase: its best
        if (out / f"best_{c}.mp4").exists():
            assert len(iio.imread(out / f"best_{c}.mp4")) == 5  # the steady phase, 200 ticks at 25 frames/s
    schema = pq.read_schema(out / "trials.parquet")
    assert all(str(schema.field(name).type) == "bool" for name in ("fell", "failed", "accepted", "context_changed"))
    assert undocumented("study trials.parquet", schema.names) == []  # docs/outputs.md
    assert undocumented("metadata.json", meta) == []
    assert {str(f.type) for f in schema if pa.types.is_floating(f.type)} == {"double"}  # one float dtype
    assert set(table["latency_ticks"]) == {0} and set(table["noise_scale"]) == {0.0}  # the paper profile's own


def test_cli_show_prints_the_table(tiny_ablation, capsys):
    _, out, text = tiny_ablation
    assert cli.main(["show", str(out), "--no-viewer"]) == 0
    printed = capsys.readouterr().out
    assert text.splitlines()[2] in printed and "real-time factor" in printed


def test_best_gaits_are_each_groups_best_run_and_trial(tiny_ablation):
    result, _, _ = tiny_ablation
    gaits = study_gaits.best_gaits(result)
    assert [g.group for g in gaits] == list(cpg.CONTROLLERS)  # one per controller, the study's groups
    n = result.trials.objective.shape[0]
    for gait in gaits:
        runs = [b for b, lab in enumerate(result.labels) if lab["controller"] == gait.group]
        # a trial walked: it did not fall, and its J is above the floor of standing still (-1); one phase here
        ok = (result.trials.fell == 0) & (result.trials.objective > -1.0)
        walked = [b for b in runs if ok[:, b].any()]
        b = max(walked or runs, key=lambda i: result.trials.objective[n - 5 :, i].mean())
        j = np.where(ok[:, b] | (not walked), result.trials.objective[:, b], -np.inf)
        t = int(np.argmax(j))
        assert gait.walked == bool(walked) and gait.phase.startswith(f"trials 0–{n - 1}: μ 0.6, 0°, 0 kg")
        assert (gait.instance, gait.trial, gait.controller) == (b, t, gait.group)
        np.testing.assert_array_equal(gait.params, result.trials.params[t, b])
    (log,) = study_gaits.gait_rollouts(gaits[:1], "native", steps=250)
    assert log.qpos.shape[0] == 250 and log.phase_rad.shape == (250, 4) and np.all(np.isfinite(log.qpos))


def test_group_names_are_file_names():
    def named(labels, group_by, schedules=None):
        schedules = schedules or (study_spec.Schedule("constant"),)
        return study_gaits.group_name(labels, study_spec.StudySpec("s", group_by=group_by, schedules=schedules))

    assert named({"controller": "vmc_tegotae", "seed": 0}, ("controller",)) == "vmc_tegotae"
    assert named({"friction": 0.3}, ("friction",)) == "friction0.3"
    assert (
        named({"schedule": "0→7.5→15 kg"}, ("schedule",), (study_spec.Schedule("0→7.5→15 kg"),)) == "schedule0-7.5-15kg"
    )  # a schedule without a name: its label
    assert named({"data_reuse": True, "controller": "vmc"}, ("controller", "data_reuse")) == "vmc_data_reuseTrue"
    # a study file names its schedules: the quick slope study's group is a word, not its label
    slope = _spec("slope_adaptation", quick=True)
    assert (
        named({"schedule": slope.schedules[0].label}, ("schedule",), slope.schedules)
        == "slope_0_10_12.5deg_inference_ramp"
    )


def test_each_group_writes_its_best_parameters_with_what_they_were_tuned_for(tiny_ablation):
    """best_params/<c>.json: the group's best gait, read from trials.parquet: of the runs with a trial that walked,
    the run with the best mean J over its last trials, its highest-J trial that walked (one condition phase here),
    that run's controller, physics and the trial's conditions; `deploy --params` reads it back, and it is the gait
    the study films."""
    _, out, _ = tiny_ablation
    table = pq.read_table(out / "trials.parquet").to_pandas()
    last = table.trial.max() - registry.LAST_TRIALS
    filmed = {g.group: g for g in study_video.load_gaits(out)}
    for c in cpg.CONTROLLERS:
        path = out / study_io.BEST_PARAMS / f"{c}.json"
        saved = json.loads(path.read_text())
        runs = table[table.controller == c]
        ok = ~runs.fell & (runs.objective > -1.0)  # a best gait is one that walked (no fall, J above -1), if any did
        walking = runs[ok] if ok.any() else runs
        final = runs[runs.trial > last].groupby("instance").objective.mean()
        run = final[final.index.isin(walking.instance)].idxmax()
        best = walking[walking.instance == run].sort_values("objective", kind="stable").iloc[::-1].iloc[0]
        assert saved["walked"] == bool(ok.any())
        assert (saved["instance"], saved["trial"], saved["objective"]) == (
            run,
            best.trial,
            pytest.approx(best.objective),
        )
        assert {k: saved[k] for k in tuned.TUNED_FOR} == dict(
            controller=c,
            gait="trot",
            physics=best.physics,
            friction=pytest.approx(best.friction),
            slope_deg=best.slope_deg,
            payload_kg=best.payload_kg,
            target_velocity_mps=best.target_velocity_mps,
        )
        read = tuned.load(path)
        np.testing.assert_allclose(read.params, [best[name] for name in param_space.PARAM_NAMES])
        np.testing.assert_array_equal(filmed[c].params, read.params)


def test_a_failing_output_keeps_the_results_written_before_it(tiny_ablation, tmp_path, monkeypatch):
    """A figure that cannot be drawn (here: a raising learning_curves) stops the outputs with one message; the trial
    table, the metadata, the best parameters and table.md are already written, and the message names them."""
    result, _, _ = tiny_ablation

    def broken(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(study_figures, "learning_curves", broken)
    with pytest.raises(
        study_io.OutputError,
        match=r"writing the study's figures in .* failed \(OSError: "
        r"\[Errno 28\] No space left on device\); kept: best_params, metadata.json, table.md, "
        r"trials.parquet",
    ):
        _write_ablation(result, tmp_path)
    assert pq.read_table(tmp_path / "trials.parquet").num_rows == 16 and (tmp_path / "metadata.json").exists()
    table = (tmp_path / "table.md").read_text()
    assert "| vmc_tegotae |" in table and "Safety during optimization" in table and "\nRun: " in table
    assert "Roll–pitch of the best parameters" not in table  # the part its figure walks is not drawn yet


def test_transfer_arms_keep_their_best_gaits_and_film_them_after_the_table(tmp_path, monkeypatch):
    """Each arm's folder gets best_params/<controller>.json (the run's best gait, tuned for the arm's home physics),
    evaluations.parquet (the table's rows before aggregation) and, once table.md is written, best_<controller>.mp4
    where this machine can render (else one line says why)."""
    from cpgjax.studies import transfer

    real_specs = transfer.specs
    study = study_driver.read("transfer", seeds=1, trials=4)

    def tiny(study=study):
        return [
            dataclasses.replace(
                s, optimizer=small_optimizer(4), trial=protocol.TrialConfig(transition_steps=100, steady_steps=200)
            )
            for s in real_specs(study)
        ]

    monkeypatch.setattr(transfer, "specs", tiny)
    lines = []
    text, out, _ = study_driver.run(
        transfer.study(study),
        study_options.RunOptions(out=tmp_path / "transfer", backend="native", notify=lines.append),
    )
    assert (out / "table.md").read_text() == text
    filmed = [line for line in lines if ".mp4: " in line]
    for (arm, home, _), spec in zip(study.arms, tiny(), strict=True):
        gaits = {g.group: g for g in study_video.load_gaits(out / spec.name)}
        assert sorted(gaits) == sorted(cpg.CONTROLLERS), arm
        assert {tuned.load(study_video.gait_file(out / spec.name, c)).tuned_for["physics"] for c in gaits} == {home}
        if filmed:
            assert all(len(iio.imread(study_video.video_file(out / spec.name, c))) == 5 for c in gaits)
    assert filmed or any(line.startswith("no video: ") for line in lines), lines
    # every run × evaluation environment, documented; the table's J at home is their mean
    for (arm, home, randomized), spec in zip(study.arms, tiny(), strict=True):
        rows = pq.read_table(out / spec.name / "evaluations.parquet").to_pydict()
        assert undocumented("evaluations.parquet", rows) == []
        environments = transfer.Environments(home).names
        assert len(rows["objective"]) == len(cpg.CONTROLLERS) * len(environments)
        assert rows["environment"][: len(environments)] == environments
        j_home = np.mean(
            [
                j
                for j, c, e in zip(rows["objective"], rows["controller"], rows["environment"], strict=True)
                if c == "vmc" and e == home
            ]
        )
        label = home + (" + randomization" if randomized else "")
        assert f"| vmc | {label} | {j_home:.3f} |" in text, arm  # one seed: the mean, no interval
    assert "1 seed: no interval or test below 3 seeds." in text.splitlines()


def test_transfer_drops_and_their_tests_over_seeds_match_scipy():
    """The transfer table's drops and their tests on hand-made J: 4 seeds per controller, every environment's J drawn
    at random. The worst fixed profile is the away profile with the lowest mean over seeds, the randomized J the mean
    over the draws; intervals and p-values are recomputed with SciPy (Welch's t, Mann–Whitney's U, Fisher's exact
    test of the seeds whose gait fell away from home)."""
    from scipy import stats as sp

    from cpgjax.studies import transfer

    seeds, fixed = 4, list(transfer.ENVIRONMENT_PROFILES)
    environments = len(fixed) + transfer.EVALUATION_DRAWS
    labels = [{"controller": c} for c in cpg.CONTROLLERS for _ in range(seeds)]
    rng = np.random.default_rng(3)
    results = {arm: type("Result", (), {"labels": labels}) for arm, _, _ in TRANSFER_ARMS}
    evaluations = {
        arm: tuple(rng.normal(2.0, 0.3, (len(labels), environments)) for _ in range(3))
        + (rng.random((len(labels), environments)) < 0.08,)
        for arm, _, _ in TRANSFER_ARMS
    }

    def drops(arm, home, controller):
        j = evaluations[arm][0][[lab["controller"] == controller for lab in labels]]
        h = fixed.index(home)
        away = [k for k in range(len(fixed)) if k != h]
        worst = away[int(np.argmin(j[:, away].mean(axis=0)))]
        return j[:, h], j[:, worst] - j[:, h], j[:, len(fixed) :].mean(axis=1) - j[:, h]

    text, falls = transfer.comparisons(TRANSFER_ARMS, results, evaluations).split("\n\n")
    rows = {tuple(cell.strip() for cell in line.split("|")[1:3]): line for line in text.splitlines()[2:]}
    assert len(rows) == 3 * 3 * 2 + 4 * 2
    for arm, home, randomized in TRANSFER_ARMS:
        label = home + (" + randomization" if randomized else "")
        for c in cpg.CONTROLLERS[1:]:
            for k, quantity in ((1, "drop: worst fixed"), (2, "drop: randomized")):
                a, b = drops(arm, home, c)[k], drops(arm, home, "open_loop")[k]
                line = rows[(f"{c} − open_loop, optimized under {label}", quantity)]
                cells = [cell.strip() for cell in line.split("|")[3:6]]
                assert cells[0].startswith(f"{a.mean() - b.mean():+.3f} [")
                welch = sp.ttest_ind(a, b, equal_var=False)
                low, high = welch.confidence_interval(0.95)
                assert cells[0] == f"{a.mean() - b.mean():+.3f} [{low:+.3f}, {high:+.3f}]"
                assert cells[1] == f"{welch.pvalue:.2g}"
                assert cells[2] == f"{sp.mannwhitneyu(a, b, alternative='two-sided').pvalue:.2g}"
    home_dr, home_plain = drops("paper_randomized", "paper", "tegotae")[0], drops("paper", "paper", "tegotae")[0]
    line = rows[("tegotae: paper + randomization − paper", "J at home")]
    assert f"| {sp.ttest_ind(home_dr, home_plain, equal_var=False).pvalue:.2g} |" in line
    # falls away by seed (any away environment; go1's home column is left out), Fisher's exact test
    fell = evaluations["go1"][3][:, [k for k in range(environments) if k != fixed.index("go1")]].any(axis=1)
    a, b = fell[[lab["controller"] == "tegotae" for lab in labels]], fell[:seeds]
    p = sp.fisher_exact([[a.sum(), seeds - a.sum()], [b.sum(), seeds - b.sum()]]).pvalue
    assert f"| go1 | tegotae | {a.sum()}/{seeds} | {b.sum()}/{seeds} | {p:.2g} |" in falls.splitlines()
    table = transfer.table(TRANSFER_ARMS, results, evaluations)
    home, worst, randomized = drops("go1", "go1", "vmc")
    line = next(r for r in table.splitlines() if r.startswith("| vmc | go1 |"))
    half = sp.t.ppf(0.975, seeds - 1) * worst.std(ddof=1) / np.sqrt(seeds)
    assert f"| {worst.mean():+.3f} [{worst.mean() - half:+.3f}, {worst.mean() + half:+.3f}] |" in line


def _hand_made_ablation(seeds: int, cot_final: np.ndarray):
    """A controller-ablation result of ``seeds`` seeds per controller and 6 trials: J and v_x drawn at random, the
    last 5 trials' CoT of each run ``cot_final`` (one value a run), and no falls."""
    rng = np.random.default_rng(7)
    spec = dataclasses.replace(_spec("controller_ablation"), seeds=tuple(range(seeds)))
    labels = study_spec.instances(spec)  # controllers × seeds
    b = len(labels)
    trials = type(
        "T",
        (),
        {
            "objective": rng.normal(1.5, 0.5, (6, b)),
            "velocity_xy_mps": rng.normal(0.5, 0.1, (6, b, 2)),
            "cot": np.broadcast_to(cot_final, (6, b)).copy(),
            "fell": np.zeros((6, b)),
        },
    )
    return type(
        "Result", (), {"trials": trials, "labels": labels, "spec": spec, "conditions": study_spec.conditions(spec)}
    )


def test_a_two_seed_table_gives_means_without_intervals_or_tests_and_says_why():
    result = _hand_made_ablation(2, np.tile([0.4, 47.6], len(cpg.CONTROLLERS)))
    text = ABLATION_REPORT.report(result, "native") + registry.notes(result)
    rows = [line for line in text.splitlines() if line.startswith("| open_loop |")]
    assert rows == [
        f"| open_loop | {result.trials.velocity_xy_mps[1:, :2, 0].mean():.3f} | 0.477 ± 0.045 | 24.000 | "
        f"0.931 ± 0.138 | {result.trials.objective[1:, :2].mean():.3f} | 1.638 ± 0.516 | 0/12 |"
    ]
    assert "[" not in "".join(rows) and " p = " not in text and "Welch" not in text
    assert "- 2 seeds: no interval or test below 3 seeds." in text.splitlines()
    assert "then mean over 2 seeds (no interval below 3);" in text and "95 % CI" not in text.splitlines()[0]
    assert "J = -1 is J's floor" in text and "at least 0.05 m" in text  # the footnotes on J's floor and on CoT


def test_a_cost_of_transports_interval_stays_above_zero_where_a_t_interval_would_not():
    """Three seeds, one of which barely moved (CoT 47.6): the t interval of the CoT reaches below 0, the table's
    starts at 0 (SciPy's t interval, cut); the comparisons' rank test says it cannot reach 5 %."""
    from scipy import stats as sp

    cot = np.tile([0.5, 0.6, 47.6], len(cpg.CONTROLLERS))
    t_low, t_high = sp.ttest_1samp(cot[:3], 0.0).confidence_interval(0.95)
    text = ABLATION_REPORT.report(_hand_made_ablation(3, cot), "native")
    row = next(line for line in text.splitlines() if line.startswith("| open_loop |"))
    assert t_low < 0.0 and f"| {cot[:3].mean():.3f} [0.000, {t_high:.3f}] |" in row
    assert "Mann–Whitney cannot reach p < 0.05 at these sizes (least p 0.1)" in text


def test_summary_marks_the_papers_j_where_the_paper_gives_it():
    """The load study's marks: the paper's J after adaptation (Table "load": 2.175, 2.213, 2.189) over the last 5
    trials of each payload phase; the ablation's: each controller's J ± std over the last 5 trials."""
    payload = np.array([0.0] * 36 + [7.5] * 22 + [15.0] * 22)
    result = type(
        "Result",
        (),
        {
            "conditions": type("C", (), {"payload_kg": payload[None, :]}),
            "trials": type("T", (), {"objective": np.zeros((80, 1))}),
        },
    )
    marks = registry.load_paper_marks(result)
    assert [(m.first_trial, m.last_trial, m.objective, m.std) for m in marks] == [
        (31, 35, 2.175, None),
        (53, 57, 2.213, None),
        (75, 79, 2.189, None),
    ]
    ablation_marks = {m.group: m for m in registry.ablation_paper_marks(result)}
    assert (ablation_marks["tegotae"].first_trial, ablation_marks["tegotae"].last_trial) == (75, 79)
    assert (ablation_marks["tegotae"].objective, ablation_marks["tegotae"].std) == (2.153, 0.042)
    assert registry.REPORTS["friction"].paper_marks(result) == []


def test_summary_draws_the_main_table_as_cells_that_fit_the_page():
    """summary.png's table: the first Markdown table's cells (not its rule, not the tables after it), each wrapped
    to its column's width, the columns together no wider than the page's line."""
    long_name = "gaittrot_target_velocity_mps0.3"
    text = (
        "intro\n\n| group | phase | trials to a prospective solution (runs never reaching one) |\n|---|---|---|\n"
        f"| {long_name} | trials 0–39: μ 0.6, 0°, 0 kg, v* 0.3 m/s | 5.350 [3.860, 6.840] (0) |\n"
        "| b | c | d |\n\nComparisons:\n\n| x | y |\n|---|---|\n| 1 | 2 |\n"
    )
    rows = study_figures._first_table(text)
    assert rows[0] == ["group", "phase", "trials to a prospective solution (runs never reaching one)"]
    assert rows[1][0] == long_name and rows[2] == ["b", "c", "d"] and len(rows) == 3
    cells, shares = study_figures._wrapped(rows)
    assert sum(shares) == pytest.approx(1.0)
    assert cells[1][0].replace("\n", "") == long_name  # broken after its underscores, nothing lost
    wide = [["h"] * 12] + [["x" * 30 + " " + "y" * 30] * 12]
    cells, _ = study_figures._wrapped(wide)
    width = max(len(line) for line in cells[1][0].split("\n"))
    assert 12 * width <= study_figures.TABLE_CHARS_PER_LINE


def test_fall_chains_counts_falls_after_a_fall_and_after_a_walk(tmp_path):
    """``studies/fall_chains.py`` on a hand-made table of two instances × five trials, counted by hand: instance 0
    falls at trials 1, 2 and 4; instance 1 at trial 3, and its condition changes at trial 3 (the pair (2, 3) is not
    counted); instance 0's trial 4 is in inference mode (neither it nor its pair is counted). The table goes through a
    parquet file and ``study_io.read_trials``, as a study's does."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "fall_chains", pathlib.Path(__file__).resolve().parents[2] / "studies" / "fall_chains.py"
    )
    fall_chains = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(fall_chains)
    fell = {0: [0, 1, 1, 0, 1], 1: [0, 0, 0, 1, 0]}
    rows = [(i, t) for i in (0, 1) for t in range(5)]
    columns = {
        "instance": np.array([i for i, _ in rows]),
        "trial": np.array([t for _, t in rows]),
        "fell": np.array([fell[i][t] for i, t in rows], float),
        "failed": np.zeros(10),
        "inference": np.array([float(i == 0 and t == 4) for i, t in rows]),
        "friction": np.full(10, 0.6),
        "slope_deg": np.array([10.0 * (i == 1 and t >= 3) for i, t in rows]),
        "payload_kg": np.zeros(10),
        "target_velocity_mps": np.full(10, 0.5),
        "c_load_n": np.array([1.0 if fell[i][t] else 20.0 + t for i, t in rows]),
        "c_slope_rad": np.zeros(10),
    }
    pq.write_table(pa.table(columns), tmp_path / "trials.parquet")
    counted = fall_chains.chains(study_io.read_trials(tmp_path / "trials.parquet"))
    assert list(counted) == ["slope_deg 0", "slope_deg 10"]
    level, steep = counted["slope_deg 0"], counted["slope_deg 10"]
    # instance 0: (0,1) walk→fall, (1,2) fall→fall, (2,3) fall→walk; instance 1: (0,1), (1,2) walk→walk
    assert level["after_fall"] == (1, 2) and level["after_walk"] == (1, 3)
    # instance 1 on the new slope: (3,4) fall→walk
    assert steep["after_fall"] == (0, 1) and steep["after_walk"] == (0, 0)
    assert (level["falls"], level["trials"], steep["falls"], steep["trials"]) == (2, 7, 1, 2)
    assert level["contexts"]["c_load_n"] == (1.0, 21.0) and steep["contexts"]["c_load_n"] == (1.0, 24.0)
    # per run (after a fall: falls, cases; after a walk: falls, cases), and the pooled difference they give
    assert level["per_run"] == [(1, 2, 1, 1), (0, 0, 0, 2)] and level["runs_with_falls"] == 1
    assert fall_chains.chain_difference(level["per_run"]) == pytest.approx(1 / 2 - 1 / 3)
    assert np.isnan(fall_chains.chain_difference(steep["per_run"]))
