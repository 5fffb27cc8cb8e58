"""Sweep `physicsrl-bench ms` over ranks and grids, fit time = A / ranks + B, draw the figure.

Re-creates the strong-scaling study of the report (section 4.3.3) for physicsrl's monodomain
Mitchell-Schaeffer step: each (grid, ranks) pair is one run of `physicsrl-bench ms` (its
default ``scheme=both``: the implicit and explicit schemes and the explicit one's floor; the
report's port only with ``--baseline``), whose per-step times (mean of steps 2..N) and phase
splits are collected into benchmarks/results/ms.csv. Per grid, the report's model of the
implicit scheme's time, A / ranks + B (A: the parallelisable work, B: the serial part and
communication), is fitted by least squares (exact for two rank counts) and the parallel efficiency
T(1) / (ranks * T(ranks)) is printed; benchmarks/results/ms.png shows the times and the fits,
benchmarks/results/ms.txt the command, the fits and the efficiencies.

    python benchmarks/ms_scaling.py [--ranks 1 2] [--grids 250 500 1000] [--steps 20]

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


def fit(ranks: np.ndarray, times: np.ndarray) -> tuple[float, float]:
    """Least-squares (A, B) of time = A / ranks + B."""
    design = np.column_stack([1.0 / ranks, np.ones_like(ranks)])
    (a, b), *_ = np.linalg.lstsq(design, times, rcond=None)
    return float(a), float(b)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ranks", type=at_least(1), nargs="+", default=[1, 2])
    parser.add_argument("--grids", type=at_least(2), nargs="+", default=[250, 500, 1000])
    parser.add_argument("--steps", type=at_least(2), default=20)
    parser.add_argument("--baseline", action="store_true", help="also run the report's port")
    args = parser.parse_args()

    rows, goals = [], []
    for n in args.grids:
        for ranks in args.ranks:
            record = bench_record(
                "ms",
                f"grid.n={n}",
                f"steps={args.steps}",
                f"baseline={str(args.baseline).lower()}",
                f"mpi.ranks={ranks}",
            )
            rows += record["rows"]
            goals += [
                f"{n}x{n}, {ranks} ranks: {'met' if g['met'] else 'MISSED'}: {g['goal']}"
                for g in record["goals"]
            ]
            print(f"{n}x{n}, {ranks} ranks: {record['rows'][0]['step_ms']} ms/step", flush=True)
    figure, axes = plt.subplots(figsize=(6, 4))
    lines = []
    for n in args.grids:
        ours = [r for r in rows if r["implementation"] == "physicsrl" and r["grid"] == f"{n}x{n}"]
        x = np.array([r["ranks"] for r in ours], dtype=float)
        y = np.array([r["step_ms"] for r in ours])
        (points,) = axes.plot(x, y, "o", label=f"{n}x{n}")
        if len(x) >= 2:
            a, b = fit(x, y)
            grid = np.linspace(x.min(), x.max(), 50)
            axes.plot(grid, a / grid + b, "-", color=points.get_color(), alpha=0.6)
            lines.append(f"{n}x{n}: time = {a:.2f} / ranks + {b:.2f} (ms per step)")
        serial = y[x == 1]
        for r, t in zip(x, y, strict=True):
            if serial.size and r > 1:
                lines.append(
                    f"{n}x{n}: parallel efficiency 1 -> {r:.0f} ranks {serial[0] / (r * t):.0%}"
                )
    axes.set(
        xlabel="MPI ranks",
        ylabel="milliseconds per step",
        yscale="log",
        title="Monodomain Mitchell-Schaeffer step (physicsrl-bench ms)",
    )
    axes.set_xticks(args.ranks)
    axes.legend()
    save_results("ms", rows, figure, [*lines, *goals])


if __name__ == "__main__":
    main()
