"""Reinforcement-learning tasks as TorchRL environments composed from config.

Entry point: :func:`make_env` (``cfg.env``, ``cfg.observation``, ``cfg.reward``, ``cfg.seed``).
Tasks: ``heat`` (:class:`HeatTask`), ``atp`` (:class:`ATPTask`); observations: ``quadrants``,
``catheter``; rewards: ``heat_stop``, ``atp``. See :mod:`physicsrl.envs.task` for the design.
"""

import physicsrl.fem  # noqa: F401 (first: makes MPI and PETSc loadable for dolfinx)
from physicsrl.envs.atp import ATPConfig, ATPTask
from physicsrl.envs.env import PhysicsEnv
from physicsrl.envs.factory import load_config, make_env
from physicsrl.envs.heat import HeatConfig, HeatOptimum, HeatTask, exact_optimum
from physicsrl.envs.observations import OBSERVATIONS, Catheter, Observation, Quadrants
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
