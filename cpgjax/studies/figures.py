"""The studies' figures (PNG, matplotlib Agg) in the paper's panel layout.

* :func:`learning_curves` — Fig. "sim_overview": rows mean forward velocity, CoT, objective value and context per
  trial; one line per group (mean over seeds) with a ±1 std band; condition changes marked by red arrows.
* :func:`optimization_progress` — Fig. "slope_adapt_exp" (b) style: the best J so far and the 8 parameters per trial,
  per group.
* :func:`attitude` — Fig. "att_comp": roll–pitch trajectories of the best parameters of two controllers.
* :func:`attitude_by_group` — roll–pitch of every group's best gait, one panel per group.
* :func:`summary` — one page per study: J per trial with the paper's values marked (:class:`PaperMark`), the table,
  and a filmstrip of each group's best gait.
"""

from __future__ import annotations

import pathlib
from typing import NamedTuple

import numpy as np

from cpgjax.trial import params as param_space

CONTEXT_LABELS = ("$c_{load}$ [N]", "$c_{slope}$ [rad]")


class PaperMark(NamedTuple):
    """A value of the paper's to mark on a per-trial panel: ``objective`` (± ``std`` where the paper gives one) over
    trials ``first_trial``…``last_trial``, in the colour of ``group``'s curve where it has one."""

    label: str
    first_trial: int
    last_trial: int
    objective: float
    std: float | None = None
    group: str | None = None


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _runs_per_curve(labels: np.ndarray) -> str:
    """'2 runs per curve' (or '2–3 runs per curve'): how many instances each drawn mean averages."""
    counts = [int(np.sum(labels == g)) for g in dict.fromkeys(labels)]
    low, high = min(counts), max(counts)
    return f"{low}{'' if low == high else f'–{high}'} run{'s' if high > 1 else ''} per curve"


