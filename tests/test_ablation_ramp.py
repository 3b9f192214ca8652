"""The continuous ramp's walk (docs/decisions.md §4, ``study.spec.walked``): each trial on the ramp starts on the
ramp's slope at the distance its instance has climbed since it reached the ramp; a trial climbs its steady-phase
distance scaled to the whole trial, sliding back lowers it down to the bottom, a fall puts it back at the bottom.
Checked against slopes worked out by hand and against a NumPy transcription of that rule, one instance at a time."""

from __future__ import annotations

import numpy as np

from cpgjax.study import spec as study_spec
from cpgjax.trial import protocol

RAMP = study_spec.Ramp(start_deg=10.0, end_deg=20.0, length_m=3.0)
TRIAL = protocol.TrialConfig(transition_steps=1500, steady_steps=3000)  # a trial climbs 4.5 / 3 its distance


def planned(slope_deg, ramp) -> study_spec.Conditions:
    """Conditions of (B, n) slopes and ramp flags, the other fields constant."""
    slope_deg = np.asarray(slope_deg, np.float64)
    shape = slope_deg.shape
    return study_spec.Conditions(
        friction=np.full(shape, 0.6),
        slope_deg=slope_deg,
        payload_kg=np.zeros(shape),
        target_velocity_mps=np.full(shape, 0.5),
        inference=np.ones(shape, bool),
        ramp=np.asarray(ramp, bool),
        mass_scale=np.ones(shape),
        latency_ticks=np.full(shape, -1, np.int64),
        noise_scale=np.full(shape, -1.0),
    )


# Two instances, 5 trials, on the ramp from trial 1; the planned slope of a ramp trial (7°) is never walked.
PLANNED = planned(
    [[5.0, 7.0, 7.0, 7.0, 7.0], [5.0, 7.0, 7.0, 7.0, 7.0]],
    [[False, True, True, True, True], [False, True, True, True, True]],
)
DISTANCE_M = np.array([[0.5, 0.5], [1.0, 2.5], [0.5, 1.0], [-2.0, 0.25]], np.float32)  # (trials, B)
FELL = np.array([[0, 0], [0, 0], [0, 1], [0, 0]], np.float32)
# Instance 0: trial 0 is off the ramp (its 0.5 m do not count); 1.0 m → 1.5 m climbed: 15°; + 0.75 m = 2.25 m: 17.5°;
# 2.0 m back slides below the bottom: 10°. Instance 1: 2.5 m → 3.75 m, past the top: 20°; trial 2 falls: back at the
# bottom, 10°; 0.25 m → 0.375 m: 11.25°.
WALKED_DEG = np.array([[5.0, 10.0, 15.0, 17.5, 10.0], [5.0, 10.0, 20.0, 10.0, 11.25]])


def test_the_ramp_walks_the_slopes_worked_out_by_hand():
    walked = study_spec.walked(PLANNED, RAMP, DISTANCE_M, FELL, TRIAL)
    np.testing.assert_allclose(walked.slope_deg, WALKED_DEG, rtol=0, atol=1e-12)
    for field in study_spec.Conditions._fields:  # the walk changes the ramp's slopes only
        if field != "slope_deg":
            np.testing.assert_array_equal(getattr(walked, field), getattr(PLANNED, field))


def test_the_trials_done_give_the_slopes_up_to_the_next_and_the_plan_stays():
    before = PLANNED.slope_deg.copy()
    for done in range(len(DISTANCE_M) + 1):
        walked = study_spec.walked(PLANNED, RAMP, DISTANCE_M[:done], FELL[:done], TRIAL)
        np.testing.assert_allclose(walked.slope_deg[:, : done + 1], WALKED_DEG[:, : done + 1], rtol=0, atol=1e-12)
        np.testing.assert_array_equal(walked.slope_deg[:, done + 1 :], PLANNED.slope_deg[:, done + 1 :])
    np.testing.assert_array_equal(PLANNED.slope_deg, before)  # the planned conditions are not written


def test_without_a_ramp_the_walk_is_the_plan():
    flat = PLANNED._replace(ramp=np.zeros_like(PLANNED.ramp))
    assert study_spec.walked(flat, None, DISTANCE_M, FELL, TRIAL) is flat
    assert study_spec.walked(flat, RAMP, DISTANCE_M, FELL, TRIAL) is flat


def _transcribed(slope_deg, on, distance_m, fell, ramp, trial) -> np.ndarray:
    """docs/decisions.md §4, one instance and one trial at a time."""
    scale = (trial.transition_steps + trial.steady_steps) / trial.steady_steps
    out = np.array(slope_deg, np.float64)
    for b in range(out.shape[0]):
        climbed = 0.0  # since the instance reached the ramp
        for t in range(out.shape[1]):
            if on[b, t]:
                out[b, t] = ramp.start_deg + (ramp.end_deg - ramp.start_deg) * min(climbed / ramp.length_m, 1.0)
            if t == len(distance_m):
                break
            climbed = 0.0 if not on[b, t] or fell[t, b] else max(climbed + scale * float(distance_m[t, b]), 0.0)
    return out


def test_the_ramp_follows_a_numpy_transcription_of_the_rule():
    rng = np.random.default_rng(3)
    batch, n = 16, 30
    trial = protocol.TrialConfig(transition_steps=100, steady_steps=200)
    ramp = study_spec.Ramp(start_deg=2.0, end_deg=6.0, length_m=4.0)
    on = rng.random((batch, n)) < 0.7  # instances leave the ramp and reach it again
    plan = planned(rng.uniform(-5.0, 5.0, (batch, n)), on)
    distance_m = rng.uniform(-0.3, 1.0, (n, batch)).astype(np.float32)
    fell = (rng.random((n, batch)) < 0.15).astype(np.float32)
    for done in (0, 1, 7, n):
        walked = study_spec.walked(plan, ramp, distance_m[:done], fell[:done], trial)
        expected = _transcribed(plan.slope_deg, on, distance_m[:done], fell[:done], ramp, trial)
        np.testing.assert_allclose(walked.slope_deg, expected, rtol=0, atol=1e-12)
    assert (walked.slope_deg[on] > ramp.start_deg).any() and (walked.slope_deg[on] == ramp.end_deg).any()
