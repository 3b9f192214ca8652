"""Why `paper` misses the paper's slope and 15 kg results: each hypothesis as a run that changes one thing and keeps
everything else (docs/REPRODUCTION.md, "Measured causes").

The population: the mid-range parameters and ``--sets`` parameter sets drawn uniformly from the paper's box (seeded,
the same sets in every run), VMC+Tegotae, C MuJoCo, v* = 0.5 m/s. Each set walks one settling trial from standing,
then ``--measured`` trials back to back; the measured trials are reported. A variant of the `paper` profile is the
profile with one field replaced, registered under its own name for the run. Paired comparisons (the same sets under
both settings): the mean difference with its 95 % interval and the Wilcoxon signed-rank p.

    python studies/paper_misses.py [--sets 32] [--measured 3]
        [--only signal,contact,start,search,floor,load,imu,placement,slope_signal]

Experiments:
  signal   the foot-force signal (c_load and the walk) as the unitree_ros plugin computes it (the mean over the update's
           in-contact steps, `paper`) against the 100 Hz sample of one step, and the 1 kHz signal's jaggedness;
           c_load's spread within one condition against the same-context tolerance t_load·r_load = 8 N
  contact  the stiff contact and the missing armature at 15 kg and 10°: `paper` against `paper` with MuJoCo's default
           soft contact, and against `paper` with the go1 profile's reflected rotor inertia
  start    a trial started from standing (as after a fall) against one that follows a walking trial
  search   how many of the box's parameter sets carry 15 kg / climb 10°, 12.5° (a walk: no fall, J ≥ 1.5):
           the probability with its exact interval, and the expected trials of a random search to find one
  floor    the share of 15 kg trials whose J is exactly the floor −1 without a fall, and the J they would have had
  load     torque saturation and the trunk's height under 0 / 7.5 / 15 kg, and the joint PD's K_p × 1.5 as a
           diagnostic (is the paper's K_p what lets the loaded legs sag?)
  imu      a slope as rotated gravity (ours) against an inclined floor under vertical gravity: the IMU pitch and
           the foot forces of the robot standing 1 s under joint PD
  placement  where the 15 kg (and 7.5 kg) payload sits, which the paper does not say: cpgjax's box at the trunk's
           centre of mass against a point mass there (a raised URDF trunk mass, its inertia unchanged) and against
           the same box resting on the trunk's top
  slope_signal  the foot-force signal on 10° and 12.5°: the plugin's mean (`paper`) against the 100 Hz sample of one
           step, the profile's only change between the slope runs before and after the plugin was modelled (the slope
           study's floor is μ 0.6, where Gazebo's friction rule changes nothing)
"""

from __future__ import annotations

import argparse
import contextlib
from importlib import resources

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from cpgjax import cpg
from cpgjax.go1 import attitude, physics, sensors
from cpgjax.go1 import model as go1_model
from cpgjax.sim import native
from cpgjax.studies import stats
from cpgjax.study import placement as study_placement
from cpgjax.trial import objective, params, protocol

TARGET_MPS = 0.5
WALK_J = 1.5  # "carries the load / climbs": no fall and J at least this (a walking gait scores 1.5 … 2.3)
SAME_CONTEXT_N = 0.2 * 40.0  # t_load · r_load (paper, appendix "Contextual BO")
IDS = go1_model.indices()
VARIANTS = {
    "paper_sampled": dict(foot_force_contact_mean=False),  # the force of the 100 Hz update step only
    "paper_no_layer": dict(foot_contact_layer_m=0.0),  # the plugin's mean over the steps the foot penetrates
    "paper_1khz": dict(foot_force_contact_mean=False, foot_force_period_ticks=1),  # the calf-frame z every step
    "paper_soft_contact": dict(
        floor_solref=physics.get("soft").floor_solref, floor_solimp=physics.get("soft").floor_solimp
    ),
    "paper_armature": dict(armature_kg_m2=physics.get("go1").armature_kg_m2),
}


def register_variants() -> None:
    for name, fields in VARIANTS.items():
        physics.PROFILES[name] = physics.get("paper")._replace(**fields)


def population(sets: int) -> np.ndarray:
    """(sets + 1, 8): the mid-range parameters, then ``sets`` uniform draws from the box (seed 0)."""
    draws = params.from_unit(np.random.default_rng(0).uniform(size=(sets, params.NUM_PARAMS)))
    return np.concatenate([params.midpoint()[None], draws])


