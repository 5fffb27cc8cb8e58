"""Cost-normalised learning curves of a training run, with baselines on the same axes.

The greedy policy's mean return (and success rate, where the task reports one) on the held-out
seeds, from the run's ``eval.csv`` (one row per evaluation, with ``frames`` and ``wall_s``, the
training's cumulative seconds, resumes included), against three costs: environment steps,
wall-clock hours and core-hours (wall-clock x the job's W ranks). Baseline policies are
horizontal lines on every panel. Used by ``physicsrl-eval`` (``learning_curve.png``) and
``experiments/learning_curve.py`` (the results' figures).
"""

from __future__ import annotations

import csv
import json
from collections.abc import Collection, Sequence
from pathlib import Path

from physicsrl.tables import mean_metrics, read_per_policy

COSTS = {  # x-axis label -> function of (frames, wall seconds, ranks)
    "environment steps": lambda frames, wall, ranks: frames,
    "wall-clock hours": lambda frames, wall, ranks: wall / 3600,
    "core-hours": lambda frames, wall, ranks: wall * ranks / 3600,
}
METRICS = {"return": "greedy mean return", "success": "greedy success rate"}


def curves(rows: Sequence[dict], ranks: int) -> dict[str, list[float]]:
    """x values per cost (:data:`COSTS`) of the evaluations ``rows`` of a job of ``ranks``."""
    return {
        cost: [f(float(r["frames"]), float(r["wall_s"]), ranks) for r in rows]
        for cost, f in COSTS.items()
    }


def best_rows(paths: Sequence[Path], seeds: Collection[int] | None = None) -> list[dict]:
    """The best row (by mean return) of each table: a CSV of means (``policy``, ``return``, ...)
    or of episodes (with a ``seed`` column), whose rows are averaged per policy over ``seeds``
    (default: all; ValueError if a policy lacks one), so that a bar is on the same seeds as the
    curve it is drawn with."""
    bars = []
    for path in paths:
        table = read_per_policy(path)
        if "seed" in next(iter(table.values()))[0]:
            wanted = set(seeds or {r["seed"] for rows in table.values() for r in rows})
            for policy, rows in table.items():
                missing = wanted - {r["seed"] for r in rows}
                if missing:
                    raise ValueError(f"{path}: {policy!r} has no row for seeds {sorted(missing)}")
                table[policy] = [mean_metrics(r for r in rows if r["seed"] in wanted)]
        rows = [{"policy": policy, **rows[0]} for policy, rows in table.items()]
        bars.append(max(rows, key=lambda r: r["return"]))
    return bars


def job_ranks(run_dir: Path) -> int | None:
    """The W ranks of the run's job, from its ``summary.json`` (None before it has one)."""
    summary = Path(run_dir) / "summary.json"
    if not summary.is_file():
        return None
    return json.loads(summary.read_text())["summary"].get("ranks")


def plot(
    run_dir: Path,
    path: Path,
    bars: Sequence[dict] = (),
    ranks: int | None = None,
    until: int | None = None,
):
    """Write the figure of ``run_dir`` to ``path``: a row of panels per metric of
    :data:`METRICS` in its ``eval.csv`` (its evaluations up to iteration ``until``, if given),
    a column per cost; ``bars`` are rows with ``policy`` and the metrics (a ``"greedy DQN"``
    row is skipped). ``ranks`` defaults to the run's :func:`job_ranks`, else 1 (said in the
    title). Returns ``path``, or None if the run has no evaluations with wall time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    evaluations = Path(run_dir) / "eval.csv"
    if not evaluations.is_file():
        return None
    with evaluations.open() as stream:
        rows = [
            r
            for r in csv.DictReader(stream)
            if until is None or int(r.get("iteration", 0)) <= until
        ]
    if not rows or "wall_s" not in rows[0]:
        return None
    ranks = ranks or job_ranks(run_dir)
    said = f"{ranks} rank{'s' * (ranks != 1)}" if ranks else "1 rank?"
    x = curves(rows, ranks or 1)
    metrics = {m: label for m, label in METRICS.items() if m in rows[0]}
    bars = [b for b in bars if b["policy"] != "greedy DQN"]
    figure, axes = plt.subplots(
        len(metrics), len(COSTS), figsize=(13, 3.3 * len(metrics)), sharey="row", squeeze=False
    )
    for i, (metric, label) in enumerate(metrics.items()):
        y = [float(r[metric]) for r in rows]
        for j, cost in enumerate(COSTS):
            ax = axes[i, j]
            ax.plot(x[cost], y, "o-", color="C0", label="DQN (greedy, held-out seeds)")
            for k, bar in enumerate(bars):
                if bar.get(metric) not in (None, ""):
                    ax.axhline(float(bar[metric]), ls="--", color=f"C{k + 1}", label=bar["policy"])
            ax.set(xlabel=cost, ylabel=label if j == 0 else None)
            ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    figure.suptitle(f"{Path(run_dir).name}: {said}")
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)
    return Path(path)
