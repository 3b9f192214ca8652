"""studies/gait_speeds.py on a hand-made trial table: the tracking rule, the cheapest walking gait at each speed, and
its tests against SciPy with Holm's correction done by hand."""

import importlib.util
import pathlib

import numpy as np
import pytest
from scipy import stats as scipy_stats

SCRIPT = pathlib.Path(__file__).resolve().parents[2] / "studies" / "gait_speeds.py"
spec = importlib.util.spec_from_file_location("gait_speeds", SCRIPT)
gait_speeds = importlib.util.module_from_spec(spec)
spec.loader.exec_module(gait_speeds)

SEEDS = 6
TRIALS = 8


def _columns(finals: dict[tuple[str, float], tuple[np.ndarray, np.ndarray, np.ndarray]]) -> dict[str, np.ndarray]:
    """A (trials, instances) table whose last 5 trials hold each instance's final v_x, CoT and falls (earlier
    trials hold values that must not count)."""
    gait, target, vx, cot, fell = [], [], [], [], []
    for (g, v), (v_final, cot_final, fell_final) in finals.items():
        for s in range(SEEDS):
            gait.append(g)
            target.append(v)
            vx.append(np.r_[np.full(TRIALS - 5, 9.0), np.full(5, v_final[s])])
            cot.append(np.r_[np.full(TRIALS - 5, 99.0), np.full(5, cot_final[s])])
            fell.append(np.r_[np.ones(TRIALS - 5, bool), [False] * 4, [bool(fell_final[s])]])
    n = len(gait)
    return {
        "gait": np.tile(np.array(gait), (TRIALS, 1)),
        "target_velocity_mps": np.tile(np.array(target), (TRIALS, 1)),
        "velocity_x_mps": np.array(vx).T,
        "cost_of_transport": np.array(cot).T,
        "fell": np.array(fell).T,
        "failed": np.zeros((TRIALS, n), bool),
    }


def test_the_cheapest_walking_gait_and_its_corrected_tests():
    rng = np.random.default_rng(0)
    ok = np.zeros(SEEDS, bool)
    trot_cot, walk_cot = 0.5 + 0.02 * rng.standard_normal(SEEDS), 0.8 + 0.02 * rng.standard_normal(SEEDS)
    pace_cot = 0.52 + 0.02 * rng.standard_normal(SEEDS)
    columns = _columns(
        {
            ("trot", 0.3): (np.full(SEEDS, 0.31), trot_cot, ok),
            ("walk", 0.3): (np.full(SEEDS, 0.29), walk_cot, ok),
            ("pace", 0.3): (np.full(SEEDS, 0.33), pace_cot, ok),
            # pronk: two seeds off target by 0.06 m/s and two falling in their last trial: 2 of 6 track,
            # it does not walk
            ("pronk", 0.3): (np.r_[0.36, 0.36, 0.3, 0.3, 0.3, 0.3], np.full(SEEDS, 0.1), np.r_[0, 0, 1, 1, 0, 0]),
        }
    )
    cells = {c.gait: c for c in gait_speeds.cells(columns)}
    assert [int(c.tracks.sum()) for c in cells.values()] == [6, 6, 6, 2] and not cells["pronk"].walks
    # the first TRIALS − 5 trials fell in every seed, and pronk's seeds 2 and 3 in their last trial too
    np.testing.assert_allclose(cells["pronk"].fall_fraction, (TRIALS - 5 + np.r_[0, 0, 1, 1, 0, 0]) / TRIALS)
    (best,), holm = gait_speeds.cheapest_by_speed(list(cells.values()))
    assert best.gait == "trot" and [r[0] for r in best.rivals] == ["walk", "pace"]
    raw = [scipy_stats.ttest_ind(trot_cot, other, equal_var=False).pvalue for other in (walk_cot, pace_cot)]
    np.testing.assert_allclose([r[2] for r in best.rivals], raw, rtol=1e-10)
    first, second = sorted(raw)
    by_hand = {first: min(1, 2 * first), second: max(min(1, 2 * first), min(1, second))}
    np.testing.assert_allclose(holm, [by_hand[p] for p in raw], rtol=1e-10)
    text = gait_speeds.table(list(cells.values()))
    assert "| pronk | 0.3 | 2/6 |" in text
    verdict = text.splitlines()[-1]
    assert verdict.startswith("| 0.3 | trot |")
    assert verdict.endswith("| cheapest |" if max(holm) < 0.05 else "| not shown cheaper than pace |")


def test_no_interval_below_three_tracking_seeds():
    """Two tracking seeds give a mean and no interval (and no gait that walks the speed to compare)."""
    ok = np.zeros(SEEDS, bool)
    two_track = np.r_[0.3, 0.3, 0.5, 0.5, 0.5, 0.5]
    columns = _columns({("bound", 0.3): (two_track, np.r_[0.8, 1.0, 5, 5, 5, 5], ok)})
    (cell,) = gait_speeds.cells(columns)
    ci = gait_speeds.bootstrap_ci(cell.cot[cell.tracks])
    assert ci.mean == pytest.approx(0.9) and np.isnan(ci.low) and np.isnan(ci.high)
    text = gait_speeds.table([cell])
    assert "| bound | 0.3 | 2/6 |" in text and "0.900 (no interval below 3 seeds)" in text
    assert text.splitlines()[-1] == "| 0.3 | no gait walks it | – | – |"
