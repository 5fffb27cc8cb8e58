r"""The heat task (report section 4.2.1): when should the agent stop a cooling/heating plate?

:math:`\partial_t u = \nabla^2 u + f` on the square ``mesh`` (default [-2, 2]^2, 50 x 50 x 2
P1 triangles), :math:`u = u_D` on the boundary, implicit Euler with ``dt``. Each reset draws a
level uniformly from the integers ``levels`` and starts from the constant :math:`u_0` = level.
Actions: 0 = stop now, 1 = advance ``advance_time`` time units. The episode ends (terminated)
on stop or after ``max_steps`` steps. Events for the reward: ``advanced``, ``ended`` and
``integral`` (of u over the domain, after the step).

The dynamics are deterministic given the level, so :func:`exact_optimum` finds the optimal
expected return by trying every stopping time for every level.

When built, the task prints how well its mesh and ``dt`` resolve the solution at its first ten
decision times (:func:`physicsrl.fem.heat.resolution`: the part of u that the level sets,
against the exact series; later the transient has decayed) and warns above 5%.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from physicsrl.checks import integer, interval, number, positive
from physicsrl.coordinated import Coordinator, parallel
from physicsrl.envs.observations import Observation
from physicsrl.envs.task import TASKS, SquareMesh, Task, Transition
from physicsrl.fem import HeatEnvironment, SimulationDiverged, heat
from physicsrl.fem.integrals import WeightedIntegrals, form_rows
from physicsrl.fem.resolution import report

STOP, ADVANCE = 0, 1
# The exact optimum (the baselines) simulates every stopping time of every level: levels x
# max_steps advances, about a minute at this bound on the default mesh.
MAX_STEPS = 1000


@dataclass(frozen=True)
class HeatConfig:
    """Settings of ``conf/env/heat.yaml`` (time in the PDE's units; u dimensionless)."""

    mesh: SquareMesh = field(default_factory=SquareMesh)
    dt: float = 0.01
    boundary_value: float = 1.0
    source: float = 0.0
    levels: tuple[int, int] = (-5, 5)
    advance_time: float = 0.1
    max_steps: int = 10

    def __post_init__(self):
        positive("dt", self.dt)
        number("boundary_value", self.boundary_value)
        number("source", self.source)
        low, high = interval("levels", self.levels)
        if low != int(low) or high != int(high):
            raise ValueError(f"levels must be a pair of integers, got {list(self.levels)!r}")
        object.__setattr__(self, "levels", (int(low), int(high)))
        steps = positive("advance_time", self.advance_time) / self.dt
        if abs(steps - round(steps)) > 1e-9 * steps:
            raise ValueError(
                f"advance_time must be a whole number of dt = {self.dt}, got {self.advance_time!r}"
            )
        if integer("max_steps", self.max_steps, 1) > MAX_STEPS:
            raise ValueError(
                f"max_steps must be <= {MAX_STEPS} (the exact optimum simulates every stopping "
                f"time), got {self.max_steps!r}"
            )


@TASKS.register("heat")
class HeatTask(Task):
    """Simulator side of the heat task (see the module docstring). Construct on every rank."""

    Config: ClassVar[type] = HeatConfig
    n_actions: ClassVar[int] = 2
    events: ClassVar[frozenset[str]] = frozenset({"advanced", "ended", "integral"})
    action_counts = {"advances": 1}

    def baselines(self, env, seeds, seed):
        """Stop at once, never stop, and the exact optimum (:func:`exact_optimum`)."""
        from physicsrl.envs.baselines import Constant, HeatOptimal  # torch: imported on use

        return {
            "stop at once": Constant(0),
            "never stop": Constant(1),
            "exact optimum": HeatOptimal(exact_optimum(env)),
        }

    @staticmethod
    def scores(returns):
        """The greedy return as a share of the optimum: raw, and of the gap between the best
        trivial policy and the optimum."""
        if "exact optimum" not in returns:
            return []
        greedy, optimum = returns["greedy DQN"], returns["exact optimum"]
        trivial = max(returns["stop at once"], returns["never stop"])
        lines = []
        if optimum > 0:
            lines.append(f"greedy / optimum: {100 * greedy / optimum:.1f}% of the optimal return")
        if optimum > trivial:
            share = 100 * (greedy - trivial) / (optimum - trivial)
            gap = "(greedy - best trivial) / (optimum - best trivial)"
            lines.append(f"{gap}: {share:.1f}% of the gap closed")
        return lines

    def __init__(self, coordinator: Coordinator, config: HeatConfig, observation: Observation):
        self.config, self.observation = config, observation
        self.max_steps = config.max_steps
        self.simulator = HeatEnvironment(
            coordinator,
            config.mesh.create(coordinator.comm),
            dt=config.dt,
            u0=0.0,
            u_D=config.boundary_value,
            f=config.source,
        )
        decisions = config.advance_time * np.arange(1, min(config.max_steps, 10) + 1)
        report(heat.resolution(self.simulator, config.mesh.extent, decisions))
        self.register_coordinator(coordinator)
        V = self.simulator.V
        # Row 0: the integral over the domain; then the observation's rows.
        self.integrals = WeightedIntegrals(V, np.vstack([form_rows(V, [1.0]), observation.rows(V)]))
        self.steps = 0

    def draw(self, rng: np.random.Generator) -> tuple[int]:
        low, high = self.config.levels
        return (int(rng.integers(low, high + 1)),)

    @parallel
    def reset(self, level: int) -> np.ndarray:
        self.simulator.reset()
        self.simulator.set_initial_condition(float(level))
        self.steps = 0
        return self.integrals_now()[1:]

    @parallel
    def step(self, action: int) -> Transition:
        if action not in (STOP, ADVANCE):
            raise ValueError(f"action must be 0 (stop) or 1 (advance), got {action!r}")
        advanced = action == ADVANCE
        if advanced:
            self.steps += 1
            try:
                self.simulator.advance_time(self.config.advance_time)
            except SimulationDiverged:
                events = {"advanced": False, "ended": False, "integral": 0.0}
                observation = np.zeros(self.observation.size)
                return Transition(observation, events, self.steps, truncated=True, diverged=True)
        values = self.integrals_now()
        ended = not advanced or self.steps >= self.max_steps
        events = {"advanced": advanced, "ended": ended, "integral": float(values[0])}
        return Transition(values[1:], events, self.steps, terminated=ended)

    @parallel
    def trajectory(self, level: int) -> tuple[np.ndarray, np.ndarray]:
        """Observations (max_steps + 1, size) and domain integrals (max_steps + 1,) after
        k = 0 .. max_steps advances from ``level`` (leaves the task mid-episode)."""
        observations = [self.reset(level)]
        integrals = [self.integrals_now()[0]]
        for _ in range(self.max_steps):
            t = self.step(ADVANCE)
            observations.append(t.observation)
            integrals.append(t.events["integral"])
        return np.array(observations), np.array(integrals)


@dataclass
class HeatOptimum:
    """The exact solution of the heat task for one environment.

    ``levels`` (L,); ``returns`` (L, max_steps + 1): the return of advancing k times, then
    stopping (k = max_steps: never stopping); ``best_stop`` (L,): the optimal k;
    ``best_return`` (L,); ``mean``: the optimal expected return (levels are uniform);
    ``observations`` (L, max_steps + 1, size): what the agent sees after k advances.
    """

    levels: np.ndarray
    returns: np.ndarray
    best_stop: np.ndarray
    best_return: np.ndarray
    mean: float
    observations: np.ndarray


def exact_optimum(env) -> HeatOptimum:
    """Try every stopping time for every level of ``env`` (a heat :class:`PhysicsEnv`).

    Leader only, inside ``with coordinator:``; one parallel call per level. The returns use the
    environment's own reward, so they hold for any reward settings.
    """
    task, reward = env.task, env.reward_fn
    low, high = task.config.levels
    levels = np.arange(low, high + 1)
    K = task.max_steps
    returns = np.empty((len(levels), K + 1))
    observations = []
    for i, level in enumerate(levels):
        seen, integral = task.trajectory(int(level))
        observations.append(seen)
        advancing = 0.0
        for k in range(K + 1):
            if k == K:
                returns[i, k] = advancing
                break
            stop = reward({"advanced": False, "ended": True, "integral": integral[k]})
            returns[i, k] = advancing + stop
            advancing += reward(
                {"advanced": True, "ended": k + 1 == K, "integral": integral[k + 1]}
            )
    best = returns.argmax(axis=1)
    best_return = returns[np.arange(len(levels)), best]
    return HeatOptimum(
        levels, returns, best, best_return, float(best_return.mean()), np.array(observations)
    )
