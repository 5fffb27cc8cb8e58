"""The leader-side TorchRL environment around a :class:`~physicsrl.envs.task.Task`.

Keys (all unbatched): ``action`` (int64 scalar, ``Categorical(task.n_actions)``);
``observation`` (float32, (size,)); ``step`` (int64, (1,): decisions taken so far, so that
baselines can be stateless); ``diverged`` (bool, (1,): the simulation stopped being finite in
this step; the episode then ends as truncated and training can go on); the task's ``flags``
(bool, (1,), e.g. ``success``); ``reward`` (float32, (1,)); ``done``, ``terminated``,
``truncated`` (bool, (1,)).

Only the leader calls ``reset``/``step``, inside ``with coordinator:``; each is one parallel
call to the task. Episode randomness comes from a ``numpy.random.Generator`` seeded by
``set_seed`` (or the constructor's seed) on the leader.
"""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from physicsrl.checks import integer
from physicsrl.envs.rewards import Reward
from physicsrl.envs.task import ResetDiverged, Task


class PhysicsEnv(EnvBase):
    """TorchRL environment: ``task`` (simulator side, on every rank) + ``reward`` (leader).

    Parameters
    ----------
    task:
        The task, constructed on every rank.
    reward:
        Maps a step's events to a number; must read only events the task reports.
    seed:
        Seed of the episode randomness (None: from the OS).
    max_reset_attempts:
        Draws tried per reset before giving up (:class:`~physicsrl.envs.task.ResetDiverged`)
        when states keep coming out non-finite.
    """

    def __init__(
        self, task: Task, reward: Reward, seed: int | None = None, max_reset_attempts: int = 10
    ):
        missing = reward.events - task.events
        if missing:
            raise ValueError(
                f"reward.name {reward.name!r} reads events {sorted(missing)} that env "
                f"{task.name!r} does not report (it reports {sorted(task.events)})"
            )
        super().__init__(device="cpu", batch_size=[])
        self.task, self.reward_fn = task, reward
        self.max_reset_attempts = max_reset_attempts
        flag = Categorical(2, shape=(1,), dtype=torch.bool)
        self.observation_spec = Composite(
            observation=Unbounded(shape=(task.observation.size,), dtype=torch.float32),
            step=Bounded(0, task.max_steps, shape=(1,), dtype=torch.int64),
            diverged=flag.clone(),
            **{name: flag.clone() for name in task.flags},
        )
        self.action_spec = Categorical(task.n_actions)
        self.reward_spec = Unbounded(shape=(1,), dtype=torch.float32)
        self.done_spec = Composite(
            done=flag.clone(), terminated=flag.clone(), truncated=flag.clone()
        )
        self._set_seed(seed)

    def _set_seed(self, seed: int | None) -> None:
        self.rng = np.random.default_rng(None if seed is None else integer("seed", seed, 0))

    def rng_state(self) -> dict:
        """The state of the episode generator (checkpoints save it for an exact resume)."""
        return self.rng.bit_generator.state

    def set_rng_state(self, state: dict) -> None:
        self.rng.bit_generator.state = state

    def _observation(
        self, observation: np.ndarray, step: int, diverged: bool = False, flags=None
    ) -> dict:
        result = {
            "observation": torch.as_tensor(observation, dtype=torch.float32),
            "step": torch.tensor([step], dtype=torch.int64),
            "diverged": torch.tensor([diverged]),
        }
        for name in self.task.flags:
            result[name] = torch.tensor([bool((flags or {}).get(name, False))])
        return result

    def _reset(self, tensordict=None, **kwargs) -> TensorDict:
        for _ in range(self.max_reset_attempts):
            observation = self.task.reset(*self.task.draw(self.rng))
            if observation is not None:
                false = torch.zeros(1, dtype=torch.bool)
                return TensorDict(
                    {
                        **self._observation(observation, 0),
                        "done": false,
                        "terminated": false.clone(),
                        "truncated": false.clone(),
                    },
                    batch_size=[],
                )
        raise ResetDiverged(self.max_reset_attempts)

    def _step(self, tensordict: TensorDict) -> TensorDict:
        action = tensordict["action"]
        if not self.action_spec.is_in(action):  # here, not on every rank inside the task
            raise ValueError(
                f"action must be an integer in 0..{self.task.n_actions - 1}, got {action.tolist()}"
            )
        t = self.task.step(int(action))
        return TensorDict(
            {
                **self._observation(t.observation, t.step, t.diverged, t.flags),
                "reward": torch.tensor([self.reward_fn(t.events)], dtype=torch.float32),
                "done": torch.tensor([t.terminated or t.truncated]),
                "terminated": torch.tensor([t.terminated]),
                "truncated": torch.tensor([t.truncated]),
            },
            batch_size=[],
        )
