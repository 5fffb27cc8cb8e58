"""Reinforcement-learning tasks as TorchRL environments composed from config.

Entry point: :func:`make_env` (``cfg.env``, ``cfg.observation``, ``cfg.reward``, ``cfg.seed``).
Tasks: ``heat`` (:class:`HeatTask`), ``atp`` (:class:`ATPTask`); observations: ``quadrants``,
``catheter``; rewards: ``heat_stop``, ``atp``. See :mod:`physicsrl.envs.task` for the design.

The tasks, configs and registries import without torch, so that the commands check a task's
settings in about a second; the TorchRL side (:class:`PhysicsEnv`, :func:`make_env`) is
imported on first use.
"""

import importlib

import physicsrl.fem  # noqa: F401 (first: makes MPI and PETSc loadable for dolfinx)
from physicsrl.envs.atp import ATPConfig, ATPTask
from physicsrl.envs.heat import HeatConfig, HeatOptimum, HeatTask, exact_optimum
from physicsrl.envs.observations import OBSERVATIONS, Catheter, Observation, Quadrants
from physicsrl.envs.registry import load_config
from physicsrl.envs.rewards import REWARDS, ATPReward, HeatStop, Reward
from physicsrl.envs.task import TASKS, SquareMesh, Task, Transition

__all__ = [
    "ATPConfig",
    "ATPReward",
    "ATPTask",
    "Catheter",
    "HeatConfig",
    "HeatOptimum",
    "HeatStop",
    "HeatTask",
    "OBSERVATIONS",
    "Observation",
    "PhysicsEnv",
    "Quadrants",
    "REWARDS",
    "Reward",
    "SquareMesh",
    "TASKS",
    "Task",
    "Transition",
    "exact_optimum",
    "load_config",
    "make_env",
]

_TORCH_SIDE = {"PhysicsEnv": "env", "make_env": "factory"}


def __getattr__(name: str):
    if name in _TORCH_SIDE:
        return getattr(importlib.import_module(f"physicsrl.envs.{_TORCH_SIDE[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
