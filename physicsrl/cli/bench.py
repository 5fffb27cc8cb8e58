"""``physicsrl-bench NAME [overrides]``: the benchmarks, beside their baselines, as tables.

Each benchmark ``NAME`` is the module ``physicsrl.bench.NAME`` (``run(cfg) -> rows``, and
optionally ``goals(rows)``) with the config ``conf/bench_NAME.yaml``, whose settings are
checked against ``physicsrl.bench.SETTINGS[NAME]`` (type and least value, or choices) before
any work and before the module is imported, for every job of a ``-m`` sweep. The leader prints
the table and the goals and writes ``NAME.csv`` and ``NAME.json`` (with the command line) into
the run directory.
"""

from __future__ import annotations

import importlib
import json
import math
import shlex
import sys

from hydra.core.hydra_config import HydraConfig
from omegaconf import OmegaConf

from physicsrl.bench import SETTINGS
from physicsrl.checks import build, plain
from physicsrl.cli.command import validate_or_exit
from physicsrl.config import MESH_BYTES_PER_CELL, check_needs
from physicsrl.guard import guard
from physicsrl.launch import check_layout, output_dir, refuse, relaunch, run_hydra
from physicsrl.tables import format_table, write_csv

BENCHMARKS = {
    "ping": "cost of one parallel call (report section 3.5)",
    "ms": "monodomain Mitchell-Schaeffer steps (report section 4.3.3)",
    "env": "ATP environment throughput and TorchRL overhead",
    "groups": "N simulator groups x P ranks: transitions per second, batched-env cost",
}

USAGE = "usage: physicsrl-bench NAME [key=value ...] [mpi.ranks=N] [--help | --cfg job]\n\n" + (
    "\n".join(f"  {name:6s} {what}" for name, what in BENCHMARKS.items())
)


def check_settings(cfg, settings: dict[str, tuple[type | tuple[str, ...], float | None]]) -> None:
    """ValueError naming a setting that is not of its type (int, float or bool) or is below its
    least value (None: no bound), or is not one of its choices (a tuple of strings)."""
    for key, (kind, least) in settings.items():
        value = OmegaConf.select(cfg, key)
        if isinstance(kind, tuple):
            if value not in kind:
                raise ValueError(f"{key}={value}: must be one of {', '.join(kind)}")
            continue
        allowed = (int, float) if kind is float else kind
        if kind is bool:
            ok = isinstance(value, bool)
        else:
            ok = isinstance(value, allowed) and not isinstance(value, bool)
            ok = ok and math.isfinite(value) and (least is None or value >= least)
        if not ok:
            what = {int: "an integer", float: "a finite number", bool: "true or false"}[kind]
            bound = f" >= {least}" if least is not None and kind is not bool else ""
            raise ValueError(f"{key}={value}: must be {what}{bound}")


def check(cfg, job, name: str) -> None:
    """:func:`check_settings` of benchmark ``name``, the settings that must agree (ms: more
    steps than the first call's, which is timed apart; groups: the layout of the job's ranks
    and no reset within the timed decisions), the ATP task it builds from its ``overrides``
    (benchmarks env and groups), as ``make_env`` will read it, and the memory per rank of the
    simulators it builds, within ``max_memory_gb``, as ``physicsrl-train`` estimates it (ms:
    each simulator it keeps, the report's LU baseline counted as one more; env and groups: the
    task's); nothing is built."""
    check_settings(cfg, SETTINGS[name])
    needs = {}
    if name == "ms":
        builds = (2 if cfg.scheme == "both" else 1) + int(cfg.baseline)
        needs[f"grid.n={cfg.grid.n}"] = (
            builds * cfg.grid.n**2 * MESH_BYTES_PER_CELL / job.ranks,
            f"{builds} simulator(s) of {MESH_BYTES_PER_CELL} bytes per cell, over mpi.ranks="
            f"{job.ranks}, per rank",
        )
    if name == "ms" and cfg.steps <= cfg.steps_per_call:
        raise ValueError(
            f"steps={cfg.steps}: must exceed steps_per_call={cfg.steps_per_call} (the first "
            "call is timed apart from the others)"
        )
    if name == "groups":
        check_layout(cfg.mpi.ranks_per_env, job.ranks)
    if "overrides" in cfg:
        from physicsrl.envs import TASKS, load_config  # MPI: after the re-launch
        from physicsrl.envs.factory import simulator_needs

        groups = plain(load_config("ms", overrides=list(cfg.overrides)))
        task, settings = TASKS.lookup(groups["env"])
        env = build(task.Config, settings, "env")
        if name == "groups" and cfg.decisions > env.max_decisions:
            raise ValueError(
                f"decisions={cfg.decisions}: must be at most env.max_decisions="
                f"{env.max_decisions} (no reset within the timed steps)"
            )
        grouped = name == "groups"
        ranks = cfg.mpi.ranks_per_env if grouped else job.ranks
        key = "mpi.ranks_per_env" if grouped else "mpi.ranks"
        needs = simulator_needs(env, ranks, f"{key}={ranks}")
    if needs:  # benchmarks that build a simulator
        check_needs(needs, cfg.max_memory_gb)


def report(name: str, rows: list[dict], goals: list[tuple[str, bool]]) -> None:
    """Print the table and goals, and write them beside the command line that reruns this job
    (a sweep's job: its own values) (leader only)."""
    print(format_table(rows))
    for text, met in goals:
        print(f"goal {'met' if met else 'MISSED'}: {text}")
    directory = output_dir()
    write_csv(directory / f"{name}.csv", rows)
    command = shlex.join(["physicsrl-bench", name, *HydraConfig.get().overrides.task])
    record = {"command": command, "rows": rows, "goals": [{"goal": t, "met": m} for t, m in goals]}
    (directory / f"{name}.json").write_text(json.dumps(record, indent=2))
    print(f"results: {directory / (name + '.csv')}")


def main() -> None:
    arguments = sys.argv[1:]
    if not arguments or arguments[0] in ("-h", "--help"):
        print(USAGE)
        return
    name, overrides = arguments[0], arguments[1:]
    if name not in BENCHMARKS:
        choose = f"choose one of {', '.join(BENCHMARKS)}"
        if "=" in name or name.startswith("-"):  # the name left out, or after a flag
            refuse(f"{name}: the first argument names the benchmark; {choose}")
        refuse(f"unknown benchmark {name!r}; {choose}")
    relaunch(overrides)
    guard()
    validate_or_exit(f"bench_{name}", overrides, lambda cfg, job: check(cfg, job, name))
    module = importlib.import_module(f"physicsrl.bench.{name}")

    def task(cfg) -> None:
        from mpi4py import MPI  # after the re-launch

        rows = module.run(cfg)
        if MPI.COMM_WORLD.rank == 0:
            report(name, rows, module.goals(rows) if hasattr(module, "goals") else [])

    run_hydra(f"bench_{name}", task, overrides)


if __name__ == "__main__":
    main()
