"""docs/outputs.md, the data dictionary, against what cpgjax writes: a column or key written but not documented fails
here (the per-tick log's schema, a parameter file) or in the test that writes the file (a study's and a robot's
trials.parquet, walk.parquet, metadata.json, run.json), each through :func:`undocumented`."""

import json
import pathlib
import re

import numpy as np

import cpgjax
from cpgjax import hardware_io as hio
from cpgjax.deployment import tick_log
from cpgjax.trial import params as param_space
from cpgjax.trial import tuned

DOC = pathlib.Path(__file__).resolve().parent.parent / "docs" / "outputs.md"


def documented(section: str) -> set[str]:
    """The names in the first cells of the table below ``<!-- columns: section -->`` (or ``keys:``) in
    docs/outputs.md; a row naming "the 8 CPG parameters" stands for their names."""
    lines = DOC.read_text().splitlines()
    start = next(
        i for i, line in enumerate(lines) if re.fullmatch(rf"<!-- (columns|keys): {re.escape(section)} -->", line)
    )
    names: set[str] = set()
    for line in lines[start + 3 :]:
        if not line.startswith("|"):
            break
        first = line.split("|")[1]
        names |= set(re.findall(r"`([^`]+)`", first))
        if "the 8 CPG parameters" in first:
            names |= set(param_space.PARAM_NAMES)
    return names


def undocumented(section: str, written) -> list[str]:
    """The names in ``written`` that docs/outputs.md's ``section`` does not document."""
    return sorted(set(written) - documented(section))


def test_every_tick_log_column_is_documented_with_its_phase_codes():
    assert undocumented("ticks.arrows", tick_log.schema().names) == []
    phase_row = next(line for line in DOC.read_text().splitlines() if line.startswith("| `phase` |"))
    assert ", ".join(f"{i} {name}" for i, name in enumerate(hio.PHASE_NAMES)) in phase_row


def test_every_parameter_file_key_is_documented(tmp_path):
    path = tmp_path / "best_params.json"
    tuned.save(
        path,
        param_space.midpoint(),
        dict.fromkeys(tuned.TUNED_FOR),
        objective=1.0,
        trial=0,
        instance=0,
        seed=0,
        study="friction",
    )
    assert undocumented("best_params.json", json.loads(path.read_text())) == []
    assert tuned.load(path).tuned_for == {}  # nulls: nothing recorded
    np.testing.assert_allclose(tuned.load(path).params, param_space.midpoint())


def test_the_parser_reads_the_tables():
    """The test's own reader: it finds names in the first cell only, and expands the parameters' row."""
    study = documented("study trials.parquet")
    assert {"objective", "velocity_x_mps", "velocity_y_mps", "context_changed"} <= study
    assert "unit" not in study and "m/s" not in study
    assert set(param_space.PARAM_NAMES) <= documented("robot trials.parquet")


def test_walk_out_writes_every_trial_documented(tmp_path, capsys, monkeypatch):
    """A real short walk through the command line (C MuJoCo, 0.1 s + 0.2 s trials): walk.parquet has a row per trial
    with documented columns, the printed table labels every trial, and the last-trial summary of ``walk.walk``
    agrees with its last rows."""
    import functools

    import pyarrow as pa
    import pyarrow.parquet as pq

    from cpgjax import cli
    from cpgjax.sim import walk
    from cpgjax.trial import protocol

    short = protocol.TrialConfig(transition_steps=100, steady_steps=200)
    monkeypatch.setattr(walk, "walk_trials", functools.partial(walk.walk_trials, trial_config=short))
    out = tmp_path / "walk"
    assert (
        cli.main(["walk", "--controllers", "vmc,tegotae", "--trials", "3", "--backend", "native", "--out", str(out)])
        == 0
    )
    printed = capsys.readouterr().out
    assert "| walk | trial | controller |" in printed and "| 1 | 2 | tegotae |" in printed
    table = pq.read_table(out / "walk.parquet")
    assert table.num_rows == 6 and undocumented("walk.parquet", table.schema.names) == []
    assert {str(f.type) for f in table.schema if pa.types.is_floating(f.type)} == {"double"}
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["study"] == "walk" and undocumented("metadata.json", meta) == []
    rows = table.to_pydict()
    assert rows["trial"] == [0, 1, 2, 0, 1, 2] and rows["controller"] == ["vmc"] * 3 + ["tegotae"] * 3
    assert cli.main(["show", str(out)]) == 0 and "a `cpgjax walk` folder" in capsys.readouterr().out
    summary, _ = walk.walk(
        controllers=("vmc", "tegotae"),
        num_trials=3,
        backend="native",
        physics=("paper",),
        trial_config=short,
        progress=lambda _: None,
    )
    for w, row in enumerate(summary):  # the same simulation: each walk's last trial
        assert row.objective == rows["objective"][3 * w + 2] and row.falls == sum(rows["fell"][3 * w : 3 * w + 3])


# ----------------------------------------------------------------------------------------------- the catalogue


def _owners() -> dict[str, tuple]:
    """cpgjax module (dotted, below ``cpgjax``) → the entries it declares (its ``OUTPUTS``)."""
    import importlib

    package = pathlib.Path(cpgjax.__file__).parent
    found = {}
    for path in sorted(package.rglob("*.py")):
        name = ".".join(path.relative_to(package).with_suffix("").parts)
        if re.search(r"^OUTPUTS = ", path.read_text(), re.M):
            found[name] = importlib.import_module(f"cpgjax.{name}").OUTPUTS
    return found


