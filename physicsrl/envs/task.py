"""The simulator side of an environment: a :class:`Task` lives on every rank.

A task owns a simulator (a :class:`~physicsrl.coordinated.Coordinated` object), the
observation and its own fused integrals. The leader's TorchRL environment
(:class:`~physicsrl.envs.env.PhysicsEnv`) makes exactly one parallel call per ``reset`` (unless
a draw has to be repeated) and per ``step``; everything that touches the fields happens inside
it, on every rank. Randomness is drawn on the leader by :meth:`Task.draw` and passed as
arguments, so a seed gives the same episode on any number of ranks.

Construct tasks on every rank in the same order (their coordinator namespaces must match).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
from dolfinx import mesh as dmesh
from mpi4py import MPI

from physicsrl.checks import choice, integer, positive
from physicsrl.coordinated import Coordinated, parallel
from physicsrl.envs.registry import Registry

TASKS = Registry("env")


@dataclass(frozen=True)
class SquareMesh:
    """The square [-extent, extent]^2 split into cells x cells quadrilaterals or 2 x that many
    triangles (``cell_type``); lengths in the task's units."""

    cells: int = 50
    extent: float = 2.0
    cell_type: str = "triangle"

    def __post_init__(self):
        integer("cells", self.cells, 1)
        positive("extent", self.extent)
        choice("cell_type", self.cell_type, ("triangle", "quadrilateral"))

    def create(self, comm: MPI.Comm = MPI.COMM_WORLD) -> dmesh.Mesh:
        """The DOLFINx mesh (collective)."""
        e = self.extent
        kind = getattr(dmesh.CellType, self.cell_type)
        return dmesh.create_rectangle(comm, [[-e, -e], [e, e]], [self.cells, self.cells], kind)

    def explicit_limit(self, D: float) -> float:
        """The explicit scheme's stability limit (:func:`~physicsrl.fem.explicit.stability_limit`)
        with diffusivity ``D`` on this mesh, computed on this process from a copy of at most
        4 x 4 cells of the same side: the bound depends on the cell side alone, and the copy has
        every kind of node (corners, edges, interior)."""
        from dolfinx import fem

        from physicsrl.fem.explicit import lumped_mass, stability_limit, stiffness_rows

        n = min(self.cells, 4)
        copy = SquareMesh(n, self.extent * n / self.cells, self.cell_type).create(MPI.COMM_SELF)
        V = fem.functionspace(copy, ("Lagrange", 1))
        indptr, _, values, _ = stiffness_rows(V)
        return stability_limit(np.add.reduceat(np.abs(values), indptr[:-1]), lumped_mass(V), D)


class ResetDiverged(RuntimeError):
    """Every draw of a reset, ``max_reset_attempts`` in a row, came out non-finite: the
    numerics cannot start an episode (training stops with this one line)."""

    def __init__(self, attempts: int, where: str = ""):
        super().__init__(
            f"{attempts} reset draws in a row gave non-finite states{where}: the time step is "
            "likely too large for the scheme (lower env.model.dt or env.dt)"
        )
        self.attempts, self.where = attempts, where

    def __reduce__(self):  # a remote group's reaches the learner pickled
        return type(self), (self.attempts, self.where)


@dataclass
class Transition:
    """What one step reports to the leader.

    ``observation``: array (observation size,); ``events``: plain numbers and flags for the
    reward (see :mod:`physicsrl.envs.rewards`); ``step``: decisions taken so far.
    """

    observation: np.ndarray
    events: dict
    step: int
    terminated: bool = False
    truncated: bool = False
    diverged: bool = False
    flags: dict = field(default_factory=dict)


class Task(Coordinated):
    """Base class of the simulator side of a task (see the module docstring).

    Subclasses set ``n_actions``, ``events`` (the event keys their transitions carry),
    ``flags`` (boolean keys copied into the tensordict), ``variables`` (the state's variables
    an observation may read; default u), ``max_steps`` and ``observation``, and
    implement :meth:`draw`, :meth:`reset` and :meth:`step` (both ``@parallel``).

    Hooks for the command line, which knows no task by name: ``action_counts`` (metric name ->
    the action counted per evaluated episode), :meth:`baselines` and :meth:`scores`. The
    observation and reward that go with the task are chosen by its YAML's defaults list.
    """

    Config: ClassVar[type]
    n_actions: ClassVar[int]
    events: ClassVar[frozenset[str]]
    flags: ClassVar[tuple[str, ...]] = ()
    variables: ClassVar[tuple[str, ...]] = ("u",)  # what an observation may read
    action_counts: ClassVar[dict[str, int]] = {}
    max_steps: int

    def baselines(self, env, seeds: Sequence[int], seed: int) -> dict[str, Callable]:
        """Display name -> baseline policy, to compare the agent with on ``seeds`` (leader
        only, inside ``with coordinator:``; ``seed`` seeds random policies)."""
        return {}

    @staticmethod
    def scores(returns: dict[str, float]) -> list[str]:
        """Summary lines from the mean return of each policy (``"greedy DQN"`` and the
        baselines' display names)."""
        return []

    def draw(self, rng: np.random.Generator) -> tuple:
        """The random numbers of one reset, drawn on the leader (plain Python numbers)."""
        raise NotImplementedError

    @parallel
    def reset(self, *draws) -> np.ndarray | None:
        """Start an episode from ``draws``; the first observation, or None on every rank if the
        state is not finite (the leader then draws again)."""
        raise NotImplementedError

    @parallel
    def step(self, action: int) -> Transition:
        """Apply ``action`` and advance to the next decision."""
        raise NotImplementedError

    def integrals_now(self) -> np.ndarray:
        """``self.integrals`` of the state now: of u, and of the other ``variables`` for a task
        that simulates more. Collective."""
        return self.integrals(self.simulator.u_n())

    @parallel
    def field(self) -> tuple[np.ndarray, np.ndarray, float] | None:
        """The field u now, gathered for plotting: dof coordinates (N, 2), values (N,) of all
        ranks and the integral of u, on the leader; None on the others. Expects
        ``self.simulator.u_n()`` and ``self.integrals`` (row 0: the integral of u)."""
        u = self.simulator.u_n()
        integral = float(self.integrals_now()[0])
        V = u.function_space
        n = V.dofmap.index_map.size_local
        local = np.column_stack([V.tabulate_dof_coordinates()[:n, :2], u.x.array[:n]])
        gathered = V.mesh.comm.gather(local, root=0)
        if gathered is None:
            return None
        points = np.concatenate(gathered)
        return points[:, :2], points[:, 2], integral
