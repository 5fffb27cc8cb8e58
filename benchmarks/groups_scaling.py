"""Sweep `physicsrl-bench groups` over layouts (N environments x P ranks) and fit the batched
env's own cost per step against N (issue 12).

Transitions per second of the ATP task at the report's grid for (N, P) = (1, 1), (1, 2),
(2, 1) in one run of this script, and (2, 2), (4, 1) oversubscribed (this machine has 2
cores: those rows check correctness, not speed); the learner's cost per batched step of
no-op environments at N = 1, 2, 4, 8 (its own cost: the wall time per step minus the wait for
the group leaders' replies), fitted as cost = a + b N so that N = 64 or 1000 can be predicted.
Writes benchmarks/results/groups.{csv,png,txt}.

    python benchmarks/groups_scaling.py [--decisions 5]
"""

from __future__ import annotations

import argparse

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from bench_run import at_least, bench_record, save_results  # noqa: E402

LAYOUTS = [(1, 1), (1, 2), (2, 1), (2, 2), (4, 1)]  # (N environments, P ranks each)
NO_OP_ENVS = [1, 2, 4, 8]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--decisions", type=at_least(1), default=5)
    args = parser.parse_args()

    rows = []
    for n, p in LAYOUTS:
        record = bench_record(
            "groups", f"mpi.ranks={n * p}", f"mpi.ranks_per_env={p}", f"decisions={args.decisions}"
        )
        rows += record["rows"]
    for n in NO_OP_ENVS:
        if not any(r["what"] == "no-op" and r["envs"] == n for r in rows):
            rows += bench_record("groups", f"mpi.ranks={n}", "atp=false")["rows"]

    atp = {(r["envs"], r["ranks_per_env"]): r for r in rows if r["what"] == "atp"}
    no_op = sorted((r["envs"], r["own_ms"]) for r in rows if r["what"] == "no-op")
    x, y = np.array(no_op).T
    b, a = np.polyfit(x, y, 1)
    rate = {layout: atp[layout]["transitions_per_s"] for layout in atp}
    decision_ms = atp[(1, 1)]["step_ms"]
    overhead_8 = dict(no_op)[8]
    lines = [
        f"batched env's own cost per step on the learner: {a:.3f} + {b:.4f} * N ms (no-op envs; "
        f"predicts N = 64: {a + 64 * b:.2f} ms, N = 1000: {a + 1000 * b:.1f} ms)",
        f"(2, 1) / (1, 1) transitions per second: {rate[2, 1] / rate[1, 1]:.2f}x",
        f"(2, 1) / (1, 2) transitions per second: {rate[2, 1] / rate[1, 2]:.2f}x",
        f"batched env's own cost at N = 8: {overhead_8:.3f} ms = "
        f"{100 * overhead_8 / decision_ms:.3f}% of one 60 x 60 decision ({decision_ms:.0f} ms)",
    ]
    goals = [
        ("(2, 1) >= 1.8x the transitions/s of (1, 1)", rate[2, 1] >= 1.8 * rate[1, 1]),
        ("(2, 1) >= 1.8x the transitions/s of (1, 2)", rate[2, 1] >= 1.8 * rate[1, 2]),
        ("batched env's own cost at N = 8 <= 2% of a decision", overhead_8 <= 0.02 * decision_ms),
    ]
    lines += [f"goal {'met' if met else 'MISSED'}: {text}" for text, met in goals]

    figure, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    labels = [f"N={n}, P={p}" for n, p in atp]
    left.bar(labels, [atp[k]["transitions_per_s"] for k in atp])
    left.set(ylabel="ATP transitions per second", title="60 x 60 ATP, by layout (2 cores)")
    right.plot(x, y, "o", label="measured (no-op envs)")
    right.plot(x, a + b * x, "-", label=f"{a:.3f} + {b:.4f} N ms")
    right.set(xlabel="environments N", ylabel="ms per batched step", title="learner's own cost")
    right.legend()
    save_results("groups", rows, figure, lines)


if __name__ == "__main__":
    main()
