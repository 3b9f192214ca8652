"""Which collision pairs make a height field cost in MJX: bare ``mjx.step`` (sensors included, no controller) of the
Go1 standing off the pad, on the plane model and on variants of the terrain model, in µs per instance-step.

Variants: the terrain model as cpgjax runs it (the feet against the field, the rest of the robot against the plane
below it); every collision geom against the field (the trunk box too); every geom but the trunk box against the
field. Each is compiled once, then ``--steps`` steps of a batch of ``--batch`` are timed, best of ``--repeats``;
the ratios are against the plane of the same run.

    JAX_PLATFORMS=cpu python benchmarks/terrain_pairs.py [--batch 4] [--steps 200] [--repeats 3]

The last line of the output is a JSON object of the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import time
import xml.etree.ElementTree as ElementTree

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from cpgjax import provenance
from cpgjax.go1 import model as go1_model
from cpgjax.go1 import terrain as terrains
from cpgjax.mjx_go1 import mjx


def terrain_variant(on_field: set[str]) -> mujoco.MjModel:
    """The terrain model with the named collision geoms (besides the feet) against the height field, on rough
    ground 4 cm (seed 3)."""
    root = ElementTree.fromstring(go1_model._with_terrain(go1_model.model_xml_without_visual_geoms()))
    feet = next(g for g in root.iter("geom") if g.get("name") == "FR_foot").get("conaffinity")
    for geom in root.iter("geom"):
        if geom.get("name") in on_field:
            geom.set("conaffinity", feet)
    m = mujoco.MjModel.from_xml_string(ElementTree.tostring(root, encoding="unicode"))
    m.hfield_data[:] = terrains.hfield_data(terrains.Ground("rough", 0.04, 3))
    return m


def step_cost_us(m: mujoco.MjModel, batch: int, steps: int, repeats: int) -> tuple[float, int]:
    """µs per instance-step of bare mjx.step and the number of contacts MJX carries per instance."""
    mx = mjx.put_model(m)
    qpos = np.tile(go1_model.standing_qpos(m), (batch, 1))
    qpos[:, go1_model.indices().root_qpos] = 1.0 + 0.1 * np.arange(batch)  # off the pad
    data = jax.vmap(lambda q: mjx.make_data(mx).replace(qpos=q))(jnp.asarray(qpos, jnp.float32))

    @jax.jit
    def run(d):
        return jax.lax.scan(lambda d, _: (jax.vmap(lambda x: mjx.step(mx, x))(d), None), d, None, length=steps)[0]

    jax.block_until_ready(run(data))
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(run(data))
        best = min(best, time.perf_counter() - start)
    ncon = int(jax.vmap(lambda x: mjx.forward(mx, x))(data)._impl.contact.dist.shape[1])
    return 1e6 * best / (batch * steps), ncon


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    base = go1_model.load_model()
    body = {
        mujoco.mj_id2name(base, mujoco.mjtObj.mjOBJ_GEOM, g)
        for g in range(base.ngeom)
        if base.geom_conaffinity[g] and not mujoco.mj_id2name(base, mujoco.mjtObj.mjOBJ_GEOM, g).endswith("_foot")
    }
    variants = {
        "plane": base,
        "terrain model (feet on the field)": terrain_variant(set()),
        "every collision geom on the field": terrain_variant(body),
        "every geom but the trunk box on the field": terrain_variant(body - {"trunk"}),
    }
    print(
        f"# {provenance.machine()}, batch {args.batch}, {args.steps} steps, best of {args.repeats}, load average "
        f"{os.getloadavg()[0]:.2f}"
    )
    figures, plane_us = {}, None
    for name, m in variants.items():
        us, ncon = step_cost_us(m, args.batch, args.steps, args.repeats)
        plane_us = us if plane_us is None else plane_us
        figures[name] = {"us_per_instance_step": us, "ratio_to_plane": us / plane_us, "contacts": ncon}
        print(
            f"{name:42s} {ncon:3d} contacts {us:8.1f} µs per instance-step {us / plane_us:6.2f}× the plane", flush=True
        )
    print(
        json.dumps(
            {
                "benchmark": "terrain_pairs",
                "machine": provenance.machine(),
                "batch": args.batch,
                "steps": args.steps,
                "repeats": args.repeats,
                "load_average": os.getloadavg()[0],
                "commit": provenance.git_commit(),
                "figures": figures,
            }
        )
    )


if __name__ == "__main__":
    main()
