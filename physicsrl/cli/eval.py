"""``physicsrl-eval run=<run dir or checkpoint> [key=value ...] [mpi.ranks=N]``: evaluate a
trained greedy policy beside the baselines on held-out seeds.

Rebuilds the env and the Q-network from the config stored in the checkpoint (every rank builds
its part of the env, as in training; the leader evaluates), prints a table (return, success,
shocks, episode length; one episode per seed), writes ``eval.csv`` (per seed) and
``eval_summary.csv`` (means) and, for the physics tasks, ``episode.gif``: the field after the
reset and after each decision, catheter electrodes, shocks marked (by default of the first seed
whose greedy episode succeeds); with ``fields=true`` the fields of that episode as a VTX series
for ParaView (``fields.bp``) and a PNG of u drawn from the series read back (``fields.png``).
Files go to this command's run directory. After the checks below, every rank runs
:func:`physicsrl.jobs.evaluate`.
"""

from __future__ import annotations

import importlib.util

from omegaconf import OmegaConf

from physicsrl.cli import command
from physicsrl.config import TrainConfig, parse_overrides, typed
from physicsrl.launch import check_layout
from physicsrl.run_directory import checkpoint_path


def check(cfg, job) -> None:
    """The layout of the job's ranks, the run's checkpoint, the reader of ``fields=true`` and
    the ``overrides``' keys, types and values (not the network's: the stored weights fit it)."""
    check_layout(cfg.mpi.ranks_per_env, job.ranks)
    checkpoint_path(str(cfg.run))  # a checkpoint file, or a run directory with one
    if cfg.fields and importlib.util.find_spec("adios2") is None:
        raise ValueError("fields=true reads the series back with adios2: pip install adios2")
    run_config({}, list(cfg.overrides))  # the keys and types; the task groups come with the run
    for override in cfg.overrides:
        if override.lstrip("+~").startswith("agent.network"):
            raise ValueError(f"overrides: {override}: the stored weights fit the run's network")


def run_config(stored: dict, overrides: list[str]):
    """The training config of the evaluated run: ``stored`` (its checkpoint's) changed by
    ``overrides``, typed; ValueError naming the key."""
    changes = parse_overrides(overrides)
    try:
        merged = OmegaConf.merge(OmegaConf.structured(TrainConfig), stored, changes)
        typed(merged)
    except Exception as error:  # noqa: BLE001 - OmegaConf's errors name the key
        raise ValueError(f"overrides: {command.one_line(error)}") from error
    return merged


def main() -> None:
    command.main("eval", "physicsrl.jobs:evaluate", check)


if __name__ == "__main__":
    main()
