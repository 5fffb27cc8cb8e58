"""Evaluate the ATP baseline policies on held-out seeds: the bar a trained agent must clear.

    python experiments/atp_baselines.py [--experiment atp] [--seeds 20] [--open-loop]
                                        [--select-seeds 5] [--single-shock K]
                                        [--policies NAME,...] [--schedules NAME,...]
                                        [--two-shocks GAP,...] [--seed-list SEED,...]
                                        [--resume] [key=value ...]
    mpiexec -n 2 python experiments/atp_baselines.py ...   # 2 environments share the seeds

The env is the training preset's (``physicsrl-train +experiment=EXPERIMENT``), composed by
Hydra exactly as the training run composes it, and built as the run builds it: W ranks run
W / ``mpi.ranks_per_env`` environments (times ``env.replicas`` on the torch backend), which
share the episodes (same rows as one): with N environments and K seeds, N / K policies run
together, each environment taking the next episode as soon as its own ends.

Policies (default): never shock, always shock, random (p = 0.5), shock every 4th decision, and
the best single shock: the decision of the one shock (or none) is chosen by mean return on the
first ``--select-seeds`` seeds (every decision tried), then evaluated on all seeds;
``--single-shock K`` fixes the decision instead (:func:`~physicsrl.envs.baselines.atp_baselines`).
``--policies`` keeps only the named ones (never,always,random,every4,single), ``--schedules``
the named schedules of ``--open-loop`` (comma-separated display names).

``--open-loop`` evaluates instead every open-loop schedule on all seeds
(:func:`~physicsrl.envs.baselines.open_loop_schedules`: never, always, one shock at each
decision, every k-th decision from each offset for k = 2..6) and names the best: the bar of
closed-loop control, and the per-seed hindsight oracle of the schedules (:func:`hindsight`).
``--open-loop --two-shocks 1,2,3`` searches instead every schedule of two shocks at decisions
i < j with j - i in 1, 2, 3 (:func:`~physicsrl.envs.baselines.two_shock_schedules`).
Seeds are the held-out evaluation seeds 1000000000, 1000000001, ..., or with ``--first-seed
S`` the seeds S, S + 1, ... (e.g. the draws labelled by ``atp_shock_timing.py``), or with
``--seed-list`` the seeds listed.

Writes, on the leader, ``<name>.csv`` (one row per policy: mean return, success rate, mean
shocks and decisions), ``<name>_per_seed.csv`` (after each policy) and ``<name>.txt`` (the
command, commit and settings), where name is ``<experiment>_baselines``,
``<experiment>_open_loop`` or ``<experiment>_two_shocks``. ``--resume`` keeps the policies
already in ``<name>_per_seed.csv`` when the settings are the same (the held-out seeds' draws
included), and adds its command and commit to ``<name>.txt``.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

import numpy as np

from physicsrl import builders
from physicsrl.checks import build, plain
from physicsrl.cli.train import train_config
from physicsrl.config import held_out_seeds
from physicsrl.coordinated import abort_on_error
from physicsrl.envs.atp import ATPConfig, ResetSampler
from physicsrl.envs.baselines import (
    atp_baselines,
    decisions,
    open_loop_schedules,
    two_shock_schedules,
)
from physicsrl.envs.layout import environments
from physicsrl.envs.task import TASKS
from physicsrl.evaluation import compare
from physicsrl.learner import n_environments
from physicsrl.tables import mean_metrics, provenance, read_per_policy, write_csv

POLICIES = ("never", "always", "random", "every4", "single")  # atp_baselines' order


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--experiment", default="atp", help="the preset: atp | atp_wide | ...")
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument(
        "--first-seed", type=int, help="seeds FIRST, FIRST+1, ... instead of the held-out seeds"
    )
    parser.add_argument("--seed-list", help="these seeds instead, e.g. 2000000008,2000000021")
    parser.add_argument("--open-loop", action="store_true", help="search every open-loop schedule")
    parser.add_argument("--two-shocks", help="--open-loop: two shocks instead, these gaps apart")
    parser.add_argument("--select-seeds", type=int, default=5)
    parser.add_argument("--single-shock", type=int, help="the single shock's decision (no search)")
    parser.add_argument("--policies", default=",".join(POLICIES))
    parser.add_argument("--schedules", help="--open-loop: only these, e.g. 'single shock at 0'")
    parser.add_argument("--resume", action="store_true", help="keep the policies already done")
    parser.add_argument("--out", type=Path, default=Path("experiments/results"))
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. env.mesh.cells=20")
    args = parser.parse_args()
    if args.seeds < 1:
        parser.error(f"--seeds {args.seeds}: must be an integer >= 1")
    keep = args.policies.split(",")
    unknown = [k for k in keep if k not in POLICIES]
    if unknown:
        parser.error(f"--policies: unknown {unknown}; use {','.join(POLICIES)}")
    gaps = integers(parser, "--two-shocks", args.two_shocks)
    if gaps and (not args.open_loop or min(gaps) < 1):
        parser.error(f"--two-shocks {args.two_shocks}: needs --open-loop and gaps >= 1")
    listed = integers(parser, "--seed-list", args.seed_list)
    if listed and args.first_seed is not None:
        parser.error("--seed-list and --first-seed: give one of them")
    family = "two_shocks" if gaps else "open_loop" if args.open_loop else "baselines"
    name = f"{args.experiment}_{family}"
    seeds_given = len(listed) if listed else args.seeds
    settings = {"experiment": args.experiment, "seeds": seeds_given, "overrides": args.overrides}
    if args.first_seed is not None:  # 0 is a first seed too
        settings["first_seed"] = args.first_seed
    if listed:
        settings["seed_list"] = listed
    if gaps:
        settings["gaps"] = gaps
    cfg = train_config([f"+experiment={args.experiment}", *args.overrides])
    make_env = lambda coordinator: builders.make_env(cfg, coordinator)  # noqa: E731
    with abort_on_error(), environments(make_env, cfg.mpi.ranks_per_env) as env:
        if env is None:  # a rank that served an environment
            return
        first = args.first_seed
        seeds = listed or (
            held_out_seeds(args.seeds) if first is None else list(range(first, first + args.seeds))
        )
        settings["draws"] = draws(cfg, seeds)
        done = previous_rows(args.out / name, settings) if args.resume else {}
        if args.open_loop:
            n = decisions(env)
            policies = two_shock_schedules(n, gaps) if gaps else open_loop_schedules(n)
            if args.schedules:
                names = args.schedules.split(",")
                if set(names) - set(policies):
                    parser.error(f"--schedules: unknown {sorted(set(names) - set(policies))}")
                policies = {name: policies[name] for name in names}
        else:
            single = args.single_shock if "single" in keep else 0  # 0: no search when unused
            policies = atp_baselines(env, seeds[: args.select_seeds], single_shock=single)
            policies = {
                n: p for k, (n, p) in zip(POLICIES, policies.items(), strict=True) if k in keep
            }
        args.out.mkdir(parents=True, exist_ok=True)
        record = args.out / f"{name}.txt"
        call = f"{shlex.join(['python', *sys.argv])}\n{provenance()}\n"
        if done:  # a resumed search: every call that computed rows stays on record
            record.write_text(record.read_text() + call)
        else:
            record.write_text(f"settings {json.dumps(settings)}\n{call}")
        todo = [policy for policy in policies if policy not in done]
        together = max(1, n_environments(env) // len(seeds))  # policies sharing the members
        for start in range(0, len(todo), together):
            chunk = {policy: policies[policy] for policy in todo[start : start + together]}
            rows, _ = compare(env, chunk, seeds, env.task.action_counts)
            for policy in chunk:
                done[policy] = [row for row in rows if row["policy"] == policy]
                print({"policy": policy, **rounded(mean_metrics(done[policy]))}, flush=True)
            per_seed = [row for policy in policies if policy in done for row in done[policy]]
            write_csv(args.out / f"{name}_per_seed.csv", per_seed)
        means = [{"policy": p, **rounded(mean_metrics(done[p]))} for p in policies]
        write_csv(args.out / f"{name}.csv", means)
        if args.open_loop:
            best = max(means, key=lambda row: row["return"])
            bar = "" if gaps else " (the bar)"  # two-shock schedules are not the bar's family
            print(f"best of these schedules by mean return{bar}: {best}", flush=True)
            print(f"per-seed hindsight oracle of these schedules: {hindsight(done)}", flush=True)


def integers(parser: argparse.ArgumentParser, option: str, text: str | None) -> list[int]:
    """The comma-separated integers of ``option`` ([] when not given); a bad one ends the run
    with one line naming it."""
    try:
        return [int(item) for item in text.split(",")] if text else []
    except ValueError:
        parser.error(f"{option} {text}: expected comma-separated integers")


def previous_rows(stem: Path, settings: dict) -> dict[str, list[dict]]:
    """Policy -> per-seed rows of a previous run with the same ``settings`` (one line and exit
    2 when they differ); {} when there is none."""
    record, table = stem.with_suffix(".txt"), Path(f"{stem}_per_seed.csv")
    if not (record.exists() and table.exists()):
        return {}
    line = next((s for s in record.read_text().splitlines() if s.startswith("settings ")), "")
    if json.loads(line.removeprefix("settings ") or "{}") != settings:
        print(f"error: --resume: {record} was made with other settings ({line})", file=sys.stderr)
        raise SystemExit(2)
    rows = {p: [{"policy": p, **row} for row in r] for p, r in read_per_policy(table).items()}
    return {k: v for k, v in rows.items() if len(v) == settings["seeds"]}


def draws(cfg, seeds: list[int]) -> list[list[float]]:
    """The reset draws of ``seeds`` in the task of ``cfg`` (any backend)."""
    _, settings = TASKS.lookup(plain(cfg)["env"])
    sampler = ResetSampler(build(ATPConfig, settings, "env"))
    return [list(sampler(np.random.default_rng(seed))) for seed in seeds]


def hindsight(rows: dict[str, list[dict]]) -> dict:
    """The best policy of ``rows`` (policy -> its per-seed rows) on each seed, chosen with
    hindsight: the mean return and success of those choices (what the agent's timing could
    win at most by choosing among these policies per seed; not a policy) and the seeds
    that no policy ends."""
    best: dict[int, dict] = {}
    for row in (row for per_seed in rows.values() for row in per_seed):
        if row["seed"] not in best or row["return"] > best[row["seed"]]["return"]:
            best[row["seed"]] = row
    chosen = list(best.values())
    return {
        "return": round(sum(row["return"] for row in chosen) / len(chosen), 3),
        "success": sum(row["success"] for row in chosen) / len(chosen),
        "unended": sorted(seed for seed, row in best.items() if not row["success"]),
    }


def rounded(row: dict) -> dict:
    return {k: round(v, 3) if isinstance(v, float) else v for k, v in row.items()}


if __name__ == "__main__":
    main()
