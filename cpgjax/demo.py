"""``make demo``: a short simulated walk of the paper's four CPG controllers on flat ground, with their trial figures."""

from cpgjax import walk


def main() -> None:
    print("cpgjax demo: the four CPG controllers, mid-range parameters, flat floor (friction 0.6), 3 trials of "
          "1.5 s + 3 s each on the CPU (the first call compiles).")
    rows, timing = walk.walk(num_trials=3)
    print(walk.markdown_table(rows))
    print(f"compile + first trial: {timing['compile_and_first_trial_s']:.1f} s; "
          f"simulation afterwards: {timing['env_steps_per_s']:,.0f} env-steps/s")


if __name__ == "__main__":
    main()
