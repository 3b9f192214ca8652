"""studies/rough_terrain.py on hand-made trial tables: the difference of differences against SciPy's Welch test, and
the verdicts of an advantage that grows, one that is unchanged, and the context against eq. (14)'s thresholds."""

import importlib.util
import pathlib

import numpy as np
from scipy import stats as scipy_stats

SCRIPT = pathlib.Path(__file__).resolve().parents[2] / "studies" / "rough_terrain.py"
spec = importlib.util.spec_from_file_location("rough_terrain", SCRIPT)
rough_terrain = importlib.util.module_from_spec(spec)
spec.loader.exec_module(rough_terrain)

SEEDS, TRIALS = 12, 6


def test_the_difference_of_differences_is_welchs_test_where_two_groups_are_constant():
    rng = np.random.default_rng(1)
    a1, b1 = 1.0 + 0.3 * rng.standard_normal(9), 0.4 + 0.1 * rng.standard_normal(14)
    a0, b0 = np.full(5, 0.7), np.full(6, 0.2)  # no variance: the test is Welch's of a1 against b1
    effect = rough_terrain.difference_of_differences(a1, b1, a0, b0)
    np.testing.assert_allclose(effect.difference, np.mean(a1) - np.mean(b1) - 0.5, rtol=1e-12)
    welch = scipy_stats.ttest_ind(a1 - 0.5, b1, equal_var=False)
    np.testing.assert_allclose(effect.two_sided_p(), welch.pvalue, rtol=1e-10)


def _columns(j_by_group: dict[tuple[str, float], np.ndarray]) -> dict[str, np.ndarray]:
    """A (trials, instances) table: each run's J constant over its trials, CoT 0.5, no falls, contexts 30 N and
    0 rad plus the ground height (c_load 30 + 10·A N)."""
    controller, height, j = [], [], []
    for (c, a), values in j_by_group.items():
        controller += [c] * SEEDS
        height += [a] * SEEDS
        j += list(values)
    n = len(j)
    tile = lambda x: np.tile(np.asarray(x), (TRIALS, 1))  # noqa: E731
    return {
        "controller": tile(controller),
        "terrain_amplitude_m": tile(height),
        "objective": tile(j),
        "cost_of_transport": np.full((TRIALS, n), 0.5),
        "fell": np.zeros((TRIALS, n), bool),
        "failed": np.zeros((TRIALS, n), bool),
        "c_load_n": tile(30.0 + 10.0 * np.asarray(height)),
        "c_slope_rad": np.zeros((TRIALS, n)),
    }


def test_an_advantage_that_grows_and_one_that_does_not_change():
    rng = np.random.default_rng(2)
    noise = lambda: 0.01 * rng.standard_normal(SEEDS)  # noqa: E731
    groups = {}
    for a, vmc_gain in ((0.0, 0.1), (0.04, 0.6)):  # VMC's advantage grows by 0.5 on rough ground
        groups[("open_loop", a)] = 1.0 + noise()
        groups[("vmc", a)] = 1.0 + vmc_gain + noise()
        groups[("tegotae", a)] = 1.2 + noise()  # Tegotae's: 0.2 on either ground
        groups[("vmc_tegotae", a)] = 1.0 + noise()
    text = rough_terrain.advantage_table(_columns(groups))
    row = {
        tuple(cell.strip() for cell in line.split("|")[1:4]): line.split("|")[-2].strip()
        for line in text.splitlines()[2:]
    }
    assert row[("vmc", "0.04", "J")] == "grows"
    assert row[("tegotae", "0.04", "J")] == "unchanged"
    assert row[("vmc", "0.04", "CoT")] == "unchanged"  # CoT is 0.5 everywhere
    assert row[("vmc", "0", "J")] == "–"


def test_the_context_on_rough_ground_against_the_thresholds():
    groups = {(c, a): np.ones(SEEDS) for c in ("open_loop", "vmc") for a in (0.0, 0.5, 1.0)}
    text = rough_terrain.context_table(_columns(groups))
    lines = text.splitlines()
    assert "threshold ±8 N" in lines[0] and "threshold ±0.05 rad" in lines[0]
    assert "+5.000 [+5.000, +5.000] (inside the threshold)" in lines[3]  # 0.5 m: c_load +5 N
    assert "+10.000 [+10.000, +10.000] (not inside the threshold)" in lines[4]  # 1 m: +10 N
