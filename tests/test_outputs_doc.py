"""docs/outputs.md, the data dictionary, against what cpgjax writes: a column or key written but not documented fails
here (the per-tick log's schema, a parameter file) or in the test that writes the file (a study's and a robot's
trials.parquet, walk.parquet, metadata.json, run.json), each through :func:`undocumented`."""

import json
import pathlib
import re

import numpy as np

from cpgjax import hardware_io as hio
from cpgjax.deployment import tick_log
from cpgjax.trial import params as param_space
from cpgjax.trial import tuned

DOC = pathlib.Path(__file__).resolve().parent.parent / "docs" / "outputs.md"


def documented(section: str) -> set[str]:
    """The names in the first cells of the table below ``<!-- columns: section -->`` (or ``keys:``) in
    docs/outputs.md; a row naming "the 8 CPG parameters" stands for their names."""
    lines = DOC.read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if re.fullmatch(rf"<!-- (columns|keys): {re.escape(section)} -->",
                                                                    line))
    names: set[str] = set()
    for line in lines[start + 3:]:
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
    tuned.save(path, param_space.midpoint(), dict.fromkeys(tuned.TUNED_FOR), objective=1.0, trial=0, instance=0,
               seed=0, study="friction")
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
    assert cli.main(["walk", "--controllers", "vmc,tegotae", "--trials", "3", "--backend", "native", "--out",
                     str(out)]) == 0
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
    summary, _ = walk.walk(controllers=("vmc", "tegotae"), num_trials=3, backend="native", physics=("paper",),
                           trial_config=short, progress=lambda _: None)
    for w, row in enumerate(summary):  # the same simulation: each walk's last trial
        assert row.objective == rows["objective"][3 * w + 2] and row.falls == sum(rows["fell"][3 * w:3 * w + 3])
