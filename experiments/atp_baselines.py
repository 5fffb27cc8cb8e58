"""Evaluate the ATP baseline policies on held-out seeds: the bar a trained agent must clear.

    python experiments/atp_baselines.py [--experiment atp] [--seeds 20] [--select-seeds 5]
                                        [--single-shock K] [--policies NAME,...] [key=value ...]

The env is the training preset's (``physicsrl-train +experiment=EXPERIMENT``), composed by
Hydra exactly as the training run composes it. Policies: never shock, always shock, random
(p = 0.5), shock every 4th decision, and the best single shock: the decision of the one shock
(or none) is chosen by mean return on the first ``--select-seeds`` seeds (every decision
tried), then evaluated on all seeds; ``--single-shock K`` fixes the decision instead. The
policies and their names are the ATP task's baselines
(:func:`~physicsrl.envs.baselines.atp_baselines`).
``--policies`` keeps only the named ones (never,always,random,every4,single). Seeds are the
held-out evaluation seeds 1000000000, 1000000001, ...

Writes, on the leader, ``<experiment>_baselines.csv`` (one row per policy: mean return, success
rate, mean shocks and decisions), ``<experiment>_baselines_per_seed.csv`` and
``<experiment>_baselines.txt`` (the command and commit).
"""

from __future__ import annotations

import argparse
import shlex
import subprocess
import sys
from pathlib import Path

from physicsrl import builders
from physicsrl.cli.command import compose
from physicsrl.config import held_out_seeds
from physicsrl.coordinated import Coordinator, abort_on_error
from physicsrl.envs.baselines import atp_baselines
from physicsrl.evaluation import compare, write_csv

POLICIES = ("never", "always", "random", "every4", "single")  # atp_baselines' order


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--experiment", default="atp", help="the preset: atp | atp_wide")
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--select-seeds", type=int, default=5)
    parser.add_argument("--single-shock", type=int, help="the single shock's decision (no search)")
    parser.add_argument("--policies", default=",".join(POLICIES))
    parser.add_argument("--out", type=Path, default=Path("experiments/results"))
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. env.mesh.cells=20")
    args = parser.parse_args()
    keep = args.policies.split(",")
    unknown = [k for k in keep if k not in POLICIES]
    if unknown:
        parser.error(f"--policies: unknown {unknown}; use {','.join(POLICIES)}")
    commit = subprocess.run(
        ["git", "rev-parse", "HEAD"], capture_output=True, text=True, cwd=Path(__file__).parent
    ).stdout.strip()
    cfg = compose("train", [f"+experiment={args.experiment}", *args.overrides])
    coordinator = Coordinator()
    env = builders.make_env(cfg, coordinator)
    seeds = held_out_seeds(args.seeds)
    with abort_on_error(), coordinator:
        if not coordinator.is_leader():
            return
        single = args.single_shock if "single" in keep else 0  # 0: no search when unused
        policies = atp_baselines(env, seeds[: args.select_seeds], single_shock=single)
        policies = {n: p for k, (n, p) in zip(POLICIES, policies.items(), strict=True) if k in keep}
        per_seed, means = compare(env, policies, seeds, env.task.action_counts)
        rows = [
            {k: round(v, 3) if isinstance(v, float) else v for k, v in r.items()} for r in means
        ]
        print(*rows, sep="\n", flush=True)
        args.out.mkdir(parents=True, exist_ok=True)
        write_csv(args.out / f"{args.experiment}_baselines.csv", rows)
        write_csv(args.out / f"{args.experiment}_baselines_per_seed.csv", per_seed)
        command = shlex.join(["python", *sys.argv])
        (args.out / f"{args.experiment}_baselines.txt").write_text(
            f"{command}\ncommit {commit or 'unknown'}\n"
        )


if __name__ == "__main__":
    main()
