"""Evaluate the ATP baseline policies on held-out seeds: the bar a trained agent must clear.

    mpiexec -n 2 python experiments/atp_baselines.py [--seeds 10] [--out experiments/results]

Writes ``atp_baselines.csv`` (one row per policy: mean return, success rate, mean shocks over
the seeds) and ``atp_baselines.txt`` (the command) on the leader. Seeds are the training
config's held-out evaluation seeds (1000000000, 1000000001, ...).
"""

from __future__ import annotations

import argparse
import csv
import shlex
import sys
from pathlib import Path

import numpy as np

from physicsrl.coordinated import Coordinator, abort_on_error
from physicsrl.envs import load_config, make_env
from physicsrl.envs.baselines import Constant, EveryKth, RandomActions

POLICIES = {
    "never shock": Constant(0),
    "always shock": Constant(1),
    "every 4th": EveryKth(4),
    "random (p=0.5)": RandomActions(0.5, seed=0),
}


def episode(env, policy, seed: int) -> dict:
    env.set_seed(seed)
    rollout = env.rollout(env.task.max_steps + 1, policy, break_when_any_done=True)
    return {
        "return": float(rollout["next", "reward"].sum()),
        "success": bool(rollout["next", "success"].any()),
        "shocks": int(rollout["action"].sum()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--out", type=Path, default=Path("experiments/results"))
    args = parser.parse_args()
    coordinator = Coordinator()
    env = make_env(load_config("ms", "catheter", "atp"), coordinator)
    seeds = range(1_000_000_000, 1_000_000_000 + args.seeds)
    with abort_on_error(), coordinator:
        if coordinator.is_leader():
            rows = []
            for name, policy in POLICIES.items():
                runs = [episode(env, policy, seed) for seed in seeds]
                rows.append(
                    {
                        "policy": name,
                        "return": round(float(np.mean([r["return"] for r in runs])), 2),
                        "success": float(np.mean([r["success"] for r in runs])),
                        "shocks": float(np.mean([r["shocks"] for r in runs])),
                        "seeds": len(runs),
                    }
                )
                print(rows[-1], flush=True)
            args.out.mkdir(parents=True, exist_ok=True)
            with open(args.out / "atp_baselines.csv", "w", newline="") as stream:
                writer = csv.DictWriter(stream, fieldnames=list(rows[0]))
                writer.writeheader()
                writer.writerows(rows)
            command = shlex.join(["mpiexec", "-n", str(coordinator.size), "python", *sys.argv])
            (args.out / "atp_baselines.txt").write_text(command + "\n")


if __name__ == "__main__":
    main()
