"""Terrain under the simulated Go1: the kinds, the height field each instance stands on, the ground height under a
point, and the periodic wrap that lets trials run back to back on a finite field (docs/physics.md, "Terrain").

``flat`` is today's plane: a batch whose instances are all flat compiles no height field. ``rough`` is MuJoCo's
height field (hfield) of white-noise heights, uniform in [−A/2, A/2] with A the peak-to-peak amplitude, drawn by
NumPy's ``default_rng(seed)`` on one period of ``PERIOD_CELLS`` × ``PERIOD_CELLS`` cells and tiled ``PERIODS`` ×
``PERIODS`` times, so the field is periodic in x and y with period ``PERIOD_M``. A flat pad of ``PAD_HALF_M``
around every period's origin is where the robot stands after a reset. The height field's grid, its extent and its
maximum height are compiled into the model and shared by a batch; the heights (``hfield_data``) are a per-instance
model array.

Trials run without resets: at the end of a trial an instance whose trunk left the central period is moved back by
whole periods (:func:`wrap_xy_m`), which leaves the ground under it, and hence its motion, unchanged.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

TERRAINS = ("flat", "rough", "blocks")
FLAT = "flat"
BLOCKS = "blocks"
# Blocks' depth (their side, in x and y) [m]: from 0.15 m, two of the field's cells, so that a block has a top
# between its edges, to 4 m; a foot's step (2 d_step μ ≤ 0.17 m) spans one edge at a time.
BLOCK_DEPTH_M = (0.15, 4.0)
# The largest peak-to-peak height: the smallest swing clearance g_c of the paper's parameter box (0.06 m,
# cpgjax/trial/params.py; tests/go1/test_terrain.py checks the two agree), so that the swing apex of every parameter
# set clears the highest bump from the lowest hollow. A literal here: the Go1's facts sit below the parameters.
MAX_AMPLITUDE_M = 0.06
CELL_M = 0.075  # grid spacing: ~Playground's Go1 rough terrain (256 samples over 20 m, 0.078 m)
PERIOD_CELLS = 128
PERIOD_M = CELL_M * PERIOD_CELLS  # 9.6 m
# Three periods per side: a trial starts within the central period (|x|, |y| ≤ PERIOD_M / 2) and walks at most
# 4.5 s × ~1 m/s, which stays within ±(4.8 + 4.5 + the robot's 0.4) = ±9.7 m < 1.5 × PERIOD_M = 14.4 m.
PERIODS = 3
FIELD_VERTICES = PERIODS * PERIOD_CELLS + 1  # per side
FIELD_HALF_M = PERIODS * PERIOD_M / 2.0
# The hfield's prisms reach this far below its lowest point (MuJoCo's hfield base, size[3]).
BASE_M = 0.05
# The flat pad at every period's origin: the standing robot's feet (x ∈ [−0.23, 0.16] m, |y| ≤ 0.13 m) with a
# cell of margin.
PAD_HALF_M = (0.35, 0.25)


class Ground(NamedTuple):
    """One instance's terrain, as ``go1_model.make_scenarios`` takes it (``**ground._asdict()``)."""

    terrain: str = FLAT
    terrain_amplitude_m: float = 0.0
    terrain_seed: int = 0
    terrain_step_m: float = 0.0  # blocks: their depth (0 on the other grounds)


FLAT_GROUND = Ground()


def ground_fields(grounds) -> dict[str, np.ndarray]:
    """Several instances' grounds (any iterable) as the per-field arrays ``go1_model.make_scenarios`` takes (field →
    (B,))."""
    grounds = list(grounds)
    return {field: np.array([getattr(g, field) for g in grounds]) for field in Ground._fields}


def check_terrain(terrain, amplitude_m, seed, step_m=None) -> None:
    """Raise ValueError in one line naming the field, the value, the instance and the allowed range: an unknown
    terrain, an amplitude outside [0, MAX_AMPLITUDE_M] (0 for flat), a seed that is not an integer in [0, 2³²), or
    a block depth outside BLOCK_DEPTH_M for blocks (0 on the other grounds; ``step_m`` None: 0 everywhere)."""
    step_m = np.zeros(len(terrain)) if step_m is None else step_m
    for i, (kind, a, s, d) in enumerate(zip(terrain, amplitude_m, seed, step_m, strict=True)):
        if kind not in TERRAINS:
            raise ValueError(f"scenario terrain = {str(kind)!r} (instance {i}) is not a terrain; allowed: {TERRAINS}")
        if not (np.isfinite(a) and 0.0 <= a <= MAX_AMPLITUDE_M):
            raise ValueError(
                f"scenario terrain_amplitude_m = {float(a)!r} (instance {i}) is outside the allowed range "
                f"[0, {MAX_AMPLITUDE_M}]"
            )
        if kind == FLAT and a != 0.0:
            raise ValueError(
                f"scenario terrain_amplitude_m = {float(a)!r} (instance {i}) on flat terrain: allowed 0 "
                "(give terrain rough for a height)"
            )
        if not (np.isfinite(s) and s == np.round(s) and 0 <= s < 2.0**32):
            raise ValueError(
                f"scenario terrain_seed = {float(s)!r} (instance {i}) is outside the allowed range "
                "an integer in [0, 2**32)"
            )
        if kind == BLOCKS and not (np.isfinite(d) and BLOCK_DEPTH_M[0] <= d <= BLOCK_DEPTH_M[1]):
            raise ValueError(
                f"scenario terrain_step_m = {float(d)!r} (instance {i}) is outside the allowed range "
                f"[{BLOCK_DEPTH_M[0]}, {BLOCK_DEPTH_M[1]}] (the blocks' depth)"
            )
        if kind != BLOCKS and d != 0.0:
            raise ValueError(
                f"scenario terrain_step_m = {float(d)!r} (instance {i}) on {kind} terrain: allowed 0 "
                "(a depth is the blocks')"
            )


