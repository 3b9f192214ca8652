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

import math
import pathlib
import textwrap
from typing import NamedTuple

import numpy as np

from cpgjax import outputs
from cpgjax.go1 import constants
from cpgjax.trial import params as param_space

SUMMARY = "summary.png"  # the one-page summary of every study (:func:`summary`)
OUTPUTS = (outputs.OutputFile("*.png", "figure", outputs.check_png, pattern=r".+\.png"),)

CONTEXT_LABELS = ("$c_{load}$ [N]", "$c_{slope}$ [rad]")
LEGEND_FONT_PT = 7
LEGEND_WIDTH_IN = 2.6  # room to the right of a figure's axes for a legend beside them
LEGEND_LABEL_CHARS = 38  # a legend label's line in LEGEND_WIDTH_IN
ATTITUDE_PANELS_PER_ROW = 5
SUMMARY_WIDTH_IN = 8.3  # A4's width
TABLE_FONT_PT = 6.5
TABLE_CHARS_PER_LINE = 165  # characters of TABLE_FONT_PT text across SUMMARY_WIDTH_IN less its margins
TABLE_LINE_IN = 1.35 * TABLE_FONT_PT / 72  # one line of a table cell, with its spacing
TABLE_PAD_CHARS = 2  # a cell's margins, in characters
TABLE_HEADER_CHARS = 22  # a column is this wide for its header where its cells are narrower
SUMMARY_J_IN = 2.6  # the height of summary.png's J panel
SUMMARY_STRIP_IN = 1.25  # one row of filmstrips, with its title
STRIP_FRAMES = 4  # frames per filmstrip


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


def _figure_label(fig, x: float, y: float, label: str, size: float) -> None:
    """``label`` at (x, y) in fractions of the figure, left and baseline aligned, drawn through its first axes."""
    fig.axes[0].annotate(label, (x, y), xycoords="figure fraction", fontsize=size)


def _legend_beside(ax):
    """``ax``'s legend to the right of it, off the data, in LEGEND_WIDTH_IN (its labels wrapped to fit)."""
    handles, labels = ax.get_legend_handles_labels()
    return ax.legend(
        handles,
        [textwrap.fill(label, LEGEND_LABEL_CHARS) for label in labels],
        loc="upper left",
        bbox_to_anchor=(1.01, 1.0),
        borderaxespad=0.0,
        fontsize=LEGEND_FONT_PT,
    )


def _legend_outside(fig, ax, where: str = "right upper", **kwargs):
    """``ax``'s curves' legend in the figure's margin (``where``: matplotlib's "outside …" places), off every panel's
    data (the figure's constrained layout makes the room)."""
    handles, labels = ax.get_legend_handles_labels()
    return fig.legend(
        handles,
        [textwrap.fill(label, LEGEND_LABEL_CHARS) for label in labels],
        loc=f"outside {where}",
        fontsize=LEGEND_FONT_PT,
        **kwargs,
    )


def _colors(count: int) -> list:
    """``count`` colours, distinct up to 20 (tab10, or tab20 beyond 10 curves)."""
    import matplotlib

    cmap = matplotlib.colormaps["tab10" if count <= 10 else "tab20"]
    return [cmap(i % cmap.N) for i in range(count)]


def _band_alpha(count: int) -> float:
    """The opacity of a ±std band among ``count`` curves: lighter where many overlap."""
    return 0.2 if count <= 6 else 0.07


def _runs_per_curve(labels: np.ndarray) -> str:
    """'2 runs per curve' (or '2–3 runs per curve'): how many instances each drawn mean averages."""
    counts = [int(np.sum(labels == g)) for g in dict.fromkeys(labels)]
    low, high = min(counts), max(counts)
    return f"{low}{'' if low == high else f'–{high}'} run{'s' if high > 1 else ''} per curve"