def walk(
    p: np.ndarray,
    profile: str,
    *,
    payload_kg=0.0,
    slope_deg=0.0,
    settle=1,
    measured=3,
    cpg_config: cpg.CPGConfig = cpg.CPGConfig(),
) -> dict:
    """Each set of ``p`` (S, 8) under one setting: ``settle`` trials from standing, then ``measured`` back-to-back
    trials. Returns arrays (measured, S): v_x, J, CoT, c_load, c_slope, saturation, fell, and the un-floored J."""
    scenario = go1_model.make_scenarios(payload_kg=[payload_kg] * len(p), slope_deg=slope_deg, physics=profile)
    sim = native.NativeBackend(scenario, cpg_config)
    gates = protocol.batch_gates(["vmc_tegotae"] * len(p))
    state = sim.reset(p)
    out = {k: [] for k in ("v", "j", "cot", "c_load", "c_slope", "saturation", "fell", "j_raw")}
    for t in range(settle + measured):
        state, record = sim.trial(state, p, gates)
        if t < settle:
            continue
        r = study_placement.fetch(record)
        j = np.asarray(jax.vmap(objective.objective, in_axes=(0, None))(r, np.float32(TARGET_MPS)))
        raw = np.asarray(
            jax.vmap(objective.velocity_reward, in_axes=(0, None))(r, np.float32(TARGET_MPS))
        ) - objective.COT_WEIGHT * np.asarray(objective.cost_of_transport(r))
        for k, v in (
            ("v", np.asarray(objective.mean_velocity(r))[:, 0]),
            ("j", j),
            ("cot", objective.cost_of_transport(r)),
            ("c_load", r.c_load_n),
            ("c_slope", r.c_slope_rad),
            ("saturation", r.saturation_fraction),
            ("fell", r.fell),
            ("j_raw", raw),
        ):
            out[k].append(np.asarray(v, np.float64))
    sim.physics.close()
    return {k: np.stack(v) for k, v in out.items()}


def summary(name: str, w: dict) -> str:
    walking = (w["fell"] == 0) & (w["j"] >= WALK_J)
    return (
        f"| {name} | {int(w['fell'].sum())}/{w['fell'].size} | {stats.mean_ci(w['v'])} | {stats.mean_ci(w['j'])} | "
        f"{stats.nonnegative_ci(np.where(w['fell'] > 0, np.nan, w['cot']))} | {walking.mean():.2f} | "
        f"{100 * w['saturation'].mean():.2f} |"
    )


def paired_line(what: str, a: dict, b: dict) -> str:
    """Per-set means of J and v under two settings, compared on the same sets."""
    cj = stats.paired_text(a["j"].mean(0), b["j"].mean(0))
    cv = stats.paired_text(a["v"].mean(0), b["v"].mean(0))
    return f"- {what}: J {cj}; v_x {cv}"


HEADER = (
    "| setting | falls / trials | v_x [m/s] (95 % CI) | J | CoT (no fall) | share walking (J ≥ 1.5) | "
    "torque saturation [% of joint-ticks] |\n|---|---|---|---|---|---|---|"
)


def signal(p, measured) -> None:
    print("\n## signal: the foot-force signal\n")
    print(
        "| payload [kg] | signal | c_load mean [N] | spread within a set (std over its trials) [N] | "
        "consecutive trials > 8 N apart | v_x | J | falls |\n|---|---|---|---|---|---|---|---|"
    )
    for payload in (0.0, 7.5, 15.0):
        for profile, label in (
            ("paper", "plugin: mean over the steps within the 1 mm contact layer"),
            ("paper_no_layer", "plugin: mean over the steps the foot penetrates (no layer)"),
            ("paper_sampled", "the force of one step per 10 ms"),
            ("paper_1khz", "every step (1 kHz)"),
        ):
            w = walk(p, profile, payload_kg=payload, measured=measured)
            ok = w["fell"] == 0
            c = np.where(ok, w["c_load"], np.nan)
            spread = np.nanstd(c, axis=0)
            jumps = np.abs(np.diff(c, axis=0)) > SAME_CONTEXT_N
            valid = np.isfinite(np.diff(c, axis=0))
            print(
                f"| {payload:g} | {label} | {stats.mean_ci(c)} | {np.nanmean(spread):.2f} | "
                f"{int(jumps[valid].sum())}/{int(valid.sum())} | {stats.mean_ci(w['v'])} | {stats.mean_ci(w['j'])} | "
                f"{int(w['fell'].sum())}/{w['fell'].size} |"
            )
    print("\nThe 1 kHz calf-frame z of the mid-range gait over 3 s after a settling trial (0 and 15 kg):\n")
    print(
        "| payload [kg] | profile | mean [N] | mean abs. change per step [N] | max [N] | "
        "10 ms windows with contact that also have steps without |\n|---|---|---|---|---|---|"
    )
    for payload in (0.0, 15.0):
        for profile in ("paper_1khz", "soft"):
            scenario = go1_model.make_scenarios(payload_kg=payload, physics=profile)
            sim = native.NativeBackend(scenario)
            mid, gates = params.midpoint()[None], protocol.batch_gates(["vmc_tegotae"])
            state, _ = sim.trial(sim.reset(mid), mid, gates)
            _, log = sim.rollout(state, mid, gates, 3000)
            sim.physics.close()
            f = np.asarray(log.foot_force_n)[0]
            label = "soft (its normal force)" if profile == "soft" else "paper (calf-frame z)"
            windows = (f > 0).reshape(-1, 10, 4)
            touching = windows.any(axis=1)
            gaps = (windows.mean(axis=1) < 1.0)[touching].mean()
            print(
                f"| {payload:g} | {label} | {f.mean():.1f} | {np.abs(np.diff(f, axis=0)).mean():.2f} | "
                f"{f.max():.0f} | {gaps:.2f} |"
            )