def _periodic_distance_m(coord_m: np.ndarray) -> np.ndarray:
    """|coordinate| from the nearest multiple of PERIOD_M."""
    return np.abs(coord_m - PERIOD_M * np.round(coord_m / PERIOD_M))


@functools.lru_cache(maxsize=64)
def period_heights_m(ground: Ground) -> np.ndarray:
    """Ground heights (PERIOD_CELLS, PERIOD_CELLS) [m] of one period, [row (y), column (x)], vertex (r, c) at
    (c, r) · CELL_M from the period's origin: 0 for flat; for rough, white noise uniform in [−A/2, A/2] at every
    vertex from ``default_rng(seed)``; for blocks, one such height per square block of side ``terrain_step_m``
    (vertex (r, c) in block (⌊r · CELL_M / d⌋, ⌊c · CELL_M / d⌋), the last block of a period cut by it), each block's
    top flat and its edges one cell wide (a height field interpolates between vertices). Rough and blocks have the pad
    around the origin at 0. Read-only."""
    terrain, amplitude_m, seed = ground.terrain, ground.terrain_amplitude_m, ground.terrain_seed
    heights = np.zeros((PERIOD_CELLS, PERIOD_CELLS))
    coord = np.arange(PERIOD_CELLS) * CELL_M
    if terrain == BLOCKS:
        block = np.floor(coord / ground.terrain_step_m + 1e-9).astype(int)
        tops = amplitude_m * (np.random.default_rng(seed).random((block[-1] + 1, block[-1] + 1)) - 0.5)
        heights = tops[np.ix_(block, block)]
    elif terrain != FLAT:
        heights = amplitude_m * (np.random.default_rng(seed).random((PERIOD_CELLS, PERIOD_CELLS)) - 0.5)
    if terrain != FLAT:
        pad = (_periodic_distance_m(coord)[:, None] <= PAD_HALF_M[1]) & (
            _periodic_distance_m(coord)[None, :] <= PAD_HALF_M[0]
        )
        heights[pad] = 0.0
    heights.flags.writeable = False
    return heights


def field_heights_m(ground: Ground) -> np.ndarray:
    """Ground heights (FIELD_VERTICES, FIELD_VERTICES) [m] of the whole field, [row (y), column (x)], vertex (r, c)
    at (c, r) · CELL_M − FIELD_HALF_M: the period repeated, the vertex at (x, y) being the period's vertex at
    (x, y) modulo PERIOD_M."""
    period = period_heights_m(
        Ground(
            str(ground.terrain),
            float(ground.terrain_amplitude_m),
            int(ground.terrain_seed),
            float(ground.terrain_step_m),
        )
    )
    index = (np.arange(FIELD_VERTICES) - round(FIELD_HALF_M / CELL_M)) % PERIOD_CELLS
    return period[np.ix_(index, index)]


def hfield_data(ground: Ground) -> np.ndarray:
    """The model's ``hfield_data`` (FIELD_VERTICES²,) in [0, 1]: MuJoCo's height is data × MAX_AMPLITUDE_M above
    the hfield geom, which sits at z = −MAX_AMPLITUDE_M / 2, so data 0.5 is the plane z = 0."""
    return (0.5 + field_heights_m(ground) / MAX_AMPLITUDE_M).reshape(-1)


def hfield_size() -> tuple[float, float, float, float]:
    """MuJoCo's hfield size: (x half-extent, y half-extent, maximum height, base) [m]."""
    return (FIELD_HALF_M, FIELD_HALF_M, MAX_AMPLITUDE_M, BASE_M)


def ground_height_m(hfield_data, x_m, y_m):
    """The ground's height [m] at (x, y) on the field whose model ``hfield_data`` is given (FIELD_VERTICES²,), in
    :func:`hfield_data`'s layout: linear on MuJoCo's triangles (each cell split along its diagonal from (c, r) to
    (c + 1, r + 1)); beyond the field, the edge cell's plane. JAX."""
    n = FIELD_VERTICES
    u, v = (x_m + FIELD_HALF_M) / CELL_M, (y_m + FIELD_HALF_M) / CELL_M
    c0, r0 = jnp.clip(jnp.floor(u), 0, n - 2), jnp.clip(jnp.floor(v), 0, n - 2)
    fx, fy = u - c0, v - r0
    at = r0.astype(jnp.int32) * n + c0.astype(jnp.int32)
    h00, h10, h01, h11 = hfield_data[at], hfield_data[at + 1], hfield_data[at + n], hfield_data[at + n + 1]
    upper = h00 + fx * (h11 - h01) + fy * (h01 - h00)  # triangle (0, 0), (1, 1), (0, 1)
    lower = h00 + fx * (h10 - h00) + fy * (h11 - h10)  # triangle (0, 0), (1, 0), (1, 1)
    return MAX_AMPLITUDE_M * (jnp.where(fy > fx, upper, lower) - 0.5)


def wrap_xy_m(xy_m):
    """Horizontal positions (..., 2) [m] moved by whole periods into the central one (|x|, |y| ≤ PERIOD_M / 2).
    NumPy (float64 kept) or JAX."""
    xp = jnp if isinstance(xy_m, jax.Array) else np
    return xy_m - PERIOD_M * xp.round(xy_m / PERIOD_M)