def learning_curves(
    path: pathlib.Path,
    result,
    group_key: str,
    *,
    changes=(),
    target=None,
    context_index: int = 1,
    groups: list[str] | None = None,
) -> pathlib.Path:
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
    rows = (
        ("velocity $v_x$ [m/s]", tr.velocity_xy_mps[..., 0]),
        ("CoT", tr.cot),
        ("objective J", tr.objective),
        (CONTEXT_LABELS[context_index], tr.context[..., context_index]),
    )
    labels = np.array(groups if groups is not None else [str(lab[group_key]) for lab in result.labels])
    order = list(dict.fromkeys(labels))
    colors, alpha = _colors(len(order)), _band_alpha(len(order))
    fig, axes = plt.subplots(len(rows), 1, figsize=(6.5 + LEGEND_WIDTH_IN, 8.0), sharex=True, layout="constrained")
    for ax, (name, values) in zip(axes, rows, strict=True):
        for group, color in zip(order, colors, strict=True):
            v = np.asarray(values)[:, labels == group]
            mean, std = v.mean(axis=1), v.std(axis=1)
            ax.plot(trials, mean, label=f"{group_key} = {group}", lw=1.4, color=color)
            ax.fill_between(trials, mean - std, mean + std, color=color, alpha=alpha, lw=0)
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
    _legend_outside(fig, axes[0])
    axes[-1].set_xlabel("trial (from 0)")
    axes[0].set_title(f"{result.spec.name}: {_runs_per_curve(labels)}, mean ± std", fontsize=10)  # clear of the legend
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
    unit = (np.asarray(tr.params, np.float64) - param_space.PARAM_LOWER) / (
        param_space.PARAM_UPPER - param_space.PARAM_LOWER
    )
    order = list(dict.fromkeys(groups))
    size_in = (6.5 + LEGEND_WIDTH_IN, 2.2 * (1 + len(order)) + 0.5)  # below: the parameters' legend
    fig, axes = plt.subplots(1 + len(order), 1, figsize=size_in, sharex=True, squeeze=False, layout="constrained")
    axes = axes[:, 0]
    best = np.maximum.accumulate(np.asarray(tr.objective, np.float64), axis=0)
    for group, color in zip(order, _colors(len(order)), strict=True):
        b = best[:, names == group]
        axes[0].plot(trials, b.mean(axis=1), lw=1.4, label=group, color=color)
        axes[0].fill_between(
            trials,
            b.mean(axis=1) - b.std(axis=1),
            b.mean(axis=1) + b.std(axis=1),
            color=color,
            alpha=_band_alpha(len(order)),
            lw=0,
        )
    axes[0].set_ylabel("best J so far")
    _legend_outside(fig, axes[0])
    for ax, group in zip(axes[1:], order, strict=True):
        x = unit[:, names == group].mean(axis=1)  # (n, 8)
        for i, name in enumerate(param_space.PARAM_NAMES):
            ax.plot(trials, x[:, i], lw=1.0, label=name)
        ax.set_ylim(-0.05, 1.05)
        ax.set_ylabel("parameter (box → [0, 1])", fontsize=8)
        ax.set_title(group, fontsize=8, loc="left")
    _legend_outside(fig, axes[1], "lower center", ncol=4)
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("trial (from 0)")
    axes[0].set_title(
        f"{result.spec.name}: best-so-far J and the parameters ({_runs_per_curve(names)})", fontsize=10
    )  # over the panel, clear of the legend
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def attitude(path: pathlib.Path, logs: dict) -> pathlib.Path:
    """Roll–pitch trajectories [deg] of per-step logs ({label: StepLog of (T, ...)})."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(4.8, 4.2 + 0.25 * len(logs)), layout="constrained")
    for label, lg in logs.items():
        rpy = np.degrees(np.asarray(lg.rpy_rad))
        ax.plot(
            rpy[:, 0],
            rpy[:, 1],
            lw=0.8,
            alpha=0.8,
            label=f"{label} (std roll {rpy[:, 0].std():.2f}°, pitch {rpy[:, 1].std():.2f}°)",
        )
    ax.set_xlabel("roll [deg]")
    ax.set_ylabel("pitch [deg]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.14), borderaxespad=0.0, fontsize=LEGEND_FONT_PT)  # below
    ax.set_title("roll–pitch, best parameters, 3 s", fontsize=10)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def run_line(result, figures: dict) -> str:
    """One line of run figures for table.md."""
    return (
        f"{len(result.labels)} instances × {result.trials.objective.shape[0]} trials, backend {result.backend}, "
        f"wall {figures['wall_s']:.0f} s, {figures['env_steps_per_s']:,.0f} env-steps/s, real-time factor "
        f"{figures['real_time_factor']:.1f}× (simulation {figures['simulation_s']:.0f} s, optimizer "
        f"{figures['optimizer_s']:.0f} s, transfers {figures['transfer_s']:.1f} s, checkpoints "
        f"{figures['checkpoint_s']:.1f} s)."
    )


def attitude_by_group(path: pathlib.Path, gaits, logs) -> pathlib.Path:
    """One roll–pitch panel [deg] per group's best gait (``studies.video.Gait`` and its log), on shared axes,
    ATTITUDE_PANELS_PER_ROW to a row."""
    plt = _plt()
    columns = min(len(gaits), ATTITUDE_PANELS_PER_ROW)
    rows = math.ceil(len(gaits) / columns)
    width_in = max(3.2 * columns, 5.0)  # one panel still leaves its title the width it needs
    fig, axes = plt.subplots(
        rows,
        columns,
        figsize=(width_in, 3.4 * rows + 0.3),
        sharex=True,
        sharey=True,
        squeeze=False,
        layout="constrained",
    )
    for ax in axes.flat[len(gaits) :]:
        ax.set_visible(False)
    for ax, gait, lg in zip(axes.flat, gaits, logs, strict=False):
        rpy = np.degrees(np.asarray(lg.rpy_rad))
        ax.plot(rpy[:, 0], rpy[:, 1], lw=0.7)
        ax.set_title(f"{gait.group}\nstd roll {rpy[:, 0].std():.2f}°, pitch {rpy[:, 1].std():.2f}°", fontsize=8)
        ax.set_xlabel("roll [deg]")
        ax.grid(alpha=0.3)
    for ax in axes[:, 0]:
        ax.set_ylabel("pitch [deg]")
    fig.suptitle(
        f"roll–pitch of each group's best gait, {constants.seconds(len(logs[0].rpy_rad)):g} s after a settling trial",
        fontsize=9,
    )
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _first_table(text: str) -> list[list[str]]:
    """The cells of the first Markdown table in ``text``, its header row first (not its rule): the study's main
    table; the comparisons and notes after it stay in table.md."""
    lines = text.splitlines()
    start = next((i for i, line in enumerate(lines) if line.startswith("|")), len(lines))
    end = next((i for i in range(start, len(lines)) if not lines[i].startswith("|")), len(lines))
    return [
        [cell.strip() for cell in line.strip().strip("|").split("|")]
        for line in lines[start:end]
        if not line.startswith("|---")
    ]


def _wrap(cell: str, width: int) -> str:
    """``cell`` in lines of at most ``width`` characters, broken at spaces, and after underscores where a word
    (a group name) is longer than the line."""
    long_word = any(len(word) > width for word in cell.split())
    lines = textwrap.wrap(cell.replace("_", "_ ") if long_word else cell, width, break_on_hyphens=False)
    return "\n".join(line.replace("_ ", "_") for line in lines) or " "


def _wrapped(rows: list[list[str]]) -> tuple[list[list[str]], list[float]]:
    """The cells wrapped to lines that fit TABLE_CHARS_PER_LINE across, and each column's share of the width: a
    column gets its longest cell's length (at least its header's longest word, and its header's length up to
    TABLE_HEADER_CHARS), the widest ones cut to one common width where they do not all fit."""
    columns = len(rows[0])
    need = [
        max(
            [len(r[c]) for r in rows[1:]]
            + [len(word) for word in rows[0][c].split()]
            + [min(len(rows[0][c]), TABLE_HEADER_CHARS)]
        )
        for c in range(columns)
    ]
    cap = max(need)
    while cap > 4 and sum(min(n, cap) for n in need) > TABLE_CHARS_PER_LINE:
        cap -= 1
    widths = [min(n, cap) for n in need]
    cells = [[_wrap(cell, width) for cell, width in zip(row, widths, strict=True)] for row in rows]
    return cells, [(w + TABLE_PAD_CHARS) / (sum(widths) + TABLE_PAD_CHARS * columns) for w in widths]


def _draw_table(ax, cells: list[list[str]], shares: list[float]) -> None:
    """Wrapped ``cells`` (header first, :func:`_wrapped`) as a table filling ``ax``, each row as tall as its most
    wrapped cell."""
    lines = [max(cell.count("\n") + 1 for cell in row) for row in cells]
    table = ax.table(cellText=cells[1:], colLabels=cells[0], colWidths=shares, cellLoc="left", bbox=[0, 0, 1, 1])
    table.auto_set_font_size(False)
    table.set_fontsize(TABLE_FONT_PT)
    for (r, _), cell in table.get_celld().items():
        cell.set_height(lines[r])  # relative: the bbox scales every row alike
        cell.set_linewidth(0.3)
        if r == 0:
            cell.set_facecolor("#eeeeee")


def summary(
    path: pathlib.Path, result, table_text: str, gaits, frames: dict, paper_marks: list[PaperMark] = ()
) -> pathlib.Path:
    """One page SUMMARY_WIDTH_IN wide and as tall as it needs: the objective J per trial (mean ± std per group, the
    legend beside it) with the paper's values (``paper_marks``: dashed segments, a band for the paper's std; the
    title says where the paper gives none), the study's main table (the first of ``table_text``) drawn as a table,
    and a filmstrip of each group's best gait (``frames``: group → a few video frames (H, W, 3); the groups without
    them are named in one line at the bottom)."""
    plt = _plt()
    group_key = result.spec.group_by[0]
    tr = result.trials
    table = _first_table(table_text)
    cells, shares = _wrapped(table) if table else ([], [])
    table_in = sum(max(c.count("\n") + 1 for c in row) + 0.4 for row in cells) * TABLE_LINE_IN
    filmed = [g for g in gaits if frames.get(g.group)]
    per_row = 1 if len(filmed) <= 6 else 2  # gaits side by side where many: a strip of STRIP_FRAMES frames each
    strip_rows = math.ceil(len(filmed) / per_row)
    # the page from the top, in inches: margin, J, its axis labels, the table with its caption, the strips, margin
    blocks = [0.4, SUMMARY_J_IN, 0.6, (table_in + 0.25) if table else 0.0, SUMMARY_STRIP_IN * strip_rows, 0.3]
    height_in = sum(blocks)
    fig = plt.figure(figsize=(SUMMARY_WIDTH_IN, height_in))
    left_in, right_in = 0.8, 0.2

    def box(top_in: float, h_in: float, x_in: float = left_in, w_in: float | None = None) -> list[float]:
        w_in = SUMMARY_WIDTH_IN - left_in - right_in if w_in is None else w_in
        return [x_in / SUMMARY_WIDTH_IN, 1.0 - (top_in + h_in) / height_in, w_in / SUMMARY_WIDTH_IN, h_in / height_in]

    ax = fig.add_axes(box(blocks[0], SUMMARY_J_IN, w_in=SUMMARY_WIDTH_IN - left_in - right_in - LEGEND_WIDTH_IN))
    labels = np.array([str(lab[group_key]) for lab in result.labels])
    trials = np.arange(tr.objective.shape[0])
    order = list(dict.fromkeys(labels))
    colors = dict(zip(order, _colors(len(order)), strict=True))
    for group in order:
        v = np.asarray(tr.objective)[:, labels == group]
        ax.plot(trials, v.mean(axis=1), label=f"{group_key} = {group}", lw=1.4, color=colors[group])
        ax.fill_between(
            trials,
            v.mean(axis=1) - v.std(axis=1),
            v.mean(axis=1) + v.std(axis=1),
            color=colors[group],
            alpha=_band_alpha(len(order)),
            lw=0,
        )
    for mark in paper_marks:
        color = colors.get(mark.group, "black")
        span = [mark.first_trial - 0.4, mark.last_trial + 0.4]
        ax.plot(span, [mark.objective] * 2, ls="--", lw=1.6, color=color, label=mark.label)
        if mark.std is not None:
            ax.fill_between(
                span, mark.objective - mark.std, mark.objective + mark.std, color=color, alpha=0.12, lw=0, hatch="//"
            )
    ax.set_xlabel("trial (from 0)")
    ax.set_ylabel("objective J")
    ax.grid(alpha=0.3)
    _legend_beside(ax)
    paper = (
        "dashed: the paper's J" + (" ± std" if any(m.std is not None for m in paper_marks) else "")
        if paper_marks
        else "the paper gives no J for this result"
    )
    ax.set_title(
        f"{result.spec.name}: {len(result.labels)} runs × {len(trials)} trials, mean ± std per group; {paper}",
        fontsize=8,
        loc="left",
    )
    top = sum(blocks[:3])
    if table:
        panel = fig.add_axes(box(top + 0.25, table_in, x_in=0.2, w_in=SUMMARY_WIDTH_IN - 0.4))
        panel.axis("off")
        _draw_table(panel, cells, shares)
        panel.set_title("The main table of table.md (its comparisons and notes are there).", fontsize=7, loc="left")
    top += blocks[3]
    frame_w_in = (SUMMARY_WIDTH_IN - 0.4) / (STRIP_FRAMES * per_row)
    for k, gait in enumerate(filmed):
        row_top, x0_in = top + (k // per_row) * SUMMARY_STRIP_IN, 0.2 + (k % per_row) * STRIP_FRAMES * frame_w_in
        for c, frame in enumerate(frames[gait.group][:STRIP_FRAMES]):
            ax = fig.add_axes(
                box(row_top + 0.2, SUMMARY_STRIP_IN - 0.25, x_in=x0_in + c * frame_w_in, w_in=frame_w_in * 0.96)
            )
            ax.axis("off")
            ax.imshow(frame)
        j = "" if gait.objective is None else f", J {gait.objective:.3f}"
        _figure_label(
            fig, (x0_in + 0.02) / SUMMARY_WIDTH_IN, 1.0 - (row_top + 0.15) / height_in, f"best_{gait.group}{j}", 7
        )
    missing = [g.group for g in gaits if not frames.get(g.group)]
    if missing:
        _figure_label(
            fig,
            0.2 / SUMMARY_WIDTH_IN,
            0.1 / height_in,
            textwrap.shorten(f"no video frames of: {', '.join(missing)}", 160),
            6,
        )
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