def learning_curves(path: pathlib.Path, result, group_key: str, *, changes=(), target=None,
                    context_index: int = 1, groups: list[str] | None = None) -> pathlib.Path:
    """Velocity, CoT, J and one context component per trial, mean ± std over the instances of each group.

    Args:
      group_key: instance label whose values form the groups (lines); or, with ``groups``, what the legend calls
        them.
      groups: each instance's group name (default: its ``group_key`` label).
      changes: trials at which the conditions change (red arrows on the J row).
      target: (N,) target velocity per trial, drawn on the velocity row (default: the first instance's).
      context_index: 0 = c_load, 1 = c_slope.
    """
    plt = _plt()
    tr = result.trials
    n = tr.objective.shape[0]
    trials = np.arange(n)  # numbered from 0, as in trials.parquet, the schedules and the progress lines
    rows = (("velocity $v_x$ [m/s]", tr.velocity_xy_mps[..., 0]), ("CoT", tr.cot), ("objective J", tr.objective),
            (CONTEXT_LABELS[context_index], tr.context[..., context_index]))
    labels = np.array(groups if groups is not None else [str(lab[group_key]) for lab in result.labels])
    fig, axes = plt.subplots(len(rows), 1, figsize=(6.5, 8.0), sharex=True)
    for ax, (name, values) in zip(axes, rows, strict=True):
        for group in dict.fromkeys(labels):
            v = np.asarray(values)[:, labels == group]
            mean, std = v.mean(axis=1), v.std(axis=1)
            line, = ax.plot(trials, mean, label=f"{group_key} = {group}", lw=1.4)
            ax.fill_between(trials, mean - std, mean + std, color=line.get_color(), alpha=0.2, lw=0)
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    tgt = result.conditions.target_velocity_mps[0] if target is None else target
    axes[0].step(trials, tgt, where="mid", color="k", ls="--", lw=1, label="target $v_x^*$")
    axes[1].set_ylim(0, min(3.0, float(np.nanpercentile(tr.cot, 95)) * 1.2 + 0.1))
    axes[2].set_ylim(-1.1, 2.6)
    for c in changes:
        axes[2].annotate("", xy=(c, -1.0), xytext=(c, -0.3), arrowprops=dict(color="red", arrowstyle="->"))
        for ax in axes:
            ax.axvline(c - 0.5, color="red", lw=0.6, alpha=0.5)
    axes[0].legend(fontsize=7, loc="lower right")
    axes[-1].set_xlabel("trial (from 0)")
    fig.suptitle(f"{result.spec.name}: {_runs_per_curve(labels)}, mean ± std", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def optimization_progress(path: pathlib.Path, result, groups: list[str]) -> pathlib.Path:
    """The paper's Fig. "slope_adapt_exp" (b) style, per group (``groups``: each instance's group name): the best J
    found so far (running maximum over the trials, mean ± std over the group's runs), and each of the 8 parameters
    per trial, normalized to the paper's box [0, 1] (mean over the group's runs)."""
    plt = _plt()
    tr = result.trials
    n = tr.objective.shape[0]
    trials = np.arange(n)
    names = np.array(groups)
    unit = (np.asarray(tr.params, np.float64) - param_space.PARAM_LOWER) / (param_space.PARAM_UPPER
                                                                          - param_space.PARAM_LOWER)
    order = list(dict.fromkeys(groups))
    fig, axes = plt.subplots(1 + len(order), 1, figsize=(6.5, 2.2 * (1 + len(order))), sharex=True, squeeze=False)
    axes = axes[:, 0]
    best = np.maximum.accumulate(np.asarray(tr.objective, np.float64), axis=0)
    for group in order:
        b = best[:, names == group]
        line, = axes[0].plot(trials, b.mean(axis=1), lw=1.4, label=group)
        axes[0].fill_between(trials, b.mean(axis=1) - b.std(axis=1), b.mean(axis=1) + b.std(axis=1),
                             color=line.get_color(), alpha=0.2, lw=0)
    axes[0].set_ylabel("best J so far")
    axes[0].legend(fontsize=7, loc="lower right")
    for ax, group in zip(axes[1:], order, strict=True):
        x = unit[:, names == group].mean(axis=1)  # (n, 8)
        for i, name in enumerate(param_space.PARAM_NAMES):
            ax.plot(trials, x[:, i], lw=1.0, label=name)
        ax.set_ylim(-0.05, 1.05)
        ax.set_ylabel(f"{group}\nparameter (box → [0, 1])", fontsize=8)
    axes[1].legend(fontsize=6, ncol=4, loc="upper right")
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("trial (from 0)")
    fig.suptitle(f"{result.spec.name}: best-so-far J and the parameters ({_runs_per_curve(names)})", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def attitude(path: pathlib.Path, logs: dict) -> pathlib.Path:
    """Roll–pitch trajectories [deg] of per-step logs ({label: StepLog of (T, ...)})."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(4.8, 4.2))
    for label, lg in logs.items():
        rpy = np.degrees(np.asarray(lg.rpy_rad))
        ax.plot(rpy[:, 0], rpy[:, 1], lw=0.8, alpha=0.8,
                label=f"{label} (std roll {rpy[:, 0].std():.2f}°, pitch {rpy[:, 1].std():.2f}°)")
    ax.set_xlabel("roll [deg]")
    ax.set_ylabel("pitch [deg]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title("roll–pitch, best parameters, 3 s", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def run_line(result, figures: dict) -> str:
    """One line of run figures for table.md."""
    return (f"{len(result.labels)} instances × {result.trials.objective.shape[0]} trials, backend {result.backend}, "
            f"wall {figures['wall_s']:.0f} s, {figures['env_steps_per_s']:,.0f} env-steps/s, real-time factor "
            f"{figures['real_time_factor']:.1f}× (simulation {figures['simulation_s']:.0f} s, optimizer "
            f"{figures['optimizer_s']:.0f} s, transfers {figures['transfer_s']:.1f} s, checkpoints "
            f"{figures['checkpoint_s']:.1f} s).")


def attitude_by_group(path: pathlib.Path, gaits, logs) -> pathlib.Path:
    """One roll–pitch panel [deg] per group's best gait (``studies.video.Gait`` and its log), on shared axes."""
    plt = _plt()
    fig, axes = plt.subplots(1, len(gaits), figsize=(3.2 * len(gaits), 3.4), sharex=True, sharey=True, squeeze=False)
    for ax, gait, lg in zip(axes[0], gaits, logs, strict=True):
        rpy = np.degrees(np.asarray(lg.rpy_rad))
        ax.plot(rpy[:, 0], rpy[:, 1], lw=0.7)
        ax.set_title(f"{gait.group}\nstd roll {rpy[:, 0].std():.2f}°, pitch {rpy[:, 1].std():.2f}°", fontsize=8)
        ax.set_xlabel("roll [deg]")
        ax.grid(alpha=0.3)
    axes[0, 0].set_ylabel("pitch [deg]")
    fig.suptitle(f"roll–pitch of each group's best gait, {len(logs[0].rpy_rad) / 1000:g} s after a settling trial",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _first_table(text: str) -> list[str]:
    """The rows of the first Markdown table in ``text`` (its header too, not its rule): the study's main table,
    whose rows fit the page's width; the comparisons after it stay in table.md."""
    lines = text.splitlines()
    start = next((i for i, line in enumerate(lines) if line.startswith("|")), len(lines))
    end = next((i for i in range(start, len(lines)) if not lines[i].startswith("|")), len(lines))
    return [line for line in lines[start:end] if not line.startswith("|---")]


def summary(path: pathlib.Path, result, table_text: str, gaits, frames: dict,
            paper_marks: list[PaperMark] = ()) -> pathlib.Path:
    """One page: the objective J per trial (mean ± std per group) with the paper's values (``paper_marks``: dashed
    segments, a band for the paper's std; the title says where the paper gives none), the study's main table, and a
    filmstrip of each group's best gait (``frames``: group → a few video frames (H, W, 3); a group without them gets
    a line saying so)."""
    plt = _plt()
    group_key = result.spec.group_by[0]
    tr = result.trials
    rows = 2 + len(gaits)
    fig = plt.figure(figsize=(8.3, 11.7))  # A4
    grid = fig.add_gridspec(rows, 4, height_ratios=[2.2, 1.6] + [1.0] * len(gaits))
    ax = fig.add_subplot(grid[0, :])
    labels = np.array([str(lab[group_key]) for lab in result.labels])
    trials = np.arange(tr.objective.shape[0])
    colors = {}
    for group in dict.fromkeys(labels):
        v = np.asarray(tr.objective)[:, labels == group]
        line, = ax.plot(trials, v.mean(axis=1), label=f"{group_key} = {group}", lw=1.4)
        colors[group] = line.get_color()
        ax.fill_between(trials, v.mean(axis=1) - v.std(axis=1), v.mean(axis=1) + v.std(axis=1),
                        color=line.get_color(), alpha=0.2, lw=0)
    for mark in paper_marks:
        color = colors.get(mark.group, "black")
        span = [mark.first_trial - 0.4, mark.last_trial + 0.4]
        ax.plot(span, [mark.objective] * 2, ls="--", lw=1.6, color=color, label=mark.label)
        if mark.std is not None:
            ax.fill_between(span, mark.objective - mark.std, mark.objective + mark.std, color=color, alpha=0.12,
                            lw=0, hatch="//")
    ax.set_xlabel("trial (from 0)")
    ax.set_ylabel("objective J")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6, ncol=2)
    paper = ("dashed: the paper's J" + (" ± std" if any(m.std is not None for m in paper_marks) else "")
             if paper_marks else "the paper gives no J for this result")
    ax.set_title(f"{result.spec.name}: {len(result.labels)} runs × {len(trials)} trials, mean ± std per group; "
                 f"{paper}", fontsize=9)
    panel = fig.add_subplot(grid[1, :])
    panel.axis("off")
    panel.annotate("\n".join(_first_table(table_text)[:12]), (0, 1), xycoords="axes fraction", family="monospace",
                   fontsize=5.5, va="top")
    for r, gait in enumerate(gaits):
        strip = frames.get(gait.group, [])
        for c in range(4):
            ax = fig.add_subplot(grid[2 + r, c])
            ax.axis("off")
            if c < len(strip):
                ax.imshow(strip[c])
            if c == 0:
                j = "" if gait.objective is None else f", J {gait.objective:.3f}"
                ax.set_title(f"best_{gait.group}{j}" + ("" if strip else " (no video)"), fontsize=7, loc="left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
