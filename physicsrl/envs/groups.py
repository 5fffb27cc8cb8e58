r"""Many environments in one MPI job: N simulator groups of P ranks, one batched env.

Layout: a job of W ranks splits into N = W / P *groups* of P consecutive ranks (group g holds
world ranks gP .. gP + P - 1). Each group builds its own mesh, simulator and task on its own
communicator with its own :class:`~physicsrl.coordinated.Coordinator`, exactly as a single
environment does; the first rank of a group leads it. World rank 0 runs the learner and also
leads group 0.

On world rank 0 the N environments appear as one TorchRL environment of ``batch_size=[N]``
(:class:`GroupedEnv`). Its ``step`` sends the N - 1 remote actions to their group leaders
(MPI point-to-point on a communicator of the group leaders), steps group 0's environment
meanwhile, then gathers the N - 1 remote transitions; ``reset`` restarts only the
environments that the ``"_reset"`` mask names, so TorchRL's ``Collector`` and
``step_and_maybe_reset`` work unchanged. The other group leaders serve those requests
(:func:`serve`); the other ranks serve their group leader's parallel calls.

Seeds: environment i is seeded with :func:`~physicsrl.envs.members.member_seed` ``(seed, i)``,
so its episodes depend only on (seed, i, its episode count), never on P or W; environment 0 is
seeded with ``seed`` itself, so N = 1 is the plain environment.

Use it through :func:`environments`, on every rank::

    with environments(lambda coordinator: make_env(cfg, coordinator), ranks_per_env=1) as env:
        if env is not None:  # world rank 0: the learner
            ...              # train on env (batch_size [N], or the plain env when N = 1)

Failures: an exception on world rank 0 inside the block tells every group to stop with
status 1 (the command-line wrapper then aborts the job); an exception in a simulator of any
group ends the whole job through its coordinator (``MPI.Abort``).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

import torch
from mpi4py import MPI
from tensordict import TensorDictBase
from torchrl import timeit
from torchrl.envs import EnvBase

from physicsrl.coordinated import Coordinator, wait_for
from physicsrl.envs.members import Members, numpy_leaves
from physicsrl.launch import check_layout

__all__ = ["GroupedEnv", "Layout", "environments", "serve"]

_REQUEST, _REPLY = 31, 32
_SEED, _RESET, _STEP, _GET_RNG, _SET_RNG, _CLOSE = range(6)


@dataclass(frozen=True)
class Layout:
    """How the ranks of ``world`` are split into groups of ``ranks_per_env`` ranks.

    ``comm``: this rank's group; ``group``: its index (0 .. n_envs - 1); ``leaders``: the
    communicator of the group leaders (rank g leads group g), ``MPI.COMM_NULL`` elsewhere.
    """

    world: MPI.Comm
    ranks_per_env: int
    n_envs: int
    group: int
    comm: MPI.Comm
    leaders: MPI.Comm

    @classmethod
    def split(cls, ranks_per_env: int, world: MPI.Comm = MPI.COMM_WORLD) -> Layout:
        """Split ``world`` (collective); ValueError naming the layout when P does not divide W."""
        check_layout(ranks_per_env, world.size)
        group = world.rank // ranks_per_env
        comm = world.Split(group, world.rank) if ranks_per_env < world.size else world
        is_leader = comm.rank == 0
        leaders = world.Split(0 if is_leader else MPI.UNDEFINED, world.rank)
        return cls(world, ranks_per_env, world.size // ranks_per_env, group, comm, leaders)


class _Member:
    """One environment of the batch as seen from world rank 0: local (group 0) or remote."""

    def __init__(self, index: int, env: EnvBase | None, leaders: MPI.Comm | None):
        self.index, self.env, self.leaders = index, env, leaders
        self.state: TensorDictBase | None = None  # the local env's current tensordict

    def send(self, command: int, argument=None) -> None:
        if self.env is None:
            self.leaders.send((command, argument), dest=self.index, tag=_REQUEST)

    def result(self, command: int, argument=None):
        """Run ``command`` here (local) or collect the reply to the request sent (remote)."""
        if self.env is None:
            with timeit("groups/wait"):  # the remote group's work, not the learner's own cost
                self.leaders.Probe(source=self.index, tag=_REPLY)
            return self.leaders.recv(source=self.index, tag=_REPLY)
        return _run(self, command, argument)


def _run(member: _Member, command: int, argument):
    """Carry out ``command`` on the environment of ``member`` (on its group leader)."""
    env = member.env
    if command == _SEED:
        env.set_seed(argument)
        return None
    if command == _RESET:
        member.state = env.reset()
        return numpy_leaves(member.state)
    if command == _STEP:
        member.state["action"] = torch.as_tensor(argument)
        step = env.step(member.state)
        member.state = step["next"]
        return numpy_leaves(member.state)
    if command == _GET_RNG:
        return env.rng.bit_generator.state
    if command == _SET_RNG:
        env.rng.bit_generator.state = argument
        return None
    raise ValueError(f"unknown command {command!r}")


def serve(env: EnvBase, leaders: MPI.Comm, spin_s: float = 0.05, max_sleep_s: float = 0.002):
    """Answer world rank 0's requests for ``env`` (a group leader other than rank 0) until it
    sends close; return the exit status it sends. Between requests the rank polls as a
    coordinator's follower does (:func:`~physicsrl.coordinated.wait_for`: busily for ``spin_s``
    seconds, then sleeping at most ``max_sleep_s`` between polls), so that it leaves the core
    to a learner that trains."""
    member = _Member(leaders.rank, env, None)
    oversubscribed = leaders.Get_size() > len(os.sched_getaffinity(0))
    request = functools.partial(leaders.Iprobe, source=0, tag=_REQUEST)
    while True:
        wait_for(request, spin_s, max_sleep_s, oversubscribed)
        command, argument = leaders.recv(source=0, tag=_REQUEST)
        if command == _CLOSE:
            return int(argument)
        leaders.send(_run(member, command, argument), dest=0, tag=_REPLY)


class GroupedEnv(Members):
    """The N environments of a :class:`Layout` as one TorchRL env of ``batch_size=[N]``
    (world rank 0 only; see the module docstring and :class:`~physicsrl.envs.members.Members`).

    Keys and specs are those of the member environments with a leading dimension N.
    """

    def __init__(self, env: EnvBase, layout: Layout, seed: int | None = None):
        if layout.world.rank != 0:
            raise ValueError("GroupedEnv lives on world rank 0 (the learner)")
        n = layout.n_envs
        super().__init__(n, device=env.device)
        self.layout = layout
        self.members = [_Member(0, env, None)] + [
            _Member(i, None, layout.leaders) for i in range(1, n)
        ]
        shape = torch.Size([n])
        self.observation_spec = env.observation_spec.expand(shape + env.observation_spec.shape)
        self.action_spec = env.action_spec.expand(shape + env.action_spec.shape)
        self.reward_spec = env.reward_spec.expand(shape + env.reward_spec.shape)
        self.done_spec = env.done_spec.expand(shape + env.done_spec.shape)
        self._set_seed(seed)

    @property
    def local_env(self) -> EnvBase:
        """Group 0's environment (on the learner's rank: plots, fields)."""
        return self.members[0].env

    @property
    def task(self):
        """Group 0's task (None for an env without one): its settings and hooks (baselines,
        scores) are every group's."""
        return vars(self.local_env).get("task")  # not getattr: EnvBase.__getattr__ searches on

    @property
    def reward_fn(self):
        return self.local_env.reward_fn

    def _all(self, command: int, arguments: Sequence, indices: Sequence[int]) -> list:
        """Send ``command`` with ``arguments[k]`` to member ``indices[k]``, remote ones first,
        so that they work while the local one does; the results in the order of ``indices``."""
        members = [self.members[i] for i in indices]
        for member, argument in zip(members, arguments, strict=True):
            member.send(command, argument)
        local = [k for k, m in enumerate(members) if m.env is not None]
        results = [None] * len(members)
        for k in local:
            results[k] = members[k].result(command, arguments[k])
        for k, member in enumerate(members):
            if k not in local:
                results[k] = member.result(command)
        return results

    def seed_each(self, seeds: Sequence[int | None], indices: Sequence[int] | None = None):
        indices = range(self.batch_size[0]) if indices is None else indices
        self._all(_SEED, list(seeds), list(indices))

    def rng_state(self) -> list[dict]:
        n = self.batch_size[0]
        return self._all(_GET_RNG, [None] * n, range(n))

    def set_rng_state(self, states: Sequence[dict]) -> None:
        n = self.batch_size[0]
        if len(states) != n:
            raise ValueError(f"{len(states)} generator states for {n} environments")
        self._all(_SET_RNG, list(states), range(n))

    def reset_some(self, indices: Sequence[int]) -> dict[int, dict]:
        return dict(zip(indices, self._all(_RESET, [None] * len(indices), indices), strict=True))

    def step_some(self, actions: dict[int, int]) -> dict[int, dict]:
        indices = list(actions)
        return dict(zip(indices, self._all(_STEP, list(actions.values()), indices), strict=True))

    def close_groups(self, status: int = 0) -> None:
        """Release the other group leaders (their serve loops return ``status``)."""
        for member in self.members[1:]:
            member.send(_CLOSE, status)


