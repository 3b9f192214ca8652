"""The ``cpgjax`` command line."""

from __future__ import annotations

import argparse
import sys

from cpgjax import cpg, walk


def _floats(text: str) -> tuple[float, ...]:
    return tuple(float(v) for v in text.split(","))


def _walk(args) -> None:
    rows, timing = walk.walk(controllers=args.controllers.split(","), friction=args.friction,
                             slope_deg=args.slope, payload_kg=args.payload, num_trials=args.trials,
                             target_velocity_mps=args.target)
    print(walk.markdown_table(rows))
    print(timing)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] == "deploy":  # its own parser: cpgjax deploy --help
        from cpgjax import deploy
        return deploy.main(argv[1:])
    parser = argparse.ArgumentParser(prog="cpgjax", description="cpgjax: online-optimized CPG control for the Go1. "
                                     "Subcommands: walk, deploy (see `cpgjax deploy --help`).")
    sub = parser.add_subparsers(dest="command", required=True)
    w = sub.add_parser("walk", help="walk with fixed parameters and print the trial figures")
    w.add_argument("--controllers", default=",".join(cpg.CONTROLLERS), help=f"comma list of {cpg.CONTROLLERS}")
    w.add_argument("--friction", type=_floats, default=(0.6,), help="comma list, e.g. 0.3,0.6,0.9")
    w.add_argument("--slope", type=_floats, default=(0.0,), help="comma list of slopes [deg], uphill along +x")
    w.add_argument("--payload", type=_floats, default=(0.0,), help="comma list of payloads [kg]")
    w.add_argument("--trials", type=int, default=2, help="back-to-back trials of 1.5 s + 3 s")
    w.add_argument("--target", type=float, default=0.5, help="target velocity v_x* [m/s] for J")
    w.set_defaults(func=_walk)
    args = parser.parse_args(argv)
    args.func(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
