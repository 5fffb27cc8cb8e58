"""A Gymnasium view of a :class:`~physicsrl.envs.env.PhysicsEnv` (either task), e.g. for
Stable-Baselines3.

Observation space ``Box(-inf, inf, (size,), float32)``, action space ``Discrete(n_actions)``;
``info`` holds ``step``, ``diverged`` and the task's flags. ``reset(seed=s)`` reseeds the
episode randomness. Use it on the leader inside ``with coordinator:``, like the TorchRL env.
"""

from __future__ import annotations

import gymnasium
import numpy as np
import torch
from tensordict import TensorDict

from physicsrl.envs.env import PhysicsEnv


class GymnasiumView(gymnasium.Env):
    """``gymnasium.Env`` adapter of ``env`` (see the module docstring)."""

    metadata = {"render_modes": []}

    def __init__(self, env: PhysicsEnv):
        self.env = env
        size = env.task.observation.size
        self.observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (size,), np.float32)
        self.action_space = gymnasium.spaces.Discrete(env.task.n_actions)

    def _unpack(self, td: TensorDict) -> tuple[np.ndarray, dict]:
        info = {key: td[key].item() for key in ("step", "diverged", *self.env.task.flags)}
        return td["observation"].numpy().astype(np.float32), info

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self.env.set_seed(seed)
        return self._unpack(self.env.reset())

    def step(self, action):
        td = TensorDict({"action": torch.tensor(int(action))}, batch_size=[])
        result = self.env.step(td)["next"]
        observation, info = self._unpack(result)
        return (
            observation,
            float(result["reward"].item()),
            bool(result["terminated"].item()),
            bool(result["truncated"].item()),
            info,
        )
