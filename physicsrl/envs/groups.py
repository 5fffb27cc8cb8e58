r"""The N simulator groups of a :class:`~physicsrl.envs.layout.Layout` as one batched TorchRL
env on world rank 0 (:class:`GroupedEnv`), and the other group leaders' side (:func:`serve`);
:func:`~physicsrl.envs.layout.environments` builds them.

On world rank 0 the N environments appear as one TorchRL environment of ``batch_size=[N]``
(``[N B]`` when each group's env is a batch of B members, as the torch backend's replicas
are). Its ``step`` sends the N - 1 remote actions to their group leaders (MPI point-to-point on
a communicator of the group leaders), steps group 0's environment meanwhile, then gathers the
N - 1 remote transitions; ``reset`` restarts only the environments that the ``"_reset"`` mask
names, so TorchRL's ``Collector`` and ``step_and_maybe_reset`` work unchanged. The other group
leaders serve those requests (:func:`serve`).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Sequence

import torch
from mpi4py import MPI
from torchrl import timeit
from torchrl.envs import EnvBase

from physicsrl.coordinated import wait_for
from physicsrl.envs.layout import Layout
from physicsrl.envs.members import Members, OneMember, as_members
from physicsrl.envs.task import ResetDiverged

__all__ = ["GroupedEnv", "serve"]

_REQUEST, _REPLY = 31, 32
_SEED, _RESET, _STEP, _GET_RNG, _SET_RNG, _CLOSE = range(6)


def _run(members: Members | OneMember, command: int, argument):
    """Carry out ``command`` on a group's members (local indices; on its group leader)."""
    if command == _SEED:
        seeds, indices = argument
        return members.seed_each(seeds, indices)
    if command == _RESET:
        return members.reset_some(argument)
    if command == _STEP:
        return members.step_some(argument)
    if command == _GET_RNG:
        return members.rng_state()
    if command == _SET_RNG:
        return members.set_rng_state(argument)
    raise ValueError(f"unknown command {command!r}")


class _Group:
    """One group's environment as seen from world rank 0: local (group 0) or remote."""

    def __init__(self, index: int, members: Members | OneMember | None, leaders: MPI.Comm):
        self.index, self.members, self.leaders = index, members, leaders

    def send(self, command: int, argument=None) -> None:
        if self.members is None:
            self.leaders.send((command, argument), dest=self.index, tag=_REQUEST)

    def result(self, command: int, argument=None):
        """Run ``command`` here (local) or collect the reply to the request sent (remote)."""
        if self.members is None:
            with timeit("groups/wait"):  # the remote group's work, not the learner's own cost
                self.leaders.Probe(source=self.index, tag=_REPLY)
            reply = self.leaders.recv(source=self.index, tag=_REPLY)
            if isinstance(reply, ResetDiverged):  # raised here, as the local group's would be
                raise reply
            return reply
        return _run(self.members, command, argument)


def serve(env: EnvBase, leaders: MPI.Comm, spin_s: float = 0.05, max_sleep_s: float = 0.002):
    """Answer world rank 0's requests for ``env`` (a group leader other than rank 0) until it
    sends close; return the exit status it sends. Between requests the rank polls as a
    coordinator's follower does (:func:`~physicsrl.coordinated.wait_for`: busily for ``spin_s``
    seconds, then sleeping at most ``max_sleep_s`` between polls), so that it leaves the core
    to a learner that trains."""
    members = as_members(env)
    oversubscribed = leaders.Get_size() > len(os.sched_getaffinity(0))
    request = functools.partial(leaders.Iprobe, source=0, tag=_REQUEST)
    while True:
        wait_for(request, spin_s, max_sleep_s, oversubscribed)
        command, argument = leaders.recv(source=0, tag=_REQUEST)
        if command == _CLOSE:
            return int(argument)
        try:
            reply = _run(members, command, argument)
        except ResetDiverged as error:  # the learner's to report (one line), not a fault here
            reply = error
        leaders.send(reply, dest=0, tag=_REPLY)


