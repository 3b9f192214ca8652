"""The files layer of a study (``cpgjax.study.files``) called directly: which folders and files a command may claim,
what ``--overwrite`` removes and what it refuses, the one-line refusals, the checkpoint read back as written, and the
trial table read back by instance and trial; every expectation written out here."""

import errno
import pathlib
import types

import jax
import numpy as np
import pytest

from cpgjax.optim import bo
from cpgjax.study import files as study_io
from cpgjax.study import placement as study_placement
from cpgjax.study import spec as study_spec
from cpgjax.study.spec import StudyError

SPEC = study_spec.StudySpec("files_test", num_trials=2, seeds=(0, 1))
PROC = pytest.mark.skipif(not pathlib.Path("/proc/self").is_dir(), reason="needs Linux's /proc")
PROC_REFUSES = ("No such file or directory", "Permission denied")  # /proc's answer to root, to another user


def _touch(path: pathlib.Path, text: str = "x") -> pathlib.Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def _tree(folder: pathlib.Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


# ----------------------------------------------------------------------------------------------- claim_folder


def test_a_missing_folder_is_created_with_its_parents(tmp_path):
    out = tmp_path / "a" / "b" / "run"
    assert study_io.claim_folder(out) == out
    assert out.is_dir() and list(out.iterdir()) == []


def test_an_empty_folder_is_claimed_as_it_is(tmp_path):
    assert study_io.claim_folder(tmp_path) == tmp_path
    assert list(tmp_path.iterdir()) == []


def test_a_folder_holding_only_a_write_probe_counts_as_empty(tmp_path):
    """Another process of the same run may be probing the folder (check_writable's file) at that moment."""
    _touch(tmp_path / ".cpgjax-write-check-12345")
    assert study_io.claim_folder(tmp_path) == tmp_path


def test_a_file_is_refused_as_the_folder(tmp_path):
    path = _touch(tmp_path / "run")
    with pytest.raises(StudyError) as err:
        study_io.claim_folder(path, overwrite=True)
    assert str(err.value) == f"{path} is a file, not a folder: give a folder to write into"


def test_a_folder_with_files_is_refused_naming_the_folder_and_the_flags(tmp_path):
    _touch(tmp_path / "notes.txt")
    with pytest.raises(StudyError) as err:
        study_io.claim_folder(tmp_path)
    assert str(err.value) == (
        f"{tmp_path} is not empty (notes.txt): pass --overwrite to replace its files, or write somewhere else"
    )
    assert _tree(tmp_path) == ["notes.txt"]


def test_the_refusal_shows_three_entries_and_offers_resume_where_a_checkpoint_is(tmp_path):
    for name in ("a.txt", "b.txt", "checkpoint.npz", "d.txt"):
        _touch(tmp_path / name)
    with pytest.raises(StudyError) as err:
        study_io.claim_folder(tmp_path)
    assert str(err.value) == (
        f"{tmp_path} is not empty (a.txt, b.txt, checkpoint.npz, ...): pass --resume to "
        f"continue its checkpoint, --overwrite to replace its files, or write somewhere else"
    )
    with pytest.raises(StudyError) as err:
        study_io.claim_folder(tmp_path, resumable=False)
    assert str(err.value) == (
        f"{tmp_path} is not empty (a.txt, b.txt, checkpoint.npz, ...): pass --overwrite to "
        f"replace its files, or write somewhere else"
    )


def _every_kind_of_output(out: pathlib.Path) -> None:
    """One file of each kind cpgjax writes, made by hand."""
    for name in (
        "trials.parquet",
        "metadata.json",
        "table.md",
        "checkpoint.npz",
        "checkpoint.npz.tmp",
        "checkpoint.1of2.t000003.npz",
        "recording.rrd",
        "best_params.json",
        "walk.parquet",
        "friction.png",
        "best_tegotae.mp4",
        "best_params/tegotae.json",
        "best_params/open_loop.json",
        "arm_go1/trials.parquet",
        "arm_go1/checkpoint.npz",
        "arm_go1/best_params/vmc.json",
    ):
        _touch(out / name)


def test_overwrite_removes_every_kind_of_cpgjax_output_and_keeps_the_folder(tmp_path):
    out = tmp_path / "run"
    _every_kind_of_output(out)
    assert study_io.claim_folder(out, overwrite=True) == out
    assert out.is_dir() and list(out.iterdir()) == []


@pytest.mark.parametrize(
    "foreign, named",
    [
        ("notes.txt", "notes.txt"),
        ("best_params/notes.txt", "best_params"),  # best_params/ holding anything but JSON
        ("arm_go1/notes.txt", "arm_go1"),  # an arm folder holding a file of someone else's
        ("best_tegotae.avi", "best_tegotae.avi"),
        ("trials.csv", "trials.csv"),
    ],
)
def test_overwrite_refuses_a_foreign_file_naming_it_and_removes_nothing(foreign, named, tmp_path):
    out = tmp_path / "run"
    _every_kind_of_output(out)
    _touch(out / foreign)
    before = _tree(out)
    with pytest.raises(StudyError) as err:
        study_io.claim_folder(out, overwrite=True)
    assert str(err.value) == (
        f"{out}: --overwrite replaces only what cpgjax wrote, and {named} is not cpgjax's: "
        f"move it, or write somewhere else"
    )
    assert _tree(out) == before


def test_overwrite_names_several_foreign_entries_and_an_empty_folder_is_foreign(tmp_path):
    _touch(tmp_path / "trials.parquet")
    _touch(tmp_path / "z.txt")
    (tmp_path / "empty").mkdir()
    with pytest.raises(StudyError) as err:
        study_io.claim_folder(tmp_path, overwrite=True)
    assert str(err.value) == (
        f"{tmp_path}: --overwrite replaces only what cpgjax wrote, and empty, z.txt are not "
        f"cpgjax's: move them, or write somewhere else"
    )
    assert _tree(tmp_path) == ["empty", "trials.parquet", "z.txt"]


def test_a_symlink_is_never_followed_nor_removed(tmp_path):
    """A link with an output's name, and a link to a folder of outputs, are foreign: the links and what they point
    at stay."""
    elsewhere = tmp_path / "elsewhere"
    _touch(elsewhere / "trials.parquet")
    out = tmp_path / "run"
    _touch(out / "metadata.json")
    (out / "trials.parquet").symlink_to(elsewhere / "trials.parquet")
    (out / "arm_go1").symlink_to(elsewhere, target_is_directory=True)
    with pytest.raises(StudyError) as err:
        study_io.claim_folder(out, overwrite=True)
    assert str(err.value) == (
        f"{out}: --overwrite replaces only what cpgjax wrote, and arm_go1, trials.parquet are "
        f"not cpgjax's: move them, or write somewhere else"
    )
    assert (out / "trials.parquet").is_symlink() and (out / "arm_go1").is_symlink()
    assert (out / "metadata.json").is_file() and _tree(elsewhere) == ["trials.parquet"]


def test_dry_run_deletes_nothing_and_creates_nothing(tmp_path):
    out = tmp_path / "run"
    _every_kind_of_output(out)
    before = _tree(out)
    assert study_io.claim_folder(out, overwrite=True, dry_run=True) == out
    assert _tree(out) == before
    missing = tmp_path / "a" / "b"
    assert study_io.claim_folder(missing, dry_run=True) == missing
    assert not (tmp_path / "a").exists()


def test_dry_run_refuses_a_missing_folder_below_a_file(tmp_path):
    parent = _touch(tmp_path / "file")
    with pytest.raises(StudyError) as err:
        study_io.claim_folder(parent / "run", dry_run=True)
    assert str(err.value) == f"cannot create the folder {parent / 'run'}: {parent} is a file"


def test_resume_keeps_the_folder_as_it_is(tmp_path):
    _every_kind_of_output(tmp_path)
    _touch(tmp_path / "notes.txt")
    before = _tree(tmp_path)
    assert study_io.claim_folder(tmp_path, resume=True) == tmp_path
    assert _tree(tmp_path) == before


@PROC
def test_a_folder_below_a_parent_that_takes_no_folders_is_refused_in_one_line():
    with pytest.raises(StudyError) as err:
        study_io.claim_folder("/proc/x/out")
    assert str(err.value) in {
        f"cannot create the folder /proc/x/out: /proc takes no new folders ({why})" for why in PROC_REFUSES
    }
    with pytest.raises(StudyError) as err:
        study_io.claim_folder("/proc/x/out", dry_run=True)
    assert str(err.value) in {f"cannot write in /proc: it takes no new files ({why})" for why in PROC_REFUSES}


# ----------------------------------------------------------------------------------------------- single files


def test_check_writable_leaves_no_file_behind(tmp_path):
    study_io.check_writable(tmp_path)
    assert list(tmp_path.iterdir()) == []


@PROC
def test_check_writable_names_the_folder_and_the_reason():
    with pytest.raises(StudyError) as err:
        study_io.check_writable(pathlib.Path("/proc"))
    assert str(err.value) in {f"cannot write in /proc: it takes no new files ({why})" for why in PROC_REFUSES}


def test_claim_file_creates_the_folders_of_a_new_file(tmp_path):
    path = tmp_path / "a" / "b" / "gait.json"
    assert study_io.claim_file(path) == path
    assert (tmp_path / "a" / "b").is_dir() and not path.exists()


def test_claim_file_refuses_an_existing_file_unless_told_to_overwrite_it(tmp_path):
    path = _touch(tmp_path / "gait.json", "kept")
    with pytest.raises(StudyError) as err:
        study_io.claim_file(path)
    assert str(err.value) == f"{path} exists: pass --overwrite to replace it, or give another file"
    assert study_io.claim_file(path, overwrite=True) == path
    assert path.read_text() == "kept"  # claimed, not yet written


def test_claim_file_refuses_a_folder(tmp_path):
    with pytest.raises(StudyError) as err:
        study_io.claim_file(tmp_path, overwrite=True)
    assert str(err.value) == f"{tmp_path} is a folder: give a file name"


@PROC
def test_claim_file_refuses_a_folder_that_cannot_be_created():
    with pytest.raises(StudyError) as err:
        study_io.claim_file("/proc/x/gait.json")
    assert str(err.value) in {f"cannot create the folder /proc/x: {why}" for why in PROC_REFUSES}


# ----------------------------------------------------------------------------------------------- writing


def test_writing_turns_an_error_into_an_output_error_naming_the_file_and_what_was_kept(tmp_path):
    _touch(tmp_path / "checkpoint.npz")
    _touch(tmp_path / "trials.parquet")
    with pytest.raises(study_io.OutputError) as err:
        with study_io.writing(tmp_path, "table.md"):
            raise OSError("disk full")
    assert str(err.value) == (
        f"writing table.md in {tmp_path} failed (OSError: disk full); kept: checkpoint.npz, "
        f"trials.parquet. Every trial is in its checkpoint: the same command with --resume "
        f"writes the outputs again"
    )
    with pytest.raises(study_io.OutputError, match=r"; kept: nothing\. "):
        with study_io.writing(tmp_path / "missing", "table.md"):
            raise ValueError("bad")


def test_writing_lets_a_successful_write_through(tmp_path):
    with study_io.writing(tmp_path, "table.md"):
        _touch(tmp_path / "table.md")
    assert _tree(tmp_path) == ["table.md"]


def test_output_folder_is_out_or_results_slash_the_name(tmp_path):
    assert study_io.output_folder("friction") == pathlib.Path("results/friction")
    assert study_io.output_folder("friction", str(tmp_path)) == tmp_path


# ----------------------------------------------------------------------------------------------- checkpoints


def _log(rows: list[float]) -> study_io.TrialLog:
    """A trial log whose every field is ``rows`` (one value per instance)."""
    return study_io.TrialLog(*(np.array(rows) for _ in study_io.TrialLog._fields))


def _checkpoint(trial: int = 2) -> study_io.Checkpoint:
    return study_io.Checkpoint(
        trial=trial,
        opt_leaves=[np.array([[1.0, 2.0], [3.0, 4.0]]), np.array([5, 6], np.int32)],
        sim_leaves=[np.array([[0.5], [0.25]], np.float32)],
        context=np.array([[10.0, 0.1], [20.0, 0.2]]),
        logs=[_log([1.0, 2.0]), _log([3.0, 4.0])][:trial],
        wall_s=12.5,
        timing={"simulation_s": 3.0},
    )


def test_a_saved_checkpoint_loads_back_the_same_arrays(tmp_path):
    path = study_io.save_checkpoint(tmp_path, SPEC, _checkpoint(), "native")
    assert path == tmp_path / "checkpoint.npz" and _tree(tmp_path) == ["checkpoint.npz"]
    got = study_io.load_checkpoint(tmp_path, SPEC)
    assert got.trial == 2 and got.wall_s == 12.5 and got.timing == {"simulation_s": 3.0}
    np.testing.assert_array_equal(got.opt_leaves[0], [[1.0, 2.0], [3.0, 4.0]])
    np.testing.assert_array_equal(got.opt_leaves[1], [5, 6])
    assert got.opt_leaves[1].dtype == np.int32 and got.sim_leaves[0].dtype == np.float32
    np.testing.assert_array_equal(got.sim_leaves[0], [[0.5], [0.25]])
    np.testing.assert_array_equal(got.context, [[10.0, 0.1], [20.0, 0.2]])
    assert len(got.logs) == 2
    for field in study_io.TrialLog._fields:
        np.testing.assert_array_equal(getattr(got.logs[0], field), [1.0, 2.0])
        np.testing.assert_array_equal(getattr(got.logs[1], field), [3.0, 4.0])


def test_a_checkpoint_loads_the_rows_asked_for_and_every_instances_logs(tmp_path):
    study_io.save_checkpoint(tmp_path, SPEC, _checkpoint(), "native")
    got = study_io.load_checkpoint(tmp_path, SPEC, rows=(1, 2))
    np.testing.assert_array_equal(got.opt_leaves[0], [[3.0, 4.0]])
    np.testing.assert_array_equal(got.sim_leaves[0], [[0.25]])
    np.testing.assert_array_equal(got.context, [[20.0, 0.2]])
    np.testing.assert_array_equal(got.logs[1].objective, [3.0, 4.0])


def test_a_folder_without_a_checkpoint_loads_none(tmp_path):
    assert study_io.load_checkpoint(tmp_path, SPEC) is None
    assert study_io.load_checkpoint(tmp_path / "missing", SPEC) is None


def test_shards_are_merged_once_every_process_wrote_the_trial(tmp_path):
    """Two processes' rows 0–1 and 2–3: rank 1 alone is no checkpoint; both give the four rows in order."""

    def shard_checkpoint(rows):
        return study_io.Checkpoint(
            1, [np.array(rows)], [np.array(rows) * 10.0], np.array([[r, -r] for r in rows]), [_log(rows)], 1.0, {}
        )

    second = study_io.save_checkpoint(tmp_path, SPEC, shard_checkpoint([3.0, 4.0]), "native", study_io.Shard(1, 2, 2))
    assert second == tmp_path / "checkpoint.1of2.t000001.npz"
    assert study_io.load_checkpoint(tmp_path, SPEC) is None
    study_io.save_checkpoint(tmp_path, SPEC, shard_checkpoint([1.0, 2.0]), "native", study_io.Shard(0, 2, 0))
    got = study_io.load_checkpoint(tmp_path, SPEC)
    np.testing.assert_array_equal(got.opt_leaves[0], [1.0, 2.0, 3.0, 4.0])
    np.testing.assert_array_equal(got.sim_leaves[0], [10.0, 20.0, 30.0, 40.0])
    np.testing.assert_array_equal(got.context, [[1.0, -1.0], [2.0, -2.0], [3.0, -3.0], [4.0, -4.0]])
    np.testing.assert_array_equal(got.logs[0].fell, [1.0, 2.0, 3.0, 4.0])


def test_a_failed_checkpoint_write_keeps_the_previous_one(tmp_path, monkeypatch):
    study_io.save_checkpoint(tmp_path, SPEC, _checkpoint(1), "native")

    def full_disk(_fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(study_io.os, "fsync", full_disk)
    with pytest.raises(study_io.OutputError) as err:
        study_io.save_checkpoint(tmp_path, SPEC, _checkpoint(2), "native")
    assert str(err.value) == (
        f"writing the checkpoint of trial 1 in {tmp_path} failed (No space left on device); "
        f"trials 0…0 are kept in its checkpoint: free space, then the same command with "
        f"--resume continues"
    )
    assert _tree(tmp_path) == ["checkpoint.npz"] and study_io.load_checkpoint(tmp_path, SPEC).trial == 1


@pytest.mark.parametrize("damage", ["garbage", "truncated"])
def test_a_damaged_checkpoint_is_a_study_error_naming_it(damage, tmp_path):
    path = study_io.save_checkpoint(tmp_path, SPEC, _checkpoint(), "native")
    data = path.read_bytes()
    path.write_bytes(b"not a checkpoint" if damage == "garbage" else data[: len(data) // 2])
    for read in (
        lambda: study_io.load_checkpoint(tmp_path, SPEC),
        lambda: study_io.resume_point(tmp_path, SPEC, "native"),
    ):
        with pytest.raises(StudyError) as err:
            read()
        message = str(err.value)
        assert message.startswith(f"checkpoint {path} is corrupt (") and message.endswith(
            "); delete it, or use another --out"
        )
        assert "pickle" not in message


# ----------------------------------------------------------------------------------------------- open_run


def test_open_run_afresh_starts_at_trial_zero_in_a_new_folder(tmp_path):
    out = tmp_path / "run"
    assert study_io.open_run(out, SPEC, "native") == 0
    assert out.is_dir()


def test_open_run_resumes_at_the_checkpoints_trial_and_keeps_the_folder(tmp_path):
    study_io.save_checkpoint(tmp_path, SPEC, _checkpoint(), "native")
    _touch(tmp_path / "trials.parquet")
    assert study_io.open_run(tmp_path, SPEC, "native", resume=True) == 2
    assert _tree(tmp_path) == ["checkpoint.npz", "trials.parquet"]


def test_resume_without_a_checkpoint_is_refused(tmp_path):
    with pytest.raises(StudyError) as err:
        study_io.open_run(tmp_path, SPEC, "native", resume=True)
    assert str(err.value) == f"--resume: there is no checkpoint in {tmp_path}; run without --resume to start afresh"


def test_resume_on_another_backend_is_refused(tmp_path):
    study_io.save_checkpoint(tmp_path, SPEC, _checkpoint(), "native")
    with pytest.raises(StudyError) as err:
        study_io.resume_point(tmp_path, SPEC, "mjx")
    assert str(err.value) == (
        f"{tmp_path / 'checkpoint.npz'} was written on the native backend, this run would "
        f"use mjx: resume with --backend native (one run, one simulator)"
    )


def test_resume_of_another_study_names_the_field_that_differs(tmp_path):
    study_io.save_checkpoint(tmp_path, SPEC, _checkpoint(), "native")
    other = study_spec.StudySpec("other_study", num_trials=2, seeds=(0, 1))
    with pytest.raises(StudyError) as err:
        study_io.resume_point(tmp_path, other, "native")
    assert str(err.value) == (
        f"{tmp_path / 'checkpoint.npz'} was written by a different study definition (name "
        f"'files_test' there, 'other_study' here); use another --out, or --overwrite to start "
        f"afresh"
    )


# ----------------------------------------------------------------------------------------------- rows


def _optimizer_state(parameters: np.ndarray, num_stored: np.ndarray) -> bo.OptimizerState:
    """A batched optimizer state built by hand: (B, capacity, 2) parameters, nothing else stored."""
    batch, capacity = parameters.shape[:2]
    return bo.OptimizerState(
        parameters=parameters,
        contexts=np.zeros((batch, capacity, 2)),
        objectives=np.zeros((batch, capacity)),
        stored=np.arange(capacity)[None, :] < num_stored[:, None],
        records=(),
        num_stored=num_stored,
        target_velocity=np.zeros((batch, 0)),
        active_dims=np.ones((batch, 2), bool),
        schedule=(),
        inference_mode=np.zeros(batch, bool),
        gp_params=(),
        margins=(),
        margin_gp_params=(),
    )


def test_a_process_checkpoint_resumes_as_the_padded_batch(tmp_path):
    """3 instances padded to 4, capacity 3, after 1 trial: the checkpoint keeps the instances' first observation
    row; resumed, the padding row is the last instance's again and the rows past the trial are init's (zeros)."""
    parameters = np.array(
        [
            [[0.0, 1.0], [2.0, 3.0], [4.0, 5.0]],
            [[6.0, 7.0], [8.0, 9.0], [10.0, 11.0]],
            [[12.0, 13.0], [14.0, 15.0], [16.0, 17.0]],
            [[18.0, 19.0], [20.0, 21.0], [22.0, 23.0]],
        ]
    )
    state = _optimizer_state(parameters, np.array([1, 1, 1, 1], np.int32))
    sim = {"q": np.array([[10.0], [20.0], [30.0], [99.0]])}
    context = np.array([[0.1, 0.2], [0.3, 0.4], [0.5, 0.6], [9.0, 9.0]])
    ckpt = study_io.process_checkpoint(
        1, state, sim, context, [_log([1.0, 2.0, 3.0, 9.0])], (0, 3), 4.0, {"simulation_s": 1.0}
    )
    np.testing.assert_array_equal(ckpt.opt_leaves[0], [[[0.0, 1.0]], [[6.0, 7.0]], [[12.0, 13.0]]])
    np.testing.assert_array_equal(ckpt.sim_leaves[0], [[10.0], [20.0], [30.0]])
    np.testing.assert_array_equal(ckpt.context, [[0.1, 0.2], [0.3, 0.4], [0.5, 0.6]])
    np.testing.assert_array_equal(ckpt.logs[0].objective, [1.0, 2.0, 3.0])
    study_io.save_checkpoint(tmp_path, SPEC, ckpt, "native")

    fresh = _optimizer_state(np.zeros((4, 3, 2)), np.array([0, 0, 0, 0], np.int32))
    placement = study_placement.Placement(mesh=None, padded_size=4, rows=(0, 4))
    got = study_io.resume_checkpoint(tmp_path, SPEC, fresh, placement, batch_size=3)
    resumed = jax.tree.unflatten(jax.tree.structure(fresh), got.opt_leaves)
    np.testing.assert_array_equal(
        resumed.parameters,
        [
            [[0.0, 1.0], [0.0, 0.0], [0.0, 0.0]],
            [[6.0, 7.0], [0.0, 0.0], [0.0, 0.0]],
            [[12.0, 13.0], [0.0, 0.0], [0.0, 0.0]],
            [[12.0, 13.0], [0.0, 0.0], [0.0, 0.0]],
        ],
    )
    np.testing.assert_array_equal(resumed.stored, [[True, False, False]] * 4)
    np.testing.assert_array_equal(resumed.num_stored, [1, 1, 1, 1])
    np.testing.assert_array_equal(got.sim_leaves[0], [[10.0], [20.0], [30.0], [30.0]])
    np.testing.assert_array_equal(got.context, [[0.1, 0.2], [0.3, 0.4], [0.5, 0.6], [0.5, 0.6]])
    np.testing.assert_array_equal(got.logs[0].objective, [1.0, 2.0, 3.0, 3.0])
    assert got.trial == 1 and got.wall_s == 4.0 and got.timing == {"simulation_s": 1.0}


# ----------------------------------------------------------------------------------------------- trial table


def test_the_trial_table_reads_back_per_trial_and_instance(tmp_path):
    """Two instances (seeds 0 and 1) × two trials; element [t, b] of each column is instance b's trial t."""
    n, batch = 2, 2
    objective = np.array([[1.5, 2.5], [3.5, 4.5]], np.float32)  # [trial, instance]
    fields = {name: np.zeros((n, batch)) for name in study_io.TrialLog._fields}
    fields.update(
        params=np.zeros((n, batch, 8)),
        context=np.zeros((n, batch, 2)),
        velocity_xy_mps=np.zeros((n, batch, 2)),
        objective=objective,
        fell=np.array([[0.0, 1.0], [0.0, 0.0]]),
    )
    fields["params"][1, 0, 0] = 0.07
    result = types.SimpleNamespace(
        spec=SPEC,
        trials=study_io.TrialLog(**fields),
        walked=study_spec.conditions(SPEC),
        labels=study_spec.instances(SPEC),
    )
    path = study_io.write_trials(result, tmp_path / "trials.parquet")
    assert path == tmp_path / "trials.parquet"
    grids = study_io.read_trials(path)
    assert list(grids)[:7] == ["instance", "trial", "controller", "seed", "schedule", "data_reuse", "physics"]
    np.testing.assert_array_equal(grids["instance"], [[0, 1], [0, 1]])
    np.testing.assert_array_equal(grids["trial"], [[0, 0], [1, 1]])
    np.testing.assert_array_equal(grids["seed"], [[0, 1], [0, 1]])
    np.testing.assert_array_equal(grids["objective"], [[1.5, 2.5], [3.5, 4.5]])
    assert grids["objective"].dtype == np.float64 and grids["fell"].dtype == bool
    np.testing.assert_array_equal(grids["fell"], [[False, True], [False, False]])
    np.testing.assert_array_equal(grids["ground_clearance_m"], [[0.0, 0.0], [0.07, 0.0]])
    np.testing.assert_array_equal(grids["friction"], [[0.6, 0.6], [0.6, 0.6]])
    assert grids["controller"].tolist() == [["vmc_tegotae", "vmc_tegotae"]] * 2
