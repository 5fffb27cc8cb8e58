"""Cost-normalised learning curves of a training run, with open-loop bars on the same axes.

    python experiments/learning_curve.py RUN_DIR OUT.png [--baselines TABLE.csv ...] [--ranks W]

The greedy policy's success rate and mean return on the held-out seeds (the run's ``eval.csv``:
one row per evaluation, with ``frames`` and ``wall_s``, the training's cumulative seconds,
resumes included) against three costs: environment steps, wall-clock hours and core-hours
(wall-clock x the job's W ranks, from the run's ``summary.json`` or ``--ranks``). ``--baselines``
takes tables with ``policy``, ``return`` and ``success`` columns (``atp_baselines.py``'s):
from each, the policy of the best mean return is drawn as a horizontal line, labelled with its
name, on every panel.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

COSTS = {  # x-axis label -> function of (frames, wall seconds, ranks)
    "environment steps": lambda frames, wall, ranks: frames,
    "wall-clock hours": lambda frames, wall, ranks: wall / 3600,
    "core-hours": lambda frames, wall, ranks: wall * ranks / 3600,
}
METRICS = {"success": "greedy success rate", "return": "greedy mean return"}


def curves(rows: list[dict], ranks: int) -> dict[str, list[float]]:
    """x values per cost (:data:`COSTS`) of the evaluations ``rows`` of a job of ``ranks``."""
    return {
        cost: [f(float(r["frames"]), float(r["wall_s"]), ranks) for r in rows]
        for cost, f in COSTS.items()
    }


def best_rows(paths: list[Path]) -> list[dict]:
    """The best row (by mean return) of each table."""
    bars = []
    for path in paths:
        with path.open() as stream:
            bars.append(max(csv.DictReader(stream), key=lambda r: float(r["return"])))
    return bars


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a physicsrl-train run directory")
    parser.add_argument("out", type=Path, help="the PNG to write")
    parser.add_argument("--baselines", type=Path, nargs="*", default=[], help="tables")
    parser.add_argument("--ranks", type=int, help="the job's ranks (default: its summary's)")
    args = parser.parse_args()
    with (args.run / "eval.csv").open() as stream:
        rows = list(csv.DictReader(stream))
    if not rows or "wall_s" not in rows[0]:
        raise SystemExit(f"{args.run / 'eval.csv'}: no evaluations with wall_s")
    ranks = args.ranks or json.loads((args.run / "summary.json").read_text())["summary"]["ranks"]
    x, bars = curves(rows, ranks), best_rows(args.baselines)

    figure, axes = plt.subplots(2, 3, figsize=(13, 6.5), sharey="row")
    for i, (metric, label) in enumerate(METRICS.items()):
        y = [float(r[metric]) for r in rows]
        for j, cost in enumerate(COSTS):
            ax = axes[i, j]
            ax.plot(x[cost], y, "o-", color="C0", label="DQN (greedy, held-out seeds)")
            for k, bar in enumerate(bars):
                ax.axhline(float(bar[metric]), ls="--", color=f"C{k + 1}", label=bar["policy"])
            ax.set(xlabel=cost, ylabel=label if j == 0 else None)
            ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    figure.suptitle(f"{args.run.name}: {ranks} ranks")
    figure.tight_layout()
    figure.savefig(args.out, dpi=120)
    print(args.out)


if __name__ == "__main__":
    main()
