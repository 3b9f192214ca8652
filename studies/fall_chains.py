"""Do falls come in chains? Per study folder: the probability that an optimized trial falls after a trial that fell
and after one that walked (the same condition, the trial before also optimized), and the contexts that fallen and
walking trials measured (docs/decisions.md §11).

    python studies/fall_chains.py results/slope_adaptation [more folders]

Reads each folder's ``trials.parquet``. The two probabilities come with Clopper–Pearson 95 % intervals and a
two-sided Fisher exact test of their difference.
"""

from __future__ import annotations

import argparse
import pathlib

import numpy as np
import pyarrow.parquet as pq
from scipy import stats as scipy_stats

from cpgjax.studies import stats

CONDITIONS = ("friction", "slope_deg", "payload_kg", "target_velocity_mps")


def chains(columns: dict[str, np.ndarray]) -> dict:
    """Counts of falls after a fall and after a walk, and the median measured contexts of fallen and walking
    trials, over every instance of one study."""
    n_inst, n_trial = columns["instance"].max() + 1, columns["trial"].max() + 1

    def col(name):
        out = np.empty((n_trial, n_inst), columns[name].dtype)
        out[columns["trial"], columns["instance"]] = columns[name]
        return out

    fell = (col("fell") > 0) | (col("failed") > 0)
    optimized = col("inference") == 0
    same = np.all([col(c)[1:] == col(c)[:-1] for c in CONDITIONS], axis=0)
    pairs = optimized[1:] & optimized[:-1] & same
    after_fall, after_walk = fell[1:][pairs & fell[:-1]], fell[1:][pairs & ~fell[:-1]]
    return dict(after_fall=(int(after_fall.sum()), after_fall.size),
                after_walk=(int(after_walk.sum()), after_walk.size),
                falls=int(fell[optimized].sum()), trials=int(optimized.sum()),
                contexts={name: (float(np.median(col(name)[fell & optimized])) if (fell & optimized).any() else np.nan,
                                 float(np.median(col(name)[~fell & optimized])))
                          for name in ("c_load_n", "c_slope_rad")})


def report(folder: pathlib.Path) -> str:
    columns = {k: np.asarray(v) for k, v in pq.read_table(folder / "trials.parquet").to_pydict().items()}
    c = chains(columns)
    (k_f, n_f), (k_w, n_w) = c["after_fall"], c["after_walk"]
    p = scipy_stats.fisher_exact([[k_f, n_f - k_f], [k_w, n_w - k_w]]).pvalue if n_f and n_w else np.nan
    contexts = "; ".join(f"{name} median {fallen:.3g} fallen, {walked:.3g} walking"
                         for name, (fallen, walked) in c["contexts"].items())
    return (f"{folder}: {c['falls']} falls in {c['trials']} optimized trials. A fall after a fall: {k_f}/{n_f} "
            f"({stats.proportion_ci(k_f, n_f)}); after a walk: {k_w}/{n_w} ({stats.proportion_ci(k_w, n_w)}); "
            f"Fisher p = {p:.2g}. Measured contexts: {contexts}.")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", type=pathlib.Path, nargs="+", help="study folders with a trials.parquet")
    for folder in parser.parse_args().folders:
        print(report(folder))


if __name__ == "__main__":
    main()
