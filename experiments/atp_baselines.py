"""Evaluate the ATP baseline policies on held-out seeds: the bar a trained agent must clear.

    python experiments/atp_baselines.py [--experiment atp] [--seeds 20] [--select-seeds 5]
                                        [--single-shock K] [--policies NAME,...] [key=value ...]

The env is the training preset's (``physicsrl-train +experiment=EXPERIMENT``), composed by
Hydra exactly as the training run composes it. Policies: never shock, always shock, random
(p = 0.5), shock every 4th decision, and the best single shock: the decision of the one shock
(or none) is chosen by mean return on the first ``--select-seeds`` seeds (every decision
tried), then evaluated on all seeds; ``--single-shock K`` fixes the decision instead.
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
from physicsrl.cli.eval import write_csv
from physicsrl.cli.train import compose
from physicsrl.coordinated import Coordinator, abort_on_error
from physicsrl.dojo import episode_metrics, held_out_seeds, mean_metrics
from physicsrl.envs.baselines import (
    Constant,
    EveryKth,
    RandomActions,
    Schedule,
    best_single_shock,
)


def episode(env, policy, seed: int) -> dict:
    """One episode of ``policy`` from the env seeded with ``seed``: return, success, shocks."""
    env.set_seed(seed)
    rollout = env.rollout(env.task.max_steps + 1, policy, break_when_any_done=True)
    metrics = episode_metrics(rollout, {"shocks": 1})
    return {k: metrics[k] for k in ("return", "success", "shocks", "length")}


POLICIES = ("never", "always", "random", "every4", "single")


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
    seeds = list(held_out_seeds(args.seeds))
    with abort_on_error(), coordinator:
        if not coordinator.is_leader():
            return
        policies = {
            "never": ("never shock", Constant(0)),
            "always": ("always shock", Constant(1)),
            "random": ("random (p=0.5)", RandomActions(0.5, seed=0)),
            "every4": ("every 4th", EveryKth(4)),
        }
        if "single" in keep:
            if args.single_shock is not None:
                best = Schedule([args.single_shock])
            else:
                best, means = best_single_shock(env, seeds[: args.select_seeds])
                print(f"mean return of one shock at each decision (None: none): {means}")
            policies["single"] = (f"single shock {sorted(best.steps)}", best)
        policies = dict(policies[k] for k in keep)
        rows, per_seed = [], []
        for name, policy in policies.items():
            runs = [{"policy": name, "seed": s, **episode(env, policy, s)} for s in seeds]
            per_seed.extend(runs)
            numbers = [{k: v for k, v in r.items() if k not in ("policy", "seed")} for r in runs]
            mean = mean_metrics(numbers)
            rows.append({"policy": name, **{k: round(v, 3) for k, v in mean.items()}})
            print(rows[-1], flush=True)
        args.out.mkdir(parents=True, exist_ok=True)
        write_csv(args.out / f"{args.experiment}_baselines.csv", rows)
        write_csv(args.out / f"{args.experiment}_baselines_per_seed.csv", per_seed)
        command = shlex.join(["python", *sys.argv])
        (args.out / f"{args.experiment}_baselines.txt").write_text(
            f"{command}\ncommit {commit or 'unknown'}\n"
        )


if __name__ == "__main__":
    main()
