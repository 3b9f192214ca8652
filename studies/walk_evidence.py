"""Evidence that the simulated Go1 walks under the paper's four CPG controllers (issue: "The Go1 walks in MJX").

1. Each controller, mid-range parameters, flat floor (friction 0.6): 7 back-to-back trials (31.5 s) — any fall?
2. Trial figures (v_x, CoT, J, c_load, c_slope) for friction 0.3 / 0.6 / 0.9 × slope 0° / 10° × payload 0 / 15 kg.
3. A figure of the oscillator states and foot trajectories over a few gait cycles (PNG).

    python studies/walk_evidence.py [--out results/walk_evidence]

Writes ``table.md``, ``walk30s.md`` and ``cpg_gait.png`` to the output folder and prints the tables.
"""

from __future__ import annotations

import argparse
import pathlib

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from cpgjax import cpg, mjx_go1
from cpgjax.go1 import constants
from cpgjax.go1 import model as go1_model
from cpgjax.sim import walk  # noqa: E402
from cpgjax.trial import params as param_space
from cpgjax.trial import protocol


def gait_figure(path: pathlib.Path, controller: str = "vmc_tegotae", seconds: float = 3.0) -> None:
    sim = mjx_go1.MJXBackend(go1_model.make_scenarios(friction=[0.6], physics="soft"))
    p = param_space.midpoint()[None]
    steps = int(seconds * 1000)
    _, log = sim.rollout(sim.reset(p), p, protocol.batch_gates([controller]), steps)
    t = np.arange(steps) * 1e-3
    window = t >= seconds - 0.6  # the last 0.6 s: a few gait cycles after the amplitude has converged
    legs = constants.LEG_NAMES
    fig, axes = plt.subplots(2, 2, figsize=(11, 7))
    ax = axes[0, 0]
    for i, leg in enumerate(legs):
        ax.plot(t[window], np.asarray(log.phase_rad[0, window, i]), label=leg)
    ax.set(title="CPG phases θ_i (eq. 2, 3, 6)", xlabel="t [s]", ylabel="θ [rad]")
    ax.legend(ncol=4, fontsize=8)
    ax = axes[0, 1]
    for i, leg in enumerate(legs):
        ax.plot(t, np.asarray(log.amplitude[0, :, i]), label=leg)
    ax.axhline(float(p[0, 4]), color="k", ls=":", label="μ")
    ax.set(title="CPG amplitudes r_i (eq. 1) from rest", xlabel="t [s]", ylabel="r")
    ax.legend(ncol=5, fontsize=8)
    ax = axes[1, 0]
    for i, leg in enumerate(legs):
        target = np.asarray(log.foot_target_m[0, window, i])
        ax.plot(target[:, 0], target[:, 2], label=f"{leg} target")
    ax.set(title="leg-frame foot targets (eqs. 4–5)", xlabel="x [m]", ylabel="z [m]")
    ax.legend(fontsize=8)
    ax = axes[1, 1]
    for i, leg in enumerate(legs):
        ax.plot(t[window], np.asarray(log.foot_force_n[0, window, i]), label=leg)
    ax.set(title="foot normal forces N_i (trot: diagonal pairs share stance)", xlabel="t [s]", ylabel="N [N]")
    ax.legend(ncol=4, fontsize=8)
    fig.suptitle(f"{controller}, mid-range parameters, flat floor μ=0.6")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("results/walk_evidence"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    rows, timing = walk.walk(num_trials=7)
    text = walk.markdown_table(rows)
    (args.out / "walk30s.md").write_text(text + "\n")
    print("## 31.5 s (7 trials) on flat ground, friction 0.6\n" + text, flush=True)

    rows, _ = walk.walk(
        controllers=cpg.CONTROLLERS,
        friction=(0.3, 0.6, 0.9),
        slope_deg=(0.0, 10.0),
        payload_kg=(0.0, 15.0),
        num_trials=2,
    )
    text = walk.markdown_table(rows)
    (args.out / "table.md").write_text(text + "\n")
    print("## scenario grid (second trial of two)\n" + text, flush=True)

    gait_figure(args.out / "cpg_gait.png")
    print(f"wrote {args.out}/walk30s.md, table.md, cpg_gait.png")


if __name__ == "__main__":
    main()
