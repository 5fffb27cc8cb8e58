"""Sweep `physicsrl-bench ping` over 1, 2 and 4 ranks, fit time = a + b * ranks, draw the figure.

Re-creates the report's Table 1 and Figure 4 (section 3.5). Each rank count is one run of
`physicsrl-bench ping`, which measures physicsrl, the report's design and the Bcast floor
side by side; this script collects their tables into benchmarks/results/ping.csv, fits the
report's linear model to each method and draws benchmarks/results/ping.png.

    python benchmarks/ping_scaling.py [--ranks 1 2 4] [--calls 200000]

Ranks beyond the machine's cores are oversubscribed (this machine has 2): those timings
measure time-sharing, not the library.
"""

from __future__ import annotations

import argparse

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from bench_run import at_least, bench_record, save_results  # noqa: E402

METHODS = ["physicsrl", "report design", "floor (Bcast 16 B)"]
REPORT = {1: 1.961, 2: 2.517, 4: 3.410, 8: 5.353}  # Table 1, microseconds per call


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ranks", type=at_least(1), nargs="+", default=[1, 2, 4])
    parser.add_argument("--calls", type=at_least(1), default=200_000)
    parser.add_argument("--repeats", type=at_least(1), default=7)
    args = parser.parse_args()

    rows, goals = [], []
    for ranks in args.ranks:
        record = bench_record(
            "ping", f"calls={args.calls}", f"repeats={args.repeats}", f"mpi.ranks={ranks}"
        )
        rows += record["rows"]
        goals += [
            f"{ranks} ranks: {'met' if g['met'] else 'MISSED'}: {g['goal']}"
            for g in record["goals"]
        ]
    figure, axes = plt.subplots(figsize=(6, 4))
    fits = []
    for method in METHODS:
        points = [(r["ranks"], r["us_per_call"]) for r in rows if r["method"] == method]
        x, y = np.array(points).T
        if len(set(x)) >= 2:  # a line needs two rank counts
            b, a = np.polyfit(x, y, 1)
            fits.append(f"{method}: time = {a:.3f} + {b:.3f} * ranks (us)")
        axes.plot(x, y, "o-", label=method)
    axes.plot(
        list(REPORT), list(REPORT.values()), "k--", alpha=0.5, label="report, Table 1 (cluster)"
    )
    axes.set(
        xlabel="MPI ranks",
        ylabel="microseconds per parallel call",
        title="Parallel call overhead (physicsrl-bench ping)",
    )
    axes.legend()
    save_results("ping", rows, figure, [*fits, *goals])


if __name__ == "__main__":
    main()