def contact(p, measured) -> None:
    print("\n## contact: stiff contact and armature\n")
    for payload, slope in ((15.0, 0.0), (0.0, 10.0)):
        print(f"\n{payload:g} kg, {slope:g}°:\n\n{HEADER}")
        runs = {
            name: walk(p, name, payload_kg=payload, slope_deg=slope, measured=measured)
            for name in ("paper", "paper_soft_contact", "paper_armature")
        }
        for name, w in runs.items():
            print(summary(name, w))
        print()
        for name in ("paper_soft_contact", "paper_armature"):
            print(paired_line(f"{name} − paper", runs[name], runs["paper"]))


def start(p, measured) -> None:
    print("\n## start: from standing against after a walking trial\n")
    for payload, slope in ((15.0, 0.0), (0.0, 10.0)):
        print(f"\n{payload:g} kg, {slope:g}°:\n\n{HEADER}")
        fresh = walk(p, "paper", payload_kg=payload, slope_deg=slope, settle=0, measured=1)
        after = walk(p, "paper", payload_kg=payload, slope_deg=slope, settle=1, measured=1)
        print(summary("first trial from standing", fresh))
        print(summary("trial after a walking trial", after))
        print()
        print(paired_line("from standing − after a trial", fresh, after))


def search(p, measured) -> None:
    print("\n## search: parameter sets in the box that walk\n")
    print(
        "| condition | sets walking (no fall, J ≥ 1.5 in every measured trial) | probability (95 % CI) | "
        "expected random-search trials (CI) |\n|---|---|---|---|"
    )
    for payload, slope in ((0.0, 0.0), (15.0, 0.0), (0.0, 10.0), (0.0, 12.5)):
        w = walk(p, "paper", payload_kg=payload, slope_deg=slope, measured=measured)
        ok = ((w["fell"] == 0) & (w["j"] >= WALK_J)).all(axis=0)
        ci = stats.proportion_ci(int(ok.sum()), ok.size)
        expected = (
            "never seen" if ci.mean == 0 else f"{1 / ci.mean:.1f} ({1 / ci.high:.1f} – {1 / max(ci.low, 1e-9):.0f})"
        )
        print(f"| {payload:g} kg, {slope:g}° | {int(ok.sum())}/{ok.size} | {ci} | {expected} |")


def floor(p, measured) -> None:
    print("\n## floor: J at exactly −1 without a fall\n")
    print(
        "| condition | trials | fell | J = −1 without a fall | un-floored J of those (median, min) |\n"
        "|---|---|---|---|---|"
    )
    for payload, slope in ((0.0, 0.0), (15.0, 0.0), (0.0, 10.0)):
        w = walk(p, "paper", payload_kg=payload, slope_deg=slope, measured=measured)
        flat = (w["fell"] == 0) & (w["j"] <= objective.MIN_OBJECTIVE)
        raw = w["j_raw"][flat]
        text = f"{np.median(raw):.1f}, {raw.min():.1f}" if raw.size else "—"
        print(f"| {payload:g} kg, {slope:g}° | {w['j'].size} | {int(w['fell'].sum())} | {int(flat.sum())} | {text} |")


