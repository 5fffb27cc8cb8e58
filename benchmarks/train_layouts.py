"""Wall time of `physicsrl-train +experiment=atp` for the same number of episodes, by layout
(issue 12).

Three runs of the ATP preset (the report's 60 x 60 grid), each for ``--episodes`` episodes
(``reset_at_each_iter``: one batch of the preset's ``frames_per_env`` = 15 transitions per
environment is one episode each) with the same number of gradient updates per transition:

- ``one env on 2 ranks``: ``mpi.ranks=2 mpi.ranks_per_env=2``, what ``mpi.ranks=2`` meant
  before environments were grouped (the baseline of the goal);
- ``one env on 1 rank``: ``mpi.ranks=1``, the fastest single environment;
- ``2 envs of 1 rank``: ``mpi.ranks=2``, the default layout now.

The training time is the run's wall time less its final evaluation (the greedy policy on
``eval.seeds``, here one seed); both are printed. Writes
benchmarks/results/train_layouts.{csv,png,txt}.

    python benchmarks/train_layouts.py [--episodes 6]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from bench_run import save_results  # noqa: E402

LAYOUTS = {  # name: (mpi.ranks, mpi.ranks_per_env)
    "one env on 2 ranks": (2, 2),
    "one env on 1 rank": (1, 1),
    "2 envs of 1 rank": (2, 1),
}
UPDATES_PER_EPISODE = 32  # the preset's updates per batch of one episode


def train(ranks: int, per_env: int, episodes: int) -> dict:
    """Run the preset for ``episodes`` episodes; its summary."""
    n = ranks // per_env
    train_command = Path(sys.executable).with_name("physicsrl-train")
    with tempfile.TemporaryDirectory() as directory:
        command = [
            str(train_command),
            "+experiment=atp",
            f"mpi.ranks={ranks}",
            f"mpi.ranks_per_env={per_env}",
            f"iterations={episodes // n}",
            f"optim.updates_per_batch={UPDATES_PER_EPISODE * n}",
            "optim.learning_starts=30",
            "eval.every=0",
            "eval.seeds=[1000000000]",
            "checkpoint.every=0",
            "logger.progress=false",
            f"hydra.run.dir={directory}",
        ]
        subprocess.run(command, check=True, capture_output=True, text=True)
        return json.loads((Path(directory) / "summary.json").read_text())["summary"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=6, help="an even number")
    args = parser.parse_args()
    if args.episodes < 2 or args.episodes % 2:
        parser.error(f"--episodes={args.episodes}: must be an even number >= 2")

    rows = []
    for name, (ranks, per_env) in LAYOUTS.items():
        summary = train(ranks, per_env, args.episodes)
        evaluation = summary["time_s"].get("evaluation", 0.0)
        rows.append(
            {
                "layout": name,
                "ranks": ranks,
                "envs": ranks // per_env,
                "episodes": summary["episodes"],
                "frames": summary["frames"],
                "updates": summary["updates"],
                "wall_s": round(summary["wall_s"], 1),
                "training_s": round(summary["wall_s"] - evaluation, 1),
            }
        )
        print(rows[-1], flush=True)
    seconds = {row["layout"]: row["training_s"] for row in rows}
    new = seconds["2 envs of 1 rank"]
    lines = [
        f"{row['layout']}: {row['episodes']} episodes, {row['updates']} updates, training "
        f"{row['training_s']} s (wall {row['wall_s']} s with the final evaluation)"
        for row in rows
    ]
    lines += [
        f"2 envs of 1 rank / one env on 2 ranks: {new / seconds['one env on 2 ranks']:.2f}x",
        f"2 envs of 1 rank / one env on 1 rank: {new / seconds['one env on 1 rank']:.2f}x",
    ]
    met = new <= 0.6 * seconds["one env on 2 ranks"]
    lines.append(
        f"goal {'met' if met else 'MISSED'}: mpi.ranks=2 trains the same episodes in <= 0.6x "
        "the training time of one environment on 2 ranks"
    )
    figure, axes = plt.subplots(figsize=(6, 4))
    axes.bar(list(seconds), list(seconds.values()))
    axes.set(ylabel="training wall time (s)", title=f"ATP preset, {args.episodes} episodes")
    save_results("train_layouts", rows, figure, lines)


if __name__ == "__main__":
    main()
