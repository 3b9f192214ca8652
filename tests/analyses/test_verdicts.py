"""studies/verdicts.py: the rule (agrees / differs / inconclusive, Holm over a family) on effects made by hand, and
the whole script on a tiny study it reads back from its folder, against SciPy's tests recomputed from the trial
table."""

from __future__ import annotations

import importlib.util
import pathlib

import numpy as np
import pytest
from scipy import stats as scipy_stats

from cpgjax import ablation
from cpgjax.studies import driver as study_driver
from cpgjax.studies import registry, stats
from cpgjax.study import files as study_io

_SPEC = importlib.util.spec_from_file_location(
    "verdicts", pathlib.Path(__file__).resolve().parents[2] / "studies" / "verdicts.py"
)
verdicts = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(verdicts)


def _row(family, difference, se, margin=0.1, kind="figure"):
    return verdicts.Row(family, f"{difference}", "", "", stats.Effect(difference, se, 19.0), margin, "", kind)


def test_the_rule_and_holm_within_a_family():
    judged = verdicts.verdicts(
        [
            _row("a", 0.0, 0.01),  # 90 % interval ±0.017 inside ±0.1: agrees
            _row("a", 0.5, 0.05),  # far outside the margin, p ≈ 1e-9: differs
            _row("a", 0.05, 0.2),  # wide: neither
            _row("b", -0.3, 0.05, kind="claim_below"),  # the claimed direction, clearly: reproduced
            _row("b", 0.0, 0.01, margin=0.1, kind="claim_below"),  # an effect of −0.1 excluded: not reproduced
            _row("b", -0.05, 0.2, kind="claim_below"),
        ]
    )
    assert [v for *_, v in judged] == [
        "agrees",
        "differs",
        "inconclusive",
        "reproduced",
        "not reproduced",
        "inconclusive",
    ]
    # Holm within family a (3 tests): the differs row's two-sided p, raw ≈ 1e-9, is multiplied by 3 (the smallest)
    raw = 2 * scipy_stats.t.sf(0.5 / 0.05, 19.0)
    assert judged[1][2] == pytest.approx(3 * raw, rel=1e-6)


def test_a_difference_that_holm_takes_back_is_inconclusive():
    """Alone, p = 0.03 differs; in a family of three with two p = 1 it becomes 0.09."""
    se = 0.1 / scipy_stats.t.isf(0.015, 19.0)  # two-sided p = 0.03 for a difference of 0.1
    alone = verdicts.verdicts([_row("a", 0.1, se, margin=0.01)])
    family = verdicts.verdicts([_row("a", 0.1, se, margin=0.01), _row("a", 0.0, 1.0), _row("a", 0.0, 1.0)])
    assert alone[0][3] == "differs" and alone[0][2] == pytest.approx(0.03, rel=1e-6)
    assert family[0][3] == "inconclusive" and family[0][2] == pytest.approx(0.09, rel=1e-6)


def test_censored_counts_keep_the_runs_that_never_get_there():
    j = np.array([[0.0, 2.0, 0.0], [1.0, 2.0, 0.0], [2.0, 2.0, 0.0]])
    np.testing.assert_array_equal(verdicts.prospective_trials(j, 1.5), [3.0, 1.0, 4.0])


@pytest.mark.slow
def test_the_script_on_a_tiny_controller_study(tmp_path, capsys):
    """A 2-seed, 8-trial controller ablation (its study file at --quick, 8 trials) run by the engine, its trial table
    and metadata written as `cpgjax study` writes them, then `verdicts.py` on the folder: every figure of the paper's
    controller table and the three CoT claims, with the effect and p-values SciPy gives on the trial table's
    last-5-trial means."""
    out = tmp_path / "results" / "controller_ablation"
    out.mkdir(parents=True)
    result = ablation.Engine(study_driver.read("controller_ablation", quick=True, trials=8).spec).run()
    study_io.write_trials(result, out / "trials.parquet")
    study_io.write_metadata(result, out / "metadata.json")
    assert verdicts.main([str(tmp_path / "results")]) == 0
    text = capsys.readouterr().out
    lines = [line for line in text.splitlines() if line.startswith("| controller")]
    assert len(lines) == 12 + 3
    cols = study_io.read_trials(out / "trials.parquet")
    tegotae = cols["controller"][0] == "tegotae"
    cot = cols["cost_of_transport"][3:8, tegotae].mean(axis=0)
    mean, std = registry.PAPER_CONTROLLER_TABLE["tegotae"][1]
    p = scipy_stats.ttest_ind_from_stats(cot.mean(), cot.std(ddof=1), 2, mean, std, 5, equal_var=False).pvalue
    row = next(line for line in lines if "| tegotae CoT |" in line)
    assert f"{cot.mean() - mean:+.3f}" in row
    cells = [c.strip() for c in row.split("|")]
    table_rows = [r for r in verdicts.study_rows("controller_ablation", out) if r.family == "controller table"]
    raw = [r.tests()[1] for r in table_rows]
    index = [r.figure for r in table_rows].index("tegotae CoT")
    assert raw[index] == pytest.approx(p, rel=1e-9)
    assert float(cells[8]) == pytest.approx(stats.holm(raw)[index], rel=0.05)  # printed to 2 digits
    assert "Runs: controller_ablation at " in text
