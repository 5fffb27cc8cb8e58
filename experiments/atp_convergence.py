"""Mesh convergence of the ATP task: the baseline policies' outcomes on the same held-out draws
at increasing resolution.

    python experiments/atp_convergence.py --experiment atp --cells 120 [--seeds 5 | --draws 1,7]
        [--policies never,single0,single1,single2,single3,every4] [key=value ...]
    mpiexec -n 4 python experiments/atp_convergence.py ...   # 4 environments share the seeds

One grid per call (``env.mesh.cells=CELLS``; unless ``env.model.scheme`` is given, the explicit
scheme above 250 cells per side, where the implicit one costs minutes per decision). Policies:
never shock, a single shock at decision k (``singleK``), every k-th decision from decision 0
(``everyK``) or from o (``everyKfromO``). Seeds are the
held-out evaluation seeds 1000000000, 1000000001, ... Every episode appends one row (cells,
scheme, policy, seed, return, success, shocks, length = decisions to success or failure) to
``<experiment>_convergence.csv`` on the leader; rows already there are skipped, so a stopped
study resumes. The command and commit of each call are appended to
``<experiment>_convergence.txt``.
"""

from __future__ import annotations

import argparse
import csv
import re
import shlex
import sys
from pathlib import Path

from physicsrl import builders
from physicsrl.checks import integer
from physicsrl.cli.train import train_config
from physicsrl.config import held_out_seeds
from physicsrl.coordinated import abort_on_error
from physicsrl.envs.baselines import Constant, EveryKth, Schedule
from physicsrl.envs.groups import GroupedEnv
from physicsrl.envs.layout import environments
from physicsrl.evaluation import run_episodes
from physicsrl.tables import provenance

EXPLICIT_ABOVE = 250
FIELDS = ("cells", "scheme", "policy", "seed", "return", "success", "shocks", "length")


def policy(name: str):
    if name == "never":
        return Constant(0)
    if name.startswith("single") and name[6:].isdigit():
        return Schedule([int(name[6:])])
    every = re.fullmatch(r"every(\d+)(?:from(\d+))?", name)
    if every:
        return EveryKth(int(every[1]), int(every[2] or 0))
    raise ValueError(f"--policies: unknown policy {name!r} (never, singleK, everyK, everyKfromO)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--experiment", default="atp", help="the preset: atp | atp_resolved")
    parser.add_argument("--cells", type=int, required=True, help="cells per side")
    parser.add_argument("--seeds", type=int, default=5, help="the first N held-out seeds")
    parser.add_argument("--draws", help="only these held-out seeds, by index: 1,7 (of --seeds)")
    parser.add_argument("--policies", default="never,single0,single1,single2,single3,every4")
    parser.add_argument("--out", type=Path, default=Path("experiments/results"))
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. env.extra_waits=0")
    args = parser.parse_args()
    try:
        integer("--seeds", args.seeds, 1)
        policies = {name: policy(name) for name in args.policies.split(",")}
    except ValueError as error:
        parser.error(str(error))
    draws = args.draws.split(",") if args.draws else range(args.seeds)
    if not {str(i) for i in draws} <= {str(i) for i in range(args.seeds)}:
        parser.error(f"--draws {args.draws}: indices from 0 to --seeds - 1 = {args.seeds - 1}")
    default = "explicit" if args.cells > EXPLICIT_ABOVE else "implicit"
    overrides = [f"env.mesh.cells={args.cells}", f"env.model.scheme={default}", *args.overrides]
    cfg = train_config([f"+experiment={args.experiment}", *overrides])
    scheme = cfg.env.model.scheme  # an env.model.scheme override wins
    make_env = lambda coordinator: builders.make_env(cfg, coordinator)  # noqa: E731
    results = args.out / f"{args.experiment}_convergence.csv"
    with abort_on_error(), environments(make_env, cfg.mpi.ranks_per_env) as env:
        if env is None:  # a rank that served an environment
            return
        args.out.mkdir(parents=True, exist_ok=True)
        with (args.out / f"{args.experiment}_convergence.txt").open("a") as log:
            log.write(f"{shlex.join(['python', *sys.argv])}  # {provenance()}\n")
        done = set()
        if results.exists():
            with results.open() as file:
                done = {
                    (r["cells"], r["scheme"], r["policy"], r["seed"]) for r in csv.DictReader(file)
                }
        n = env.batch_size[0] if isinstance(env, GroupedEnv) else 1
        seeds = [held_out_seeds(args.seeds)[int(i)] for i in draws]
        for name, actions in policies.items():
            todo = [s for s in seeds if (str(args.cells), scheme, name, str(s)) not in done]
            for start in range(0, len(todo), n):  # one episode per environment, then saved
                for row in run_episodes(
                    env, actions, todo[start : start + n], env.task.action_counts
                ):
                    row = {"cells": args.cells, "scheme": scheme, "policy": name, **row}
                    new = not results.exists()
                    with results.open("a", newline="") as file:
                        writer = csv.DictWriter(file, FIELDS, extrasaction="ignore")
                        if new:
                            writer.writeheader()
                        writer.writerow(row)
                    print({k: row[k] for k in FIELDS}, flush=True)


if __name__ == "__main__":
    main()
