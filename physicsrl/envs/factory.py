"""``make_env(cfg, coordinator)``: the environment a config describes (stable entry point).

``cfg`` (a ``DictConfig`` or plain mapping) has the groups

- ``env``: ``name`` (a task in :data:`~physicsrl.envs.task.TASKS`: ``heat``, ``atp``) and that
  task's settings (``conf/env/heat.yaml``, ``conf/env/ms.yaml``);
- ``observation``: ``name`` (``quadrants``, ``catheter``) and its settings;
- ``reward``: ``name`` (``heat_stop``, ``atp``) and its settings;
- ``seed`` (optional, default None): the seed of the episode randomness.

Call it on every rank, in the same order relative to other coordinated objects; then only the
leader calls ``reset``/``step``, inside ``with coordinator:``. Bad settings raise ValueError
naming the key (``env.dt must be ...``), and so does a simulator whose estimated memory per rank
(:func:`simulator_needs`) exceeds ``cfg.max_memory_gb`` (default: ``physicsrl-train``'s), before
its mesh is made. With ``env.model.backend=torch`` (the ATP task) the env
is :class:`~physicsrl.envs.batched.BatchedATPEnv`: ``env.replicas`` copies of the task on this
rank alone (a group of one rank).

The ranks that only serve a coordinator's leader never step the env: :func:`make_env_for_rank`
builds there the task alone (:func:`make_task`, the same collective calls), so that they import
no torch (``benchmarks/follower_memory.py``: their peak memory). This module imports torch only
in :func:`make_env`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from physicsrl.checks import build, integer, plain
from physicsrl.config import (
    MESH_BYTES_PER_CELL,
    STATE_BYTES_PER_DOF,
    check_needs,
    train_default,
)
from physicsrl.coordinated import Coordinator
from physicsrl.envs.observations import OBSERVATIONS
from physicsrl.envs.rewards import REWARDS
from physicsrl.envs.task import TASKS, SquareMesh, Task
from physicsrl.launch import check_backend

if TYPE_CHECKING:
    from torchrl.envs import EnvBase


def make_env(cfg: Mapping | Any, coordinator: Coordinator) -> EnvBase:
    """Build task (on this rank), observation and reward from ``cfg``; see the module docstring."""
    cfg = plain(cfg)
    observation, reward, task_class, config = parts(cfg)
    check_memory(cfg, config, coordinator)
    if getattr(getattr(config, "model", None), "backend", None) == "torch":
        from physicsrl.envs.batched import BatchedATPEnv  # torch's time loop

        check_backend("torch", coordinator.comm.size)
        return BatchedATPEnv(config, observation, reward, seed=cfg.get("seed"))
    from physicsrl.envs.env import PhysicsEnv  # TorchRL: on the ranks that step an env

    return PhysicsEnv(task_class(coordinator, config, observation), reward, seed=cfg.get("seed"))


def make_task(cfg: Mapping | Any, coordinator: Coordinator) -> Task:
    """The task of :func:`make_env`'s env alone (its simulator side; no torch): what a rank that
    only serves ``coordinator``'s leader needs. Collective as :func:`make_env` is."""
    cfg = plain(cfg)
    observation, _, task_class, config = parts(cfg)
    check_memory(cfg, config, coordinator)
    if getattr(getattr(config, "model", None), "backend", None) == "torch":
        check_backend("torch", coordinator.comm.size)  # its env has no followers: refused
    return task_class(coordinator, config, observation)


def make_env_for_rank(cfg: Mapping | Any, coordinator: Coordinator) -> EnvBase | Task:
    """What this rank of ``coordinator`` builds of ``cfg``'s env: the env on the leader
    (:func:`physicsrl.builders.make_env`: ``env.factory``'s, else :func:`make_env`), the task
    alone on the other ranks, which only serve the leader's parallel calls (:func:`make_task`);
    an ``env.factory``'s env on every rank (its followers' needs are its own)."""
    if builds_env(cfg, coordinator.is_leader()):
        from physicsrl import builders  # torch and TorchRL

        return builders.make_env(cfg, coordinator)
    return make_task(cfg, coordinator)


def builds_env(cfg: Mapping | Any, leader: bool) -> bool:
    """Whether :func:`make_env_for_rank` builds the whole env on a rank that leads its
    coordinator (``leader``) or not: on the leader, and on every rank for ``env.factory``."""
    return leader or bool(plain(cfg)["env"].get("factory"))


def parts(cfg: dict) -> tuple:
    """(observation, reward, task class, task config) of a plain ``cfg``; ValueError naming a
    missing group, a bad setting (the seed too) or an observation of a variable the task does
    not simulate."""
    for group in ("env", "observation", "reward"):
        if group not in cfg:
            raise ValueError(
                f"{group} is missing from the config (groups: env, observation, reward)"
            )
    if cfg.get("seed") is not None:
        integer("seed", cfg["seed"], 0)
    observation = build(*OBSERVATIONS.lookup(cfg["observation"]), "observation")
    reward = build(*REWARDS.lookup(cfg["reward"]), "reward")
    task_class, settings = TASKS.lookup(cfg["env"])
    if observation.variable not in task_class.variables:
        raise ValueError(
            f"observation.variable {observation.variable!r} does not fit the {task_class.name} "
            f"task: it simulates {', '.join(task_class.variables)}"
        )
    return observation, reward, task_class, build(task_class.Config, settings, "env")


def check_memory(cfg: dict, task_config, coordinator: Coordinator) -> None:
    """ValueError naming the setting (``env.mesh.cells``, ``env.replicas``) whose simulator
    would need more than ``cfg["max_memory_gb"]`` (default: ``physicsrl-train``'s) per rank of
    ``coordinator``, before anything is built."""
    ranks = coordinator.comm.size
    needs = simulator_needs(task_config, ranks, f"its coordinator's {ranks} rank(s)")
    check_needs(needs, cfg.get("max_memory_gb", train_default("max_memory_gb")))


def simulator_needs(task_config, ranks: int, over: str) -> dict[str, tuple[float, str]]:
    """The memory per rank of the simulator of a task config on a square mesh, its cells
    shared by ``ranks`` ranks (``over``: the setting or communicator that says so), and of its
    torch replicas (which run on one rank each): setting -> (bytes, how), for
    :func:`~physicsrl.config.check_needs`."""
    mesh = getattr(task_config, "mesh", None)
    if not isinstance(mesh, SquareMesh):
        return {}
    needs = {
        f"env.mesh.cells={mesh.cells}": (
            mesh.cells**2 * MESH_BYTES_PER_CELL / ranks,
            f"{MESH_BYTES_PER_CELL} bytes per cell, over {over}, per rank",
        )
    }
    if getattr(getattr(task_config, "model", None), "backend", None) == "torch":
        replicas = task_config.replicas
        needs[f"env.replicas={replicas}"] = (
            replicas * (mesh.cells + 1) ** 2 * STATE_BYTES_PER_DOF,
            f"{STATE_BYTES_PER_DOF} bytes per replica and dof",
        )
    return needs
