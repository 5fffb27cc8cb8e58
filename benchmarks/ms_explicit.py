"""The explicit Mitchell-Schaeffer scheme against the implicit one, its floor and its ranks.

Runs, one after the other (issue 11's benchmark):

- ``physicsrl-bench ms scheme=both`` at 60, 1000 and 2000 cells per side on 1 and 2 ranks
  (``--steps``, default 201) and at 3000 x 3000 on 2 ranks for 100 steps (the report's run),
  ``--per-call`` steps per call (default 100; a task's decision runs 1667, and from 8 the
  explicit scheme takes its structured path): ms per step of both schemes with their phases,
  and the floor (a fused structured-grid C loop on each rank's strip,
  :mod:`physicsrl.bench.ms_floor`), all in the same job;
- the 2000 x 2000 explicit steps per second on 2 ranks against 1 rank, with one decision's
  1667 steps per call, 1 and 2 ranks alternated ``--repeats`` times (default 3; the medians),
  beside the same ratio for the floor (each rank's strip alone: what the machine allows);
- one decision (50 time units, a wait and a shock) of the ATP task at 1000 x 1000 with the
  explicit scheme on one rank (this process), after a reset.

Writes benchmarks/results/ms_explicit.csv (the rows) and ms_explicit.txt (the command, a
table, the goals met/MISSED).

    python benchmarks/ms_explicit.py [--steps 201] [--per-call 100] [--skip-3000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import time

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from bench_run import at_least, bench_record, save_results  # noqa: E402

DECISION_GRID = 1000
DECISION_STEPS = 1667  # 50 time units of dt = 0.03
SCALING = (
    "grid.n=2000",
    f"steps={2 * DECISION_STEPS + 1}",
    f"steps_per_call={DECISION_STEPS}",
    "scheme=explicit",
    "baseline=false",
)


def scaling_goal(repeats: int) -> str:
    """The 2000 x 2000 explicit steps per second on 2 ranks against 1 rank, one decision's
    steps per call, the runs alternated ``repeats`` times (the median of each), beside the same
    ratio for the floor."""
    step_ms = {}
    for _ in range(repeats):
        for ranks in (1, 2):
            for row in bench_record("ms", *SCALING, f"mpi.ranks={ranks}")["rows"]:
                step_ms.setdefault((row["implementation"], ranks), []).append(row["step_ms"])
    ours, floor = (
        np.median(step_ms[name, 1]) / np.median(step_ms[name, 2])
        for name in ("physicsrl explicit", "floor (structured C loop)")
    )
    runs = {key: ", ".join(f"{t:.2f}" for t in times) for key, times in step_ms.items()}
    return (
        f"{'met' if ours >= 1.7 else 'MISSED'}: 2000x2000 explicit, {DECISION_STEPS} steps per "
        f"call: 2 ranks {ours:.2f}x the steps/s of 1 rank >= 1.7x (the floor's ratio: "
        f"{floor:.2f}x; ms/step of {repeats} alternated runs: {runs})"
    )


def decision_seconds(n: int) -> tuple[float, float, float]:
    """(reset, wait, shock) seconds of the ATP task on n x n cells, explicit, this process."""
    from physicsrl.coordinated import Coordinator
    from physicsrl.envs import load_config, make_env
    from physicsrl.envs.atp import SHOCK, WAIT

    overrides = [f"env.mesh.cells={n}", "env.model.scheme=explicit", "env.snapshots.capacity=0"]
    env = make_env(load_config("ms", overrides=overrides), Coordinator())
    task, clock = env.task, time.perf_counter
    with task.coordinator:
        start = clock()
        task.reset(*task.draw(np.random.default_rng(0)))
        reset = clock() - start
        start = clock()
        task.step(WAIT)
        wait = clock() - start
        start = clock()
        task.step(SHOCK)
        return reset, wait, clock() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=at_least(2), default=201)
    parser.add_argument("--per-call", type=at_least(1), default=100)
    parser.add_argument("--skip-3000", action="store_true")
    parser.add_argument("--repeats", type=at_least(1), default=3, help="of the scaling runs")
    args = parser.parse_args()
    runs = [(n, ranks, args.steps) for n in (60, 1000, 2000) for ranks in (1, 2)]
    if not args.skip_3000:
        runs.append((3000, 2, 100))
    rows, goals = [], []
    for n, ranks, steps in runs:
        record = bench_record(
            "ms",
            f"grid.n={n}",
            f"steps={steps}",
            f"steps_per_call={args.per_call}",
            "scheme=both",
            "baseline=false",
            f"mpi.ranks={ranks}",
        )
        rows += record["rows"]
        goals += [f"{'met' if g['met'] else 'MISSED'}: {g['goal']}" for g in record["goals"]]
        for row in record["rows"]:
            print(
                f"{n}x{n}, {ranks} ranks, {row['implementation']}: {row['step_ms']} ms/step",
                flush=True,
            )
    goals.append(scaling_goal(args.repeats))
    reset, wait, shock = decision_seconds(DECISION_GRID)
    decision = max(wait, shock)
    goals.append(
        f"{'met' if decision <= 10 else 'MISSED'}: ATP decision at {DECISION_GRID}x"
        f"{DECISION_GRID}, explicit, 1 rank: wait {wait:.1f} s, shock {shock:.1f} s <= 10 s"
        f" (reset {reset:.1f} s)"
    )
    table = [
        f"Steps per call: {args.per_call}.",
        "",
        "| grid | ranks | implementation | setup s | ms/step | phases (ms/step) | run s |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        phases = ", ".join(
            f"{p} {r[f'{p}_ms']}"
            for p in ("solve", "rhs", "ionic", "explicit", "ghosts", "coordination")
            if r.get(f"{p}_ms")
        )
        table.append(
            f"| {r['grid']} | {r['ranks']} | {r['implementation']} | {r['setup_s']} | "
            f"{r['step_ms']} | {phases} | {r['run_s']} |"
        )
    figure, axes = plt.subplots(figsize=(6, 4))
    labels = {"physicsrl": "implicit", "physicsrl explicit": "explicit"}
    for name in ("physicsrl", "physicsrl explicit", "floor (structured C loop)"):
        ours = [r for r in rows if r["implementation"] == name and r["ranks"] == 1]
        dofs, times = [r["dofs"] for r in ours], [r["step_ms"] for r in ours]
        axes.plot(dofs, times, "o-", label=labels.get(name, name))
    axes.set(xscale="log", yscale="log", xlabel="dofs", ylabel="ms per step (1 rank)")
    axes.legend()
    save_results("ms_explicit", rows, figure, [*table, "", *goals])


if __name__ == "__main__":
    main()
