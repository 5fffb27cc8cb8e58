"""Independent environments as the members of one TorchRL env of ``batch_size=[N]``.

Two envs are such batches: :class:`~physicsrl.envs.groups.GroupedEnv` (N simulator groups of
MPI ranks) and :class:`~physicsrl.envs.batched.BatchedATPEnv` (N replicas on one device). A
batch seeded with ``seed`` seeds member i with :func:`member_seed` ``(seed, i)``, and each member
draws its episodes from its own generator, so member i's episodes depend only on (seed, i, its
episode count): not on N, and not on how the batch is built. Member i of N groups and replica i
of N replicas run the same episodes, and member 0 of a batch seeded with ``seed`` runs those of
the plain env seeded with ``seed``.

Members are seeded, reset and stepped alone or together (:meth:`Members.seed_each`,
:meth:`~Members.reset_some`, :meth:`~Members.step_some`, values as numpy arrays per member);
TorchRL's ``reset`` (with its ``"_reset"`` mask) and ``step`` go through them, so the
``Collector`` and ``step_and_maybe_reset`` work unchanged. :func:`spread_episodes` runs
evaluation episodes (a policy and a seed each) on the members as they come free.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase

from physicsrl.checks import integer
from physicsrl.config import SEED_STRIDE

__all__ = ["Members", "OneMember", "as_members", "member_seed", "spread_episodes"]


def member_seed(seed: int | None, index: int) -> int | None:
    """The seed of member ``index`` of a batch seeded with ``seed`` (an integer >= 0, else
    ValueError naming it; None: unseeded)."""
    return None if seed is None else integer("seed", seed, 0) + index * SEED_STRIDE


class Members(EnvBase):
    """Base class of a batch of independent environments (see the module docstring).

    Subclasses set the specs (a leading dimension N) and implement :meth:`seed_each`,
    :meth:`reset_some`, :meth:`step_some`, :meth:`rng_state` and :meth:`set_rng_state`, and
    name their task (:attr:`task`: its hooks give the baselines, action counts and scores).
    """

    def __init__(self, n: int, device="cpu"):
        super().__init__(device=device, batch_size=[n])
        self._last: list[dict | None] = [None] * n  # each member's latest values

    @property
    def task(self):
        """The task behind the members (a :class:`~physicsrl.envs.task.Task` or its class)."""
        raise NotImplementedError

    def seed_each(self, seeds: Sequence[int | None], indices: Sequence[int] | None = None):
        """Seed member ``indices[k]`` (default: all) with ``seeds[k]``."""
        raise NotImplementedError

    def reset_some(self, indices: Sequence[int]) -> dict[int, dict]:
        """Start a new episode on members ``indices``; their first values (key -> numpy array,
        shaped as one member's)."""
        raise NotImplementedError

    def step_some(self, actions: dict[int, int]) -> dict[int, dict]:
        """Step members ``actions.keys()`` with their actions; their next values (with
        ``reward`` and the done flags)."""
        raise NotImplementedError

    def rng_state(self) -> list[dict]:
        """The episode generators' states, one per member (checkpoints save them)."""
        raise NotImplementedError

    def set_rng_state(self, states: Sequence[dict]) -> None:
        raise NotImplementedError

    # TorchRL ------------------------------------------------------------------------------
    def _set_seed(self, seed: int | None) -> None:
        self.seed_each([member_seed(seed, i) for i in range(self.batch_size[0])])

    def _batch(self, rows: dict[int, dict]) -> TensorDict:
        """Stack per-member values into one tensordict of batch size [N]; members absent from
        ``rows`` get their latest values (TorchRL's partial-reset update masks them out). No
        rows: a reset that names no member, the latest values but the reward."""
        self._last = [rows.get(i, last) for i, last in enumerate(self._last)]
        keys = next(iter(rows.values())).keys() if rows else self._last[0].keys() - {"reward"}
        return TensorDict(
            {key: torch.from_numpy(np.stack([row[key] for row in self._last])) for key in keys},
            self.batch_size,
        )

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDict:
        n = self.batch_size[0]
        mask = None if tensordict is None else tensordict.get("_reset", None)
        indices = range(n) if mask is None else mask.reshape(n).nonzero().flatten().tolist()
        return self._batch(self.reset_some(list(indices)))

    def _step(self, tensordict: TensorDictBase) -> TensorDict:
        actions = tensordict["action"].reshape(self.batch_size[0]).tolist()
        return self._batch(self.step_some(dict(enumerate(actions))))


def numpy_leaves(td: TensorDictBase) -> dict:
    """The leaves of an unbatched tensordict as numpy arrays (cheap to pickle)."""
    return {key: value.numpy() for key, value in td.items(True, True)}


class OneMember:
    """A plain environment seen as a batch of one member (index 0): the interface of
    :class:`Members` (seeding, resets, steps and generator states by member)."""

    def __init__(self, env: EnvBase):
        self.env = env
        self.state: TensorDictBase | None = None  # the env's current tensordict

    def seed_each(self, seeds, indices=(0,)):
        self.env.set_seed(seeds[0])

    def reset_some(self, indices) -> dict[int, dict]:
        if 0 not in indices:
            return {}
        self.state = self.env.reset()
        return {0: numpy_leaves(self.state)}

    def step_some(self, actions: dict[int, int]) -> dict[int, dict]:
        self.state["action"] = torch.as_tensor(actions[0])
        self.state = self.env.step(self.state)["next"]
        return {0: numpy_leaves(self.state)}

    def rng_state(self) -> list[dict]:
        return [self.env.rng.bit_generator.state]

    def set_rng_state(self, states) -> None:
        self.env.rng.bit_generator.state = states[0]


def as_members(env: EnvBase) -> Members | OneMember:
    """``env`` itself if it is a batch of members, else ``env`` as a batch of one."""
    return env if isinstance(env, Members) else OneMember(env)


def _tensordict(leaves: dict) -> TensorDict:
    return TensorDict({key: torch.from_numpy(value) for key, value in leaves.items()}, [])


def spread_episodes(
    env: Members, jobs: Sequence[tuple[Callable, int]], max_steps: int
) -> list[TensorDict]:
    """One episode per job ``(policy, seed)``, spread over the members: each member takes the
    next job as soon as its episode ends (K jobs on N members take about K / N episode times;
    several policies can share the batch). Each episode is the unbatched rollout its member
    would produce alone (a stack of at most ``max_steps`` steps with ``"next"``), returned in
    the order of ``jobs``."""
    queue = list(enumerate(jobs))[::-1]  # popped from the end: in order
    episodes: list[TensorDict | None] = [None] * len(jobs)
    running: dict[int, tuple[int, Callable, list[TensorDict]]] = {}  # member -> job, its steps
    current: dict[int, TensorDict] = {}  # member -> the tensordict its policy reads next

    def start(members: Sequence[int]) -> None:
        taken = [(i, queue.pop()) for i in members if queue]  # until the queue is empty
        if taken:
            env.seed_each([seed for _, (_, (_, seed)) in taken], [i for i, _ in taken])
            starts = env.reset_some([i for i, _ in taken])
            for i, (k, (policy, _)) in taken:
                running[i], current[i] = (k, policy, []), _tensordict(starts[i])

    start(range(env.batch_size[0]))
    while running:
        actions = {i: int(running[i][1](td.clone())["action"]) for i, td in current.items()}
        ended = []
        for i, leaves in env.step_some(actions).items():
            k, _, steps = running[i]
            following = _tensordict(leaves)
            step = current[i].clone()
            step["action"] = torch.as_tensor(actions[i])
            step["next"] = following
            steps.append(step)
            if bool(following["done"]) or len(steps) >= max_steps:
                episodes[k] = torch.stack(steps)
                ended.append(i)
                del running[i], current[i]
            else:
                current[i] = following.exclude("reward")
        start(ended)
    return episodes
