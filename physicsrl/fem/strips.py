r"""A structured grid of square Q1 cells cut into strips of node rows, one per rank: the state
moved between DOLFINx's dof layout and the strips, and the halo rows of the 9-point stencil.

The explicit scheme's operator on such a grid (:mod:`physicsrl.fem.grid`) is the 9-point
stencil, so a step needs, besides a rank's own rows, only the row above and the row below.
Whatever partition DOLFINx chose, rank r of P takes the node rows
:math:`[\lfloor r R / P \rfloor, \lfloor (r + 1) R / P \rfloor)` of the R rows, stored
row-major with a halo row on either side ((rows + 2, n + 1) arrays): :meth:`Strips.scatter`
moves owned values there (one ``Alltoallv``), :meth:`Strips.gather` back, and
:meth:`Strips.fill_halos` copies the neighbours' edge rows into the halos (two ``Sendrecv``
of one row each) or, at the grid's edge, mirrors node row 1 (the Neumann condition). On one
rank the transfer is a permutation and there is nothing to exchange.

:func:`square_stencil` finds the strips of a function space and checks, on a random vector,
that an assembled operator is the stencil on them: the transfer, the halos and the stencil
together against the assembled rows.
"""

from __future__ import annotations

import numpy as np
from dolfinx import fem
from mpi4py import MPI

from physicsrl.fem.grid import grid_axes, nine_point_stencil


class Strips:
    """The node rows of a grid of ``width`` nodes per row and ``height`` rows, cut into one
    strip per rank of ``comm``; ``index`` (owned,) is the grid index (row-major) of each owned
    dof. Every strip has at least two rows. Collective.

    ``first``, ``last``: this rank's node rows [first, last); ``order``: the owned dofs in the
    order they are sent (on one rank, grid order)."""

    def __init__(self, comm: MPI.Comm, width: int, height: int, index: np.ndarray):
        size, rank = comm.size, comm.rank
        bounds = np.arange(size + 1) * height // size
        self.comm, self.width = comm, width
        self.first, self.last = int(bounds[rank]), int(bounds[rank + 1])
        self.above = rank - 1 if rank > 0 else MPI.PROC_NULL
        self.below = rank + 1 if rank < size - 1 else MPI.PROC_NULL
        destination = np.searchsorted(bounds, index // width, side="right") - 1
        self.order = np.argsort(index)  # by destination too: rows grow with the index
        self.send_counts = np.bincount(destination, minlength=size)
        self.receive_counts = np.array(comm.alltoall(self.send_counts.tolist()))
        received = self._exchange(
            index[self.order].astype(np.int64), self.send_counts, self.receive_counts
        )
        self.positions = received - (self.first - 1) * width  # in the (rows + 2, width) strip

    @property
    def shape(self) -> tuple[int, int]:
        """(rows + 2, width): the strip with its two halo rows."""
        return (self.last - self.first + 2, self.width)

    def scatter(self, owned: np.ndarray) -> np.ndarray:
        """This rank's strip (rows + 2, width) of the owned values of every rank (halos not
        set)."""
        strip = np.empty(self.shape)
        strip.ravel()[self.positions] = self._exchange(
            owned[self.order], self.send_counts, self.receive_counts
        )
        return strip

    def gather(self, strip: np.ndarray, owned: np.ndarray) -> None:
        """Write the strips' values back into ``owned`` (this rank's owned dofs)."""
        values = strip.ravel()[self.positions]
        owned[self.order] = self._exchange(values, self.receive_counts, self.send_counts)

    def fill_halos(self, strip: np.ndarray) -> None:
        """The halo rows of ``strip``: the neighbouring strips' edge rows, or a mirror of node
        row 1 at the grid's first and last rows."""
        comm = self.comm
        comm.Sendrecv(strip[1], dest=self.above, recvbuf=strip[-1], source=self.below)
        comm.Sendrecv(strip[-2], dest=self.below, recvbuf=strip[0], source=self.above)
        if self.above == MPI.PROC_NULL:
            strip[0] = strip[2]
        if self.below == MPI.PROC_NULL:
            strip[-1] = strip[-3]

    def _exchange(self, values: np.ndarray, send: np.ndarray, receive: np.ndarray) -> np.ndarray:
        """``Alltoallv`` of ``values``, ``send[q]`` of them to rank q and ``receive[q]`` from
        it."""
        if self.comm.size == 1:
            return values
        received = np.empty(int(receive.sum()), dtype=values.dtype)
        self.comm.Alltoallv([values, send], [received, receive])
        return received


def square_stencil(V: fem.FunctionSpace, apply, scale: float) -> tuple[Strips, float] | None:
    """(strips, c) when ``V``'s dofs (on all ranks) form a grid of square cells, at least two
    node rows per rank, on which ``apply`` (this rank's nodal values, ghosts included, (n,) ->
    the owned values of C times them) is :func:`~physicsrl.fem.grid.nine_point_stencil` with
    c = ``scale`` / h^2, else None. Checked on a random vector: ``apply`` in DOLFINx's layout
    against the stencil on the strips with their halos. Collective."""
    axes = grid_axes(V)
    comm = V.mesh.comm
    if axes is None:
        return None
    x, y, index = axes
    h = x[1] - x[0]
    square = min(len(x), len(y)) >= 3 and all(
        np.allclose(np.diff(a), h, rtol=1e-9, atol=0) for a in (x, y)
    )
    if not square or len(y) < 2 * comm.size:
        return None
    owned = V.dofmap.index_map.size_local
    strips = Strips(comm, len(x), len(y), index[:owned])
    c = scale / h**2
    u = _noise(index)
    strip = strips.scatter(u[:owned])
    strips.fill_halos(strip)
    rows = strips.scatter(apply(u))[1:-1]
    matches = np.allclose(rows, nine_point_stencil(strip, c), rtol=0, atol=1e-12)
    return (strips, c) if comm.allreduce(matches, op=MPI.LAND) else None


def _noise(index: np.ndarray) -> np.ndarray:
    """Values in [0, 1) that look random, a function of the grid index alone (so that every
    rank computes the same value for a shared node)."""
    return np.modf(np.abs(np.sin(index * 12.9898 + 78.233)) * 43758.5453)[0]
