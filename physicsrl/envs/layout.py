r"""Many environments in one MPI job: the ranks split into N simulator groups of P ranks
(:class:`Layout`), each building its own environment (:func:`environments`).

A job of W ranks splits into N = W / P *groups* of P consecutive ranks (group g holds world
ranks gP .. gP + P - 1). Each group builds its own mesh, simulator and task on its own
communicator with its own :class:`~physicsrl.coordinated.Coordinator`, exactly as a single
environment does; the first rank of a group leads it. World rank 0 runs the learner and also
leads group 0: there the N environments are one TorchRL env of ``batch_size=[N]``
(:class:`~physicsrl.envs.groups.GroupedEnv`), whose requests the other group leaders serve
(:func:`~physicsrl.envs.groups.serve`); the other ranks serve their group leader's parallel
calls. This module imports no torch: a rank that only serves its group's simulator may build
its task alone (:func:`~physicsrl.envs.factory.make_env_for_rank`).

Seeds: environment i is seeded with :func:`~physicsrl.envs.members.member_seed` ``(seed, i)``,
so its episodes depend only on (seed, i, its episode count), never on P or W; environment 0 is
seeded with ``seed`` itself, so N = 1 is the plain environment.

Use it on every rank::

    with environments(lambda coordinator: make_env(cfg, coordinator), ranks_per_env=1) as env:
        if env is not None:  # world rank 0: the learner
            ...              # train on env (batch_size [N], or the plain env when N = 1)

Failures: an exception on world rank 0 inside the block tells every group to stop with
status 1 (the command-line wrapper then aborts the job); an exception in a simulator of any
group ends the whole job through its coordinator (``MPI.Abort``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from mpi4py import MPI

from physicsrl.coordinated import Coordinator
from physicsrl.launch import check_layout

__all__ = ["Layout", "environments"]


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


@contextmanager
def environments(
    make_env: Callable[[Coordinator], Any],
    ranks_per_env: int = 1,
    seed: int | None = None,
    world: MPI.Comm = MPI.COMM_WORLD,
) -> Iterator[Any]:
    """Split ``world`` into groups (:class:`Layout`), build one environment per group with
    ``make_env(coordinator)`` (collective within the group) and yield, on world rank 0, the
    batched env (the plain env when there is one group); None on every other rank, after its
    group has been released. See the module docstring."""
    layout = Layout.split(ranks_per_env, world)
    coordinator = Coordinator(layout.comm)
    env = make_env(coordinator)
    with coordinator:
        if world.rank == 0:
            from physicsrl.envs.groups import GroupedEnv  # TorchRL: on the ranks with an env

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
            from physicsrl.envs.groups import serve  # TorchRL, likewise

            status = serve(env, layout.leaders)
            if status:
                raise SystemExit(status)
            yield None
        else:
            yield None
    if layout.leaders != MPI.COMM_NULL:  # a few thousand communicators per process
        layout.leaders.Free()