def test_the_catalogue_gathers_every_writers_entries_once():
    from cpgjax import show

    owners = _owners()
    assert {"outputs", "study.files", "sim.walk", "deployment.tick_log", "studies.video"} <= set(owners)
    assert sorted(e.name for entries in owners.values() for e in entries) == sorted(e.name for e in show.catalogue())
    names = [e.name for e in show.catalogue()]
    assert len(names) == len(set(names)) and all(e.meaning for e in show.catalogue())


def _file_table() -> dict[str, str]:
    """The names in the first cells of docs/outputs.md's table of files → the row's "holds" cell."""
    lines = DOC.read_text().splitlines()
    start = lines.index("| file | written by | holds |") + 2
    rows = {}
    for line in lines[start:]:
        if not line.startswith("|"):
            break
        cells = line.split("|")
        rows |= dict.fromkeys(re.findall(r"`([^`]+)`", cells[1]), cells[3].strip())
    return rows


def test_docs_outputs_names_exactly_the_catalogues_files():
    """Every catalogue entry is documented with what it holds, and docs/outputs.md names no file the catalogue
    lacks."""
    from cpgjax import show

    table = _file_table()
    assert sorted(set(table)) == sorted(e.name for e in show.catalogue())
    assert all(table.values())


def _example(name: str) -> str:
    """A file name of an entry's family (``NAME.air.ticks.arrows`` → ``go1_calibration.air.ticks.arrows``)."""
    for family, example in (
        ("<rank>of<N>.t<trial>", "0of2.t3"),
        ("<group>", "tegotae"),
        ("NAME", "go1_calibration"),
        ("*", "learning_curves"),
    ):
        name = name.replace(family, example)
    return name


def test_each_entry_matches_its_own_files_exact_names_first():
    from cpgjax import outputs, show
    from cpgjax.deployment import calibrate
    from cpgjax.studies import figures

    entries = show.catalogue()
    for e in entries:
        assert outputs.entry_of(_example(e.name).split("/")[0], entries) == e, e.name
    assert outputs.entry_of(figures.SUMMARY, entries).name == "*.png"  # a figure, by its family
    assert outputs.entry_of(tick_log.FILE_NAME, entries).name == tick_log.FILE_NAME  # not a calibration stand's log
    assert outputs.entry_of("go1_calibration.air.ticks.arrows", entries) == calibrate.STAND_LOGS["air"]
    assert outputs.entry_of("notes.txt", entries) is None


def test_overwrite_removes_every_catalogue_file_and_no_other(tmp_path):
    """``--overwrite`` (``claim_folder``) and the catalogue agree: each catalogue file in a folder is removed, and
    each name claim_folder takes as cpgjax's is a catalogue entry. A calibration's stand logs are the exception: they
    lie beside the calibration file ``deploy calibrate --out`` names, which guards each with ``claim_file``."""
    from cpgjax import show
    from cpgjax.deployment import calibrate
    from cpgjax.study import files as study_io

    out = tmp_path / "run"
    (out / study_io.BEST_PARAMS).mkdir(parents=True)
    for e in show.catalogue():
        if e not in calibrate.OUTPUTS:
            (out / _example(e.name)).write_text("{}")
    assert study_io.claim_folder(out, overwrite=True) == out and list(out.iterdir()) == []
    exact = {e.name for e in show.catalogue() if e.pattern is None}
    assert sorted(study_io.OUTPUT_FILES - exact) == []
    assert sorted(exact - study_io.OUTPUT_FILES) == []


def test_the_checks_find_each_kind_of_damage(tmp_path):
    from cpgjax import outputs

    cases = {
        "a.json": (b"{", None),
        "b.png": (b"GIF89a", "not a PNG image"),
        "c.mp4": (b"\0\0\0\x18ftypisom", "not a complete MP4 video"),
        "d.rrd": (outputs.RRD_MAGIC + bytes(40), "truncated (no rerun footer"),
        "e.rrd": (b"RIFF" + bytes(40), "not a rerun recording"),
    }
    checks = {
        ".json": outputs.check_json,
        ".png": outputs.check_png,
        ".mp4": outputs.check_mp4,
        ".rrd": outputs.check_recording,
    }
    for name, (data, problem) in cases.items():
        path = tmp_path / name
        path.write_bytes(data)
        check = checks[path.suffix]
        if problem is None:
            try:
                check(path)
                raise AssertionError(f"{name} read back")
            except ValueError:
                pass
        else:
            assert check(path).startswith(problem), name
    good = tmp_path / "good.rrd"
    good.write_bytes(outputs.RRD_MAGIC + bytes(40) + outputs.RRD_FOOTER + bytes(4))
    assert outputs.check_recording(good) is None


def test_no_file_name_is_written_out_outside_its_owner():
    """A catalogue file's name appears as a string literal only in the module that declares it (the others use its
    constant); ``study.files`` names the files of the writers it cannot import, for ``--overwrite``."""
    import ast

    from cpgjax.deployment import deploy
    from cpgjax.deployment import trials as robot_trials
    from cpgjax.studies import transfer

    package = pathlib.Path(cpgjax.__file__).parent
    owner = {e.name: module for module, entries in _owners().items() for e in entries if e.pattern is None}
    beyond_its_imports = {
        tick_log.FILE_NAME,
        tick_log.RUN_FILE,
        deploy.TRUTH_FILE,
        deploy.CALIBRATION_FILE,
        robot_trials.RECORDING,
        transfer.EVALUATIONS,
    }
    found = []
    for path in sorted(package.rglob("*.py")):
        module = ".".join(path.relative_to(package).with_suffix("").parts)
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Constant) and node.value in owner and owner[node.value] != module:
                if not (module == "study.files" and node.value in beyond_its_imports):
                    found.append(f"{path.relative_to(package.parent)}:{node.lineno}: {node.value!r}")
    assert found == []
