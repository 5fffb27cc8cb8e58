"""Rewards: small frozen dataclasses (fields = the YAML settings of ``conf/reward/<name>.yaml``)
registered in :data:`REWARDS`, computed on the leader from the *events* a task reports for each
step (a dict of plain numbers and flags). Each declares the events it reads, so a reward that
does not fit the task is refused when the environment is built. To add one: subclass
:class:`Reward`, register it, implement ``__call__``, add the YAML.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import ClassVar

from physicsrl.checks import number
from physicsrl.envs.registry import Registry

REWARDS = Registry("reward")


class Reward:
    """Base class: ``reward(events) -> float``."""

    name: str
    events: ClassVar[frozenset[str]] = frozenset()

    def __call__(self, events: Mapping) -> float:
        raise NotImplementedError


@REWARDS.register("heat_stop")
@dataclass(frozen=True)
class HeatStop(Reward):
    """The heat task (report section 4.2.1): ``-step_cost`` for each advance; when the episode
    ends (stop, or the step limit) also ``terminal_weight`` x the integral of u over the domain.

    Events: ``advanced`` (the step advanced time), ``ended``, ``integral``.
    """

    events: ClassVar[frozenset[str]] = frozenset({"advanced", "ended", "integral"})
    step_cost: float = 0.1
    terminal_weight: float = 1.0

    def __post_init__(self):
        number("step_cost", self.step_cost)
        number("terminal_weight", self.terminal_weight)

    def __call__(self, events: Mapping) -> float:
        reward = -self.step_cost if events["advanced"] else 0.0
        return reward + (self.terminal_weight * events["integral"] if events["ended"] else 0.0)


@REWARDS.register("atp")
@dataclass(frozen=True)
class ATPReward(Reward):
    """Anti-tachycardia pacing (report section 4.3.4): ``-shock_cost`` per shock; on success
    ``success_reward - step_cost x steps`` (decisions plus extra waits taken); when the episode
    ends without success, ``failure_reward``.

    Events: ``shock``, ``success``, ``failure``, ``steps``.
    """

    events: ClassVar[frozenset[str]] = frozenset({"shock", "success", "failure", "steps"})
    shock_cost: float = 10.0
    success_reward: float = 500.0
    step_cost: float = 1.0
    failure_reward: float = 0.0

    def __post_init__(self):
        for name in ("shock_cost", "success_reward", "step_cost", "failure_reward"):
            number(name, getattr(self, name))

    def __call__(self, events: Mapping) -> float:
        reward = -self.shock_cost if events["shock"] else 0.0
        if events["success"]:
            reward += self.success_reward - self.step_cost * events["steps"]
        elif events["failure"]:
            reward += self.failure_reward
        return reward