def load(p, measured) -> None:
    print("\n## load: saturation, trunk height and the joint PD gains\n")
    print(
        "The mid-range gait's trunk height over 3 s after a settling trial (the controller's nominal stance height "
        "is 0.30 m at the feet, the trunk origin 0.32 m standing):\n"
    )
    print("| payload [kg] | trunk height mean [m] | min [m] |\n|---|---|---|")
    for payload in (0.0, 7.5, 15.0):
        sim = native.NativeBackend(go1_model.make_scenarios(payload_kg=payload, physics="paper"))
        mid, gates = params.midpoint()[None], protocol.batch_gates(["vmc_tegotae"])
        state, _ = sim.trial(sim.reset(mid), mid, gates)
        _, log = sim.rollout(state, mid, gates, 3000)
        sim.physics.close()
        z = np.asarray(log.qpos)[0, :, IDS.root_qpos + 2]
        print(f"| {payload:g} | {z.mean():.3f} | {z.min():.3f} |")
    stiff = cpg.CPGConfig(kp_nm_rad=1.5 * cpg.CPGConfig().kp_nm_rad)
    for payload in (0.0, 7.5, 15.0):
        print(
            f"\n{payload:g} kg (joint PD K_p {cpg.CPGConfig().kp_nm_rad:g}, the paper's, against "
            f"{stiff.kp_nm_rad:g}: a diagnostic, not a model change):\n\n{HEADER}"
        )
        base = walk(p, "paper", payload_kg=payload, measured=measured)
        firm = walk(p, "paper", payload_kg=payload, measured=measured, cpg_config=stiff)
        print(summary(f"K_p {cpg.CPGConfig().kp_nm_rad:g}", base))
        print(summary(f"K_p {stiff.kp_nm_rad:g}", firm))
        print()
        print(paired_line(f"K_p {stiff.kp_nm_rad:g} − K_p {cpg.CPGConfig().kp_nm_rad:g}", firm, base))


def _standing_reading(slope_deg: float, inclined_floor: bool) -> tuple[float, np.ndarray]:
    """IMU pitch [rad] and foot normal forces [N] after 1 s standing under joint PD (Kp 70, Kd 1.3), on a slope made
    by rotating gravity (ours) or by inclining the floor under vertical gravity."""
    m = go1_model.model_with_payload(0.0, "paper").__copy__()
    s = np.deg2rad(slope_deg)
    turn = np.array([np.cos(-s / 2), 0.0, np.sin(-s / 2), 0.0])  # the floor and the robot pitched nose-up
    if inclined_floor:  # a world geom's pose is fixed when the model compiles: incline the floor in the spec
        with resources.as_file(resources.files("cpgjax.go1.assets") / go1_model.MODEL_FILE) as path:
            spec = mujoco.MjSpec.from_file(str(path))
        spec.geom("floor").quat = turn
        m = spec.compile()
        physics.apply_to_model(m, physics.get("paper"), IDS.floor_geom, IDS.joint_dof)
    d = mujoco.MjData(m)
    qpos = go1_model.standing_qpos(m)
    if inclined_floor:
        r = IDS.root_qpos
        rotation = attitude.quat_to_matrix(jnp.asarray(turn))
        qpos[r : r + 3] = np.asarray(rotation) @ qpos[r : r + 3]
        qpos[r + 3 : r + 7] = np.asarray(attitude.quat_mul(jnp.asarray(turn), jnp.asarray(qpos[r + 3 : r + 7])))
        m.opt.gravity[:] = go1_model.gravity_vector(0.0)
    else:
        m.opt.gravity[:] = go1_model.gravity_vector(slope_deg)
    d.qpos[:] = qpos
    target = qpos[IDS.joint_qpos].copy()
    for _ in range(1000):
        d.ctrl[IDS.actuator] = 70.0 * (target - d.qpos[IDS.joint_qpos]) - 1.3 * d.qvel[IDS.joint_dof]
        mujoco.mj_step(m, d)
    mujoco.mj_forward(m, d)
    obs = sensors.observe(
        jnp.asarray(d.qpos), jnp.asarray(d.qvel), jnp.asarray(d.sensordata), jnp.asarray(m.opt.gravity)
    )
    pitch = float(attitude.quat_to_rpy(obs.imu_quat_wxyz)[1])
    return pitch, np.asarray(d.sensordata[IDS.foot_force_sensor])


