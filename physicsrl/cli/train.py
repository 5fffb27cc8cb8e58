"""``physicsrl-train [key=value ...] [mpi.ranks=N]``: DQN training (the Dojo) under Hydra + MPI.

Composes ``conf/train.yaml`` into the typed :class:`~physicsrl.config.TrainConfig`: the task
groups ``env``, ``observation``, ``reward`` (``env=NAME`` picks the task's observation and
reward unless given), the ``agent`` group (network and exploration) and sections named after
the TorchRL objects they configure (``collector``, ``buffer``, ``loss``, ``optim``, ``logger``,
``checkpoint``, ``eval``). The config is checked on every rank before anything is simulated:
an unknown key, a wrong type or a bad value exits with status 2 and one line naming the key.
Then every rank runs :func:`physicsrl.training.train`.
"""

from __future__ import annotations

from physicsrl.cli import command


def check_task(cfg) -> None:
    """The layout of environments over the job's ranks, and the task groups as
    :func:`physicsrl.envs.make_env` will read them (nothing is built); an env from
    ``env.factory`` checks its own settings."""
    from physicsrl.envs.groups import check_layout
    from physicsrl.launch import launched_size

    check_layout(cfg.mpi.ranks_per_env, launched_size() or 1)
    if cfg.env.get("factory"):
        return
    from physicsrl.envs import OBSERVATIONS, REWARDS, TASKS
    from physicsrl.envs.config import build, plain

    groups = plain(cfg)
    for group, registry in (("observation", OBSERVATIONS), ("reward", REWARDS)):
        build(*registry.lookup(groups[group]), group)
    task, settings = TASKS.lookup(groups["env"])
    build(task.Config, settings, "env")


def main() -> None:
    command.main("train", "physicsrl.training:train", check_task, pairs=True)


if __name__ == "__main__":
    main()