@contextmanager
def environments(
    make_env: Callable[[Coordinator], EnvBase],
    ranks_per_env: int = 1,
    seed: int | None = None,
    world: MPI.Comm = MPI.COMM_WORLD,
) -> Iterator[EnvBase | None]:
    """Split ``world`` into groups (:class:`Layout`), build one environment per group with
    ``make_env(coordinator)`` (collective within the group) and yield, on world rank 0, the
    batched env (the plain env when there is one group); None on every other rank, after its
    group has been released. See the module docstring."""
    layout = Layout.split(ranks_per_env, world)
    coordinator = Coordinator(layout.comm)
    env = make_env(coordinator)
    with coordinator:
        if world.rank == 0:
            grouped = env if layout.n_envs == 1 else GroupedEnv(env, layout, seed)
            if layout.n_envs == 1 and seed is not None:
                env.set_seed(seed)
            status = 1
            try:
                yield grouped
                status = 0
            except SystemExit as stop:  # a clean exit on the learner is clean everywhere
                status = stop.code if isinstance(stop.code, int) else int(stop.code is not None)
                raise
            finally:
                if isinstance(grouped, GroupedEnv):
                    grouped.close_groups(status)
        elif coordinator.is_leader():
            status = serve(env, layout.leaders)
            if status:
                raise SystemExit(status)
            yield None
        else:
            yield None
