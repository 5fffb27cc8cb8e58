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
from torchrl.envs import EnvBase

from physicsrl.envs.env import PhysicsEnv
from physicsrl.envs.members import Members, as_members, member_seed


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
        td = TensorDict({"action": torch.as_tensor(np.asarray(action))}, batch_size=[])
        result = self.env.step(td)["next"]
        observation, info = self._unpack(result)
        return (
            observation,
            float(result["reward"].item()),
            bool(result["terminated"].item()),
            bool(result["truncated"].item()),
            info,
        )


class GymnasiumVectorView(gymnasium.vector.VectorEnv):
    """``gymnasium.vector.VectorEnv`` adapter of the N environments that
    :func:`~physicsrl.envs.layout.environments` gives the learner's rank: the groups of a
    :class:`~physicsrl.envs.groups.GroupedEnv` (each one environment or a batch of replicas), a
    :class:`~physicsrl.envs.batched.BatchedATPEnv`'s replicas, or one plain env (N = 1).

    Spaces: the single env's, batched (``(N, size)`` observations, ``MultiDiscrete`` actions).
    Autoreset ``SAME_STEP``: an environment whose episode ends restarts within the same
    ``step``; the returned observation is its first one, its last is ``infos["final_obs"][i]``
    and its last infos are in ``infos["final_info"]`` (``infos["_final_obs"]`` and
    ``infos["_final_info"]`` mark which). ``infos`` holds ``step``, ``diverged`` and the
    task's flags as arrays. ``reset(seed=s)`` seeds environment i with
    ``member_seed(s, i)``; ``seed=[s0, s1, ...]`` seeds each.
    """

    metadata = {"render_modes": [], "autoreset_mode": gymnasium.vector.AutoresetMode.SAME_STEP}

    def __init__(self, env: EnvBase):
        self.env = as_members(env)
        self.num_envs = env.batch_size[0] if isinstance(env, Members) else 1
        task = env.task if isinstance(env, Members) else vars(env)["task"]  # or the task's class
        self._info_keys = ("step", "diverged", *task.flags)
        size = env.observation_spec["observation"].shape[-1]
        self.single_observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (size,), np.float32)
        self.single_action_space = gymnasium.spaces.Discrete(task.n_actions)
        batch = gymnasium.vector.utils.batch_space
        self.observation_space = batch(self.single_observation_space, self.num_envs)
        self.action_space = batch(self.single_action_space, self.num_envs)

    def _stack(self, rows: list[dict]) -> tuple[np.ndarray, dict]:
        observations = np.stack([row["observation"] for row in rows]).astype(np.float32)
        infos = {key: np.array([row[key].item() for row in rows]) for key in self._info_keys}
        return observations, infos

    def reset(self, *, seed=None, options: dict | None = None):
        if isinstance(seed, int):
            self.env.seed_each([member_seed(seed, i) for i in range(self.num_envs)])
        elif seed is not None:
            self.env.seed_each(list(seed))
        rows = self.env.reset_some(list(range(self.num_envs)))
        return self._stack([rows[i] for i in range(self.num_envs)])

    def step(self, actions):
        rows = self.env.step_some({i: int(a) for i, a in enumerate(actions)})
        rows = [rows[i] for i in range(self.num_envs)]
        rewards = np.array([row["reward"].item() for row in rows], dtype=np.float64)
        terminated = np.array([bool(row["terminated"].item()) for row in rows])
        truncated = np.array([bool(row["truncated"].item()) for row in rows])
        final, final_infos = self._stack(rows)
        ended = np.flatnonzero(terminated | truncated).tolist()
        for i, first in self.env.reset_some(ended).items():
            rows[i] = first
        observations, infos = self._stack(rows)
        for i in ended:  # laid out as gymnasium's own vector envs do (its _add_info)
            final_info = {key: values[i] for key, values in final_infos.items()}
            infos = self._add_info(infos, {"final_obs": final[i], "final_info": final_info}, i)
        return observations, rewards, terminated, truncated, infos
