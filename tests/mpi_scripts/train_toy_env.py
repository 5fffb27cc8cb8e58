"""A tiny known-optimum task for the training tests: stop on the marked step of a short chain.

Each episode draws a target step ``c`` in [0, length) from the env's generator. The agent sees
``(t / length, c / length)`` and chooses advance (0) or stop (1). Stopping at ``t == c`` pays 1,
stopping elsewhere pays 0, and running off the end pays 0: the optimal return is exactly 1.

The env is :class:`Coordinated`: each step runs a ``@parallel`` method that does an MPI
reduction on every rank, like a distributed simulator, so the env must be built on every rank
in the same order and stepped by the leader inside ``with coordinator``.
"""

from __future__ import annotations

import os

import numpy as np
import torch
from mpi4py import MPI
from tensordict import TensorDict
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from physicsrl.coordinated import Coordinated, parallel


class ToyChainEnv(EnvBase, Coordinated):
    optimum = 1.0

    def __init__(self, coordinator, length: int = 5, seed: int = 0, vanish_at: int = 0):
        super().__init__(device="cpu", batch_size=[])
        self.register_coordinator(coordinator)
        self.length = length
        self.observation_spec = Composite(
            observation=Unbounded(shape=(2,)), success=Unbounded(shape=(1,), dtype=torch.bool)
        )
        self.action_spec = Categorical(2, shape=())
        self.reward_spec = Unbounded(shape=(1,))
        self.rng = np.random.default_rng(seed)
        self.t = 0
        self.c = 0
        self.vanish_at = vanish_at  # > 0: the job's last rank calls os._exit(0) in that call
        self.calls = 0

    @parallel
    def _simulate(self, t: int) -> int:
        """Stand-in for a distributed solve: every rank of the env's group takes part in a
        reduction (its coordinator's communicator, not COMM_WORLD: a job may hold many envs)."""
        self.calls += 1
        if self.calls == self.vanish_at and MPI.COMM_WORLD.rank == MPI.COMM_WORLD.size - 1:
            os._exit(0)  # a rank that vanishes without a word
        return self.coordinator.comm.allreduce(t, op=MPI.MAX)

    def _obs(self):
        return torch.tensor([self.t / self.length, self.c / self.length], dtype=torch.float32)

    def _reset(self, tensordict=None, **kwargs):
        self.t = 0
        self.c = int(self.rng.integers(self.length))
        self._simulate(self.t)
        return TensorDict(
            observation=self._obs(),
            done=torch.zeros(1, dtype=torch.bool),
            terminated=torch.zeros(1, dtype=torch.bool),
            success=torch.zeros(1, dtype=torch.bool),
        )

    def _step(self, tensordict):
        action = int(tensordict["action"])
        reward = 0.0
        if action == 1:
            reward = 1.0 if self.t == self.c else 0.0
            done = True
        else:
            self.t = self._simulate(self.t + 1)
            done = self.t >= self.length
        return TensorDict(
            observation=self._obs(),
            reward=torch.tensor([reward]),
            done=torch.tensor([done]),
            terminated=torch.tensor([done]),
            success=torch.tensor([action == 1 and reward > 0]),
        )

    def _set_seed(self, seed):
        self.rng = np.random.default_rng(seed)

    def rng_state(self):
        return self.rng.bit_generator.state

    def set_rng_state(self, state):
        self.rng.bit_generator.state = state


def make_env(cfg, coordinator):
    """Factory for ``env.factory`` (the Hydra training runner)."""
    length, vanish_at = int(cfg.env.get("length", 5)), int(cfg.env.get("vanish_at", 0))
    return ToyChainEnv(coordinator, length, int(cfg.seed), vanish_at)