class GroupedEnv(Members):
    """The environments of the N groups of a :class:`Layout` as one TorchRL env (world rank 0
    only; see the module docstring and :class:`~physicsrl.envs.members.Members`). A group's
    environment is one member, or B members when it is itself a batch (the replicas of
    :class:`~physicsrl.envs.batched.BatchedATPEnv`): ``batch_size=[N B]``, member g B + j being
    member j of group g.

    Keys and specs are those of one member with a leading dimension N B.
    """

    def __init__(self, env: EnvBase, layout: Layout, seed: int | None = None):
        if layout.world.rank != 0:
            raise ValueError("GroupedEnv lives on world rank 0 (the learner)")
        self.per_group = env.batch_size[0] if isinstance(env, Members) else 1
        n = layout.n_envs * self.per_group
        super().__init__(n, device=env.device)
        self.layout = layout
        self.groups = [_Group(0, as_members(env), layout.leaders)] + [
            _Group(g, None, layout.leaders) for g in range(1, layout.n_envs)
        ]
        self.local_env = env
        shape = torch.Size([n])
        for name in ("observation_spec", "action_spec", "reward_spec", "done_spec"):
            one = getattr(env, f"{name}_unbatched")
            setattr(self, name, one.expand(shape + one.shape))
        self._set_seed(seed)

    @property
    def task(self):
        """Group 0's task (None for an env without one): its settings and hooks (baselines,
        scores) are every group's."""
        env = self.local_env
        # not getattr for a plain env: EnvBase.__getattr__ searches on
        return env.task if isinstance(env, Members) else vars(env).get("task")

    @property
    def reward_fn(self):
        return self.local_env.reward_fn

    def _by_group(self, indices: Sequence[int]) -> dict[int, list[tuple[int, int]]]:
        """Group -> [(position in ``indices``, member index within the group)]."""
        groups: dict[int, list[tuple[int, int]]] = {}
        for position, k in enumerate(indices):
            groups.setdefault(k // self.per_group, []).append((position, k % self.per_group))
        return groups

    def _all(self, command: int, arguments: dict[int, object]) -> dict[int, object]:
        """Send ``command`` with ``arguments[g]`` to each group g named, remote ones first, so
        that they work while the local one does; the results by group."""
        for g, argument in arguments.items():
            self.groups[g].send(command, argument)
        results = {g: self.groups[g].result(command, a) for g, a in arguments.items() if g == 0}
        results |= {g: self.groups[g].result(command) for g in arguments if g != 0}
        return results

    def seed_each(self, seeds: Sequence[int | None], indices: Sequence[int] | None = None):
        indices = range(self.batch_size[0]) if indices is None else indices
        groups = self._by_group(indices)
        self._all(
            _SEED, {g: ([seeds[p] for p, _ in m], [j for _, j in m]) for g, m in groups.items()}
        )

    def rng_state(self) -> list[dict]:
        states = self._all(_GET_RNG, dict.fromkeys(range(len(self.groups))))
        return [state for g in range(len(self.groups)) for state in states[g]]

    def set_rng_state(self, states: Sequence[dict]) -> None:
        n, B = self.batch_size[0], self.per_group
        if len(states) != n:
            raise ValueError(f"{len(states)} generator states for {n} environments")
        self._all(_SET_RNG, {g: list(states[g * B : (g + 1) * B]) for g in range(len(self.groups))})

    def reset_some(self, indices: Sequence[int]) -> dict[int, dict]:
        groups = self._by_group(indices)
        results = self._all(_RESET, {g: [j for _, j in m] for g, m in groups.items()})
        return {indices[p]: results[g][j] for g, m in groups.items() for p, j in m}

    def step_some(self, actions: dict[int, int]) -> dict[int, dict]:
        indices = list(actions)
        groups = self._by_group(indices)
        arguments = {g: {j: actions[indices[p]] for p, j in m} for g, m in groups.items()}
        results = self._all(_STEP, arguments)
        return {indices[p]: results[g][j] for g, m in groups.items() for p, j in m}

    def close_groups(self, status: int = 0) -> None:
        """Release the other group leaders (their serve loops return ``status``)."""
        for group in self.groups[1:]:
            group.send(_CLOSE, status)
