"""Your own task in about 100 lines: a thermostat on the heat equation.

A plate obeys du/dt = lap(u) + f with u = 0 on the boundary. Every 0.1 time units the agent
switches a heater off (f = 0) or on (f = heat); it is paid -|mean temperature - target| per
step. The simulator lives on every rank; the leader trains DQN on it:

    python examples/thermostat.py                  # 1 rank
    mpiexec -n 2 python examples/thermostat.py     # the same training, the solve on 2 ranks

The task and its reward are registered under the names of their YAML files
(``examples/conf/env/thermostat.yaml``, ``examples/conf/reward/keep_target.yaml``, which name
this file as their ``module``), so the command line trains it too, from the repository root:

    physicsrl-train hydra.searchpath=[file://examples/conf] +experiment=thermostat
"""

import sys
from dataclasses import dataclass

import numpy as np
import torch

from physicsrl.builders import make_q_network
from physicsrl.checks import integer, positive
from physicsrl.config import OptimConfig, TrainConfig, held_out_seeds
from physicsrl.coordinated import Coordinator, parallel
from physicsrl.dojo import Dojo
from physicsrl.envs import (
    REWARDS,
    TASKS,
    PhysicsEnv,
    Quadrants,
    Reward,
    SquareMesh,
    Task,
    Transition,
)
from physicsrl.envs.baselines import Constant
from physicsrl.evaluation import compare
from physicsrl.fem import HeatEnvironment, heat
from physicsrl.fem.integrals import WeightedIntegrals, form_rows
from physicsrl.fem.resolution import report


@dataclass(frozen=True)
class Thermostat:
    """The settings of ``env=thermostat`` (the keys of its YAML), checked when built."""

    mesh: SquareMesh = SquareMesh(cells=16, extent=1.0)
    dt: float = 0.005
    interval: float = 0.1  # time between decisions
    heat: float = 40.0  # f when the heater is on
    max_steps: int = 20

    def __post_init__(self):
        for name in ("dt", "interval", "heat"):
            positive(name, getattr(self, name))
        integer("max_steps", self.max_steps, 1)


@TASKS.register("thermostat")
class ThermostatTask(Task):
    """Simulator side: one parallel call per reset and per step, on every rank."""

    Config, n_actions, events = Thermostat, 2, frozenset({"mean"})
    action_counts = {"heating": 1}  # reported per evaluated episode

    def baselines(self, env, seeds, seed):
        return {"heater off": Constant(0), "heater on": Constant(1)}

    def __init__(self, coordinator: Coordinator, config: Thermostat, observation: Quadrants):
        self.config, self.max_steps, self.observation = config, config.max_steps, observation
        domain = config.mesh.create(coordinator.comm)
        self.simulator = HeatEnvironment(coordinator, domain, dt=config.dt, u_D=0.0)
        # How well mesh and dt resolve the start's decay, at the first ten decisions
        report(
            heat.resolution(self.simulator, config.mesh.extent, config.interval * np.arange(1, 11))
        )
        self.register_coordinator(coordinator)
        V = self.simulator.V
        self.integrals = WeightedIntegrals(V, np.vstack([form_rows(V, [1.0]), observation.rows(V)]))
        self.area = (2 * config.mesh.extent) ** 2

    def draw(self, rng: np.random.Generator) -> tuple[float]:
        return (float(rng.uniform(0.0, 2.0)),)  # the starting temperature, drawn on the leader

    @parallel
    def reset(self, start: float) -> np.ndarray:
        self.simulator.reset()
        self.simulator.set_initial_condition(start)
        self.steps = 0
        return self.integrals(self.simulator.u_n())[1:]

    @parallel
    def step(self, action: int) -> Transition:
        self.simulator.set_source(self.config.heat * action)
        self.simulator.advance_time(self.config.interval)
        self.steps += 1
        values = self.integrals(self.simulator.u_n())
        mean = {"mean": float(values[0]) / self.area}
        return Transition(values[1:], mean, self.steps, terminated=self.steps >= self.max_steps)


@REWARDS.register("keep_target")
@dataclass(frozen=True)
class KeepTarget(Reward):
    events = frozenset({"mean"})
    target: float = 1.0

    def __call__(self, events) -> float:
        return -abs(events["mean"] - self.target)


def main(iterations: int) -> dict[str, float]:
    coordinator = Coordinator()
    task = ThermostatTask(coordinator, Thermostat(), Quadrants())
    env = PhysicsEnv(task, KeepTarget(), seed=0)
    with coordinator:
        if coordinator.is_leader():
            torch.manual_seed(0)
            config = TrainConfig(iterations=iterations, optim=OptimConfig(learning_starts=100))
            dojo = Dojo(make_q_network(env), env, config)
            dojo.train()
            seeds = held_out_seeds(5)
            policies = {"greedy DQN": dojo.q_network, **task.baselines(env, seeds, 0)}
            _, means = compare(env, policies, seeds, task.action_counts)
            returns = {row["policy"]: row["return"] for row in means}
            print(", ".join(f"{name}: {value:.2f}" for name, value in returns.items()))
            return returns


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 60)
