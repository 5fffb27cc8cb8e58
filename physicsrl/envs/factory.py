"""``make_env(cfg, coordinator)``: the environment a config describes (stable entry point).

``cfg`` (a ``DictConfig`` or plain mapping) has the groups

- ``env``: ``name`` (a task in :data:`~physicsrl.envs.task.TASKS`: ``heat``, ``atp``) and that
  task's settings (``conf/env/heat.yaml``, ``conf/env/ms.yaml``);
- ``observation``: ``name`` (``quadrants``, ``catheter``) and its settings;
- ``reward``: ``name`` (``heat_stop``, ``atp``) and its settings;
- ``seed`` (optional, default None): the seed of the episode randomness.

Call it on every rank, in the same order relative to other coordinated objects; then only the
leader calls ``reset``/``step``, inside ``with coordinator:``. Bad settings raise ValueError
naming the key (``env.dt must be ...``). With ``env.model.backend=torch`` (the ATP task) the env
is :class:`~physicsrl.envs.batched.BatchedATPEnv`: ``env.replicas`` copies of the task on this
rank alone (a group of one rank).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from torchrl.envs import EnvBase

from physicsrl.checks import build, plain
from physicsrl.coordinated import Coordinator
from physicsrl.envs.env import PhysicsEnv
from physicsrl.envs.observations import OBSERVATIONS
from physicsrl.envs.rewards import REWARDS
from physicsrl.envs.task import TASKS
from physicsrl.launch import check_backend


def make_env(cfg: Mapping | Any, coordinator: Coordinator) -> EnvBase:
    """Build task (on this rank), observation and reward from ``cfg``; see the module docstring."""
    cfg = plain(cfg)
    for group in ("env", "observation", "reward"):
        if group not in cfg:
            raise ValueError(
                f"{group} is missing from the config (groups: env, observation, reward)"
            )
    observation_class, settings = OBSERVATIONS.lookup(cfg["observation"])
    observation = build(observation_class, settings, "observation")
    reward_class, settings = REWARDS.lookup(cfg["reward"])
    reward = build(reward_class, settings, "reward")
    task_class, settings = TASKS.lookup(cfg["env"])
    config = build(task_class.Config, settings, "env")
    if getattr(getattr(config, "model", None), "backend", None) == "torch":
        from physicsrl.envs.batched import BatchedATPEnv  # torch's time loop: imported on use

        check_backend("torch", coordinator.comm.size)
        return BatchedATPEnv(config, observation, reward, seed=cfg.get("seed"))
    task = task_class(coordinator, config, observation)
    return PhysicsEnv(task, reward, seed=cfg.get("seed"))
