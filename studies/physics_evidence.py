"""Measurements behind the physics profiles (docs/physics.md), in C MuJoCo:

1. Standing: the feet's penetration into the floor and each foot's signal (contact normal, calf-frame z) per profile,
   after 1 s holding the standing pose under joint PD (Kp 70, Kd 1.3).
2. Does the foot-force sensor report the forces that moved the robot? Over 2 s of open-loop walking, the impulse of
   the four feet's normal forces, Σ F dt, must equal m g T + Δp (vertical momentum balance of the trunk, the legs'
   momentum being periodic). With stiff contact and few Newton iterations the solver is not converged: its contact
   forces are not those of the step it integrated, and the sensor reads high.
3. ``--components``: which part of the ``paper`` profile changes a walk? Each component alone on top of ``soft``,
   mid-range parameters, 3 back-to-back trials on flat ground and on a 10° uphill.

    python studies/physics_evidence.py [--components]
"""

from __future__ import annotations

import sys

import jax.numpy as jnp
import mujoco
import numpy as np

from cpgjax.go1 import model as go1_model
from cpgjax.go1 import physics
from cpgjax.sim import native as native_go1
from cpgjax.trial import params, protocol

IDS = go1_model.indices()


def standing(profile: str) -> None:
    m = go1_model.model_with_payload(0.0, profile).__copy__()
    d = mujoco.MjData(m)
    d.qpos[:] = go1_model.standing_qpos(m)
    target = d.qpos[IDS.joint_qpos].copy()
    for _ in range(1000):
        d.ctrl[IDS.actuator] = 70.0 * (target - d.qpos[IDS.joint_qpos]) - 1.3 * d.qvel[IDS.joint_dof]
        mujoco.mj_step(m, d)
    mujoco.mj_forward(m, d)
    contact = jnp.asarray(d.sensordata[IDS.foot_contact_data])
    calf = physics.foot_force_signal(
        physics.arrays(physics.get("paper")), jnp.asarray(d.qpos), contact, IDS.root_qpos, IDS.joint_qpos
    )
    sink_mm = 1e3 * (go1_model.FOOT_RADIUS_M - min(d.geom_xpos[g][2] for g in IDS.foot_geom))
    print(
        f"| {profile} | {sink_mm:.4f} | {np.round(d.sensordata[IDS.foot_force_sensor], 2).tolist()} | "
        f"{np.round(np.asarray(calf, np.float64), 2).tolist()} | {float(np.mean(calf)):.2f} |"
    )


def impulse(profile: str, iterations: int, ls_iterations: int, seconds: float = 2.0) -> None:
    # This profile with the plain normal force at every tick, under its own name (models are cached by name).
    name = f"{profile} (normal force, 1 kHz)"
    physics.PROFILES[name] = physics.PROFILES[profile]._replace(
        foot_force_frame="contact", foot_force_period_ticks=1, foot_force_n_per_count=0.0
    )
    sim = native_go1.NativeBackend(go1_model.make_scenarios(physics=[name]))
    for model in sim.physics.models:
        model.opt.iterations, model.opt.ls_iterations = iterations, ls_iterations
    p = params.midpoint()[None]
    warm, steps = 1000, int(seconds * 1000)
    _, log = sim.rollout(sim.reset(p), p, protocol.batch_gates(["open_loop"]), warm + steps)
    sim.physics.close()
    force = np.asarray(log.foot_force_n)[0, warm:]
    vz = np.asarray(log.qvel)[0, :, IDS.root_dof + 2]
    mass = float(go1_model.model_with_payload(0.0, profile).body_subtreemass[IDS.trunk_body])
    needed = mass * 9.81 * seconds + mass * (vz[-1] - vz[warm - 1])
    measured = force.sum() * 1e-3
    vx = float(np.asarray(log.qvel)[0, warm:, IDS.root_dof].mean())
    print(
        f"| {profile} | ({iterations}, {ls_iterations}) | {measured:.1f} | {needed:.1f} | "
        f"{100 * (measured / needed - 1):+.1f} % | {vx:.3f} |"
    )


def components() -> None:
    from cpgjax.sim import walk

    soft, paper = physics.PROFILES["soft"], physics.PROFILES["paper"]
    variants = {
        "soft": soft,
        "soft + stiff contact": soft._replace(floor_solref=paper.floor_solref, floor_solimp=paper.floor_solimp),
        "soft + joint friction and damping": soft._replace(
            frictionloss_nm=paper.frictionloss_nm, damping_nm_s_rad=paper.damping_nm_s_rad
        ),
        "soft + no armature": soft._replace(armature_kg_m2=paper.armature_kg_m2),
        "soft + velocity limit": soft._replace(velocity_limit_rad_s=paper.velocity_limit_rad_s),
        "soft + calf-frame 100 Hz signal": soft._replace(foot_force_frame="calf", foot_force_period_ticks=10),
        "paper": paper,
    }
    for name, profile in variants.items():
        physics.PROFILES[f"component: {name}"] = profile
    rows, _ = walk.walk(
        controllers=("vmc_tegotae", "open_loop"),
        slope_deg=(0.0, 10.0),
        physics=[f"component: {name}" for name in variants],
        num_trials=3,
        backend="native",
        progress=lambda _: None,
    )
    print("| variant | controller | slope [°] | v_x [m/s] | CoT | J | falls |\n|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r.physics.removeprefix('component: ')} | {r.controller} | {r.condition.slope_deg:g} "
            f"| {r.vx_mps:.3f} | {r.cot:.2f} | {r.objective:.2f} | {r.falls} |"
        )


def main() -> None:
    if "--components" in sys.argv[1:]:
        components()
        return
    print("| profile | foot penetration [mm] | contact normal [N] | calf-frame z [N] | calf-frame z mean [N] |")
    print("|---|---|---|---|---|")
    profiles = list(physics.PROFILES)
    for profile in profiles:
        standing(profile)
    print(
        "\n| profile | solver (iterations, line search) | Σ F dt [N s] | m g T + Δp [N s] | sensor excess | v_x [m/s] |"
    )
    print("|---|---|---|---|---|---|")
    for profile in profiles:
        for setting in ((2, 6), (4, 8), (6, 10), (100, 50)):
            impulse(profile, *setting)


if __name__ == "__main__":
    main()