def imu(p, measured) -> None:
    del p, measured
    print("\n## imu: rotated gravity against an inclined floor (standing 1 s)\n")
    print("| slope [deg] | setup | IMU pitch [rad] | foot normal forces FR, FL, RR, RL [N] |\n|---|---|---|---|")
    for slope in (10.0, 12.5):
        for inclined in (False, True):
            pitch, forces = _standing_reading(slope, inclined)
            label = "inclined floor, vertical gravity" if inclined else "rotated gravity (cpgjax)"
            print(f"| {slope:g} | {label} | {pitch:+.5f} | {np.array2string(forces, precision=2)} |")


# The payload's placements (docs/decisions.md §6 places cpgjax's): its body's position in the trunk frame [m] and
# whether it keeps the box's inertia. The box on the back rests on the trunk's collision box (half-height 0.057 m).
TRUNK_TOP_M = 0.057
PLACEMENTS = {
    "box at the trunk's centre of mass (cpgjax)": (None, True),
    "point mass at the trunk's centre of mass (the trunk's URDF mass raised)": (None, False),
    "box on the trunk's back": ((0.0223, 0.002, TRUNK_TOP_M + go1_model.PAYLOAD_BOX_M[2] / 2), True),
}


@contextlib.contextmanager
def payload_placed(pos_m, box_inertia: bool):
    """Within the block, every model the native backend builds carries its payload at ``pos_m`` (the trunk frame;
    None keeps go1.xml's) and, unless ``box_inertia``, as a point mass; the derived quantities recomputed."""
    original = go1_model.scenario_model

    def placed(scenario, i):
        m = original(scenario, i)
        if pos_m is not None:
            m.body_pos[IDS.payload_body] = pos_m
        if not box_inertia:
            m.body_inertia[IDS.payload_body] = 0.0
        mujoco.mj_setConst(m, mujoco.MjData(m))
        return m

    go1_model.scenario_model = placed
    try:
        yield
    finally:
        go1_model.scenario_model = original


def placement(p, measured) -> None:
    print("\n## placement: where the payload sits\n")
    for payload in (7.5, 15.0):
        print(f"\n{payload:g} kg:\n\n{HEADER}")
        runs = {}
        for name, (pos_m, box) in PLACEMENTS.items():
            with payload_placed(pos_m, box):
                runs[name] = walk(p, "paper", payload_kg=payload, measured=measured)
            print(summary(name, runs[name]))
        print()
        base = next(iter(PLACEMENTS))
        for name in list(PLACEMENTS)[1:]:
            print(paired_line(f"{name} − {base}", runs[name], runs[base]))


def slope_signal(p, measured) -> None:
    print("\n## slope_signal: the foot-force signal on the slopes\n")
    for slope in (10.0, 12.5):
        print(f"\n{slope:g}°:\n\n{HEADER}")
        runs = {name: walk(p, name, slope_deg=slope, measured=measured) for name in ("paper", "paper_sampled")}
        for name, w in runs.items():
            print(summary(name, w))
        print()
        print(
            paired_line(
                "paper − paper_sampled (the plugin's mean − one step's force)", runs["paper"], runs["paper_sampled"]
            )
        )


EXPERIMENTS = {
    "signal": signal,
    "contact": contact,
    "start": start,
    "search": search,
    "floor": floor,
    "load": load,
    "imu": imu,
    "placement": placement,
    "slope_signal": slope_signal,
}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sets", type=int, default=32, help="random parameter sets besides the mid-range one")
    parser.add_argument("--measured", type=int, default=3, help="measured back-to-back trials per set")
    parser.add_argument("--only", default=",".join(EXPERIMENTS), help="comma list of " + ", ".join(EXPERIMENTS))
    args = parser.parse_args(argv)
    chosen = [e for e in args.only.split(",") if e]
    unknown = [e for e in chosen if e not in EXPERIMENTS]
    if unknown or not 1 <= args.sets <= 512 or not 1 <= args.measured <= 20:
        parser.error(
            f"--only {unknown} unknown (allowed: {', '.join(EXPERIMENTS)}), or --sets outside 1 … 512, or "
            "--measured outside 1 … 20"
        )
    register_variants()
    p = population(args.sets)
    print(
        f"{len(p)} parameter sets (the mid-range one and {args.sets} uniform draws), VMC+Tegotae, v* = {TARGET_MPS} "
        f"m/s, C MuJoCo; {args.measured} measured trials after one settling trial"
    )
    for name in chosen:
        EXPERIMENTS[name](p, args.measured)


if __name__ == "__main__":
    main()
