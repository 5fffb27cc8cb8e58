r"""Structured grids of Q1 cells: their node order, their operators as Kronecker products, and
the direct solve of :math:`(M + c K) x = b` by fast diagonalisation.

On the rectangles of ``mesh.create_rectangle`` (quadrilateral cells) the dofs of the Lagrange
degree-1 space, over all ranks, are the nodes :math:`(x_j, y_i)` of a tensor grid
(:func:`grid_axes`), :math:`n_x` nodes per row and :math:`n_y` rows. In grid order
(row-major, node :math:`k = i n_x + j`) the Q1 mass and stiffness matrices are Kronecker
products of the 1D P1 matrices of the node coordinates (exact, with the exact quadrature
DOLFINx uses):

.. math::

    M = M_y \otimes M_x, \qquad K = K_y \otimes M_x + M_y \otimes K_x,

    (M_1)_{j,j\pm1} = \frac{h}{6}, \quad (M_1)_{jj} = \frac{h_- + h_+}{3}, \qquad
    (K_1)_{j,j\pm1} = -\frac{1}{h}, \quad (K_1)_{jj} = \frac{1}{h_-} + \frac{1}{h_+},

h the length of the segment between the two nodes, :math:`h_\pm` those on either side (0 past
an end: the Neumann rows).

Fast diagonalisation (Lynch, Rice & Thomas 1964): the generalised eigenvectors
:math:`K_1 Q = M_1 Q \Lambda`, :math:`Q^T M_1 Q = I`, give
:math:`M_1 = Q^{-T} Q^{-1}` and :math:`K_1 = Q^{-T} \Lambda Q^{-1}`, hence

.. math::

    (M + c K)^{-1} = (Q_y \otimes Q_x)\,
        \mathrm{diag}\big(1 / (1 + c(\lambda^y_i + \lambda^x_j))\big)\,
        (Q_y \otimes Q_x)^T :

four products with :math:`n_y \times n_y` and :math:`n_x \times n_x` matrices and one
division, :math:`4 (n_x + n_y)` multiply-adds per node, no iteration. :func:`grid_of` checks
the assembled matrices against the Kronecker products before anything relies on them.

On square cells of side h the explicit scheme's operator
:math:`C = I - \Delta t D M_L^{-1} K` (:mod:`physicsrl.fem.explicit`) is the 9-point stencil
:math:`u_{ij} - c\big(8 u_{ij} - \sum_{\text{8 neighbours}} u\big)`,
:math:`c = \Delta t D / (3 h^2)`, with the Neumann condition as a mirror (node -1 reads node
1: the mirrored row is twice the boundary row, as the boundary's lumped mass is half);
:func:`~physicsrl.fem.strips.square_stencil` checks it against the assembled operator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse
from dolfinx import fem
from mpi4py import MPI


@dataclass(frozen=True)
class Grid:
    """The node order and coordinates of a structured grid of Q1 cells.

    ``order[k]`` is the dof of grid node k (row-major), ``x`` (n_x,) and ``y`` (n_y,) the node
    coordinates along each axis, increasing.
    """

    order: np.ndarray
    x: np.ndarray
    y: np.ndarray

    def operators(self) -> tuple[scipy.sparse.csr_matrix, scipy.sparse.csr_matrix]:
        """(M, K) in grid order, as the Kronecker products of the module docstring."""
        (mx, kx), (my, ky) = interval_operators(self.x), interval_operators(self.y)
        mass = scipy.sparse.kron(my, mx, format="csr")
        return mass, (scipy.sparse.kron(ky, mx) + scipy.sparse.kron(my, kx)).tocsr()

    def fast_diagonalisation(self, c: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        r"""(Q_x, Q_y, d) with :math:`(M + cK)^{-1} = (Q_y \otimes Q_x) \mathrm{diag}(1/d)
        (Q_y \otimes Q_x)^T`, d of shape (n_y, n_x) (module docstring)."""
        (mx, kx), (my, ky) = interval_operators(self.x), interval_operators(self.y)
        lx, qx = scipy.linalg.eigh(kx.toarray(), mx.toarray())
        ly, qy = scipy.linalg.eigh(ky.toarray(), my.toarray())
        return qx, qy, 1.0 + c * (ly[:, None] + lx[None, :])


def interval_operators(nodes: np.ndarray) -> tuple[scipy.sparse.csr_matrix, ...]:
    """(M_1, K_1): the P1 mass and stiffness matrices on the 1D mesh of ``nodes`` (increasing)."""
    h = np.diff(nodes)
    on_both_sides = lambda a: np.append(a, 0.0) + np.insert(a, 0, 0.0)  # noqa: E731
    mass = scipy.sparse.diags([h / 6, on_both_sides(h) / 3, h / 6], [-1, 0, 1], format="csr")
    stiffness = scipy.sparse.diags([-1 / h, on_both_sides(1 / h), -1 / h], [-1, 0, 1], format="csr")
    return mass, stiffness


def grid_axes(V: fem.FunctionSpace) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(x, y, index) when the dofs of ``V`` (a scalar space on a 2D mesh), on all ranks
    together, are the nodes of a tensor grid: the node coordinates along each axis (increasing)
    and the grid index (row-major: ``i * len(x) + j`` for node (x_j, y_i)) of this rank's dofs
    (owned, then ghosts). Else None, on every rank. Collective."""
    comm = V.mesh.comm
    owned = V.dofmap.index_map.size_local
    if V.dofmap.index_map_bs != 1 or V.mesh.geometry.dim != 2:
        return None
    xy = V.tabulate_dof_coordinates()[:, :2]
    scale = comm.allreduce(float(np.abs(xy).max(initial=0.0)), op=MPI.MAX) or 1.0
    rounded = np.round(xy / scale, 12)  # the keys that identify a grid line
    keys, axes = [], []  # per axis: the lines' keys and coordinates (one dof's, exact)
    for a in (0, 1):
        mine, first = np.unique(rounded[:owned, a], return_index=True)
        every = np.concatenate(comm.allgather(mine))
        coordinates = np.concatenate(comm.allgather(xy[:owned, a][first]))
        unique, pick = np.unique(every, return_index=True)
        keys.append(unique)
        axes.append(coordinates[pick])
    node = [np.searchsorted(keys[a], rounded[:, a]).clip(0, len(keys[a]) - 1) for a in (0, 1)]
    index = node[1] * len(keys[0]) + node[0]
    grid = (
        len(keys[0]) * len(keys[1]) == comm.allreduce(owned)
        and min(len(k) for k in keys) >= 2
        and all((keys[a][node[a]] == rounded[:, a]).all() for a in (0, 1))
        and (np.diff(np.sort(index[:owned])) > 0).all()  # no node twice
    )
    if not comm.allreduce(grid, op=MPI.LAND):
        return None
    return axes[0], axes[1], index


def grid_of(V: fem.FunctionSpace, mass=None, stiffness=None) -> Grid | None:
    """The :class:`Grid` of ``V``'s dofs when ``V`` is a degree-1 Lagrange space on one rank
    whose nodes form a tensor grid, else None. With ``mass`` and ``stiffness`` (V's assembled
    scipy matrices) also None unless they equal the Kronecker products (to 1e-10 relative)."""
    axes = grid_axes(V) if V.mesh.comm.size == 1 else None
    if axes is None or len(axes[2]) < 4:
        return None
    x, y, index = axes
    order = np.empty_like(index)
    order[index] = np.arange(len(index))
    grid = Grid(order, x, y)
    if mass is not None:
        for assembled, product in zip((mass, stiffness), grid.operators(), strict=True):
            difference = abs(assembled[order][:, order] - product).max()
            if difference > 1e-10 * abs(assembled).max():
                return None
    return grid


def nine_point_stencil(u: np.ndarray, c: float) -> np.ndarray:
    """The 9-point stencil of the module docstring on the node rows of ``u`` (rows + 2,
    n + 1): the rows with a halo row above and below (the columns are mirrored); shape
    (rows, n + 1)."""
    padded = np.pad(u, ((0, 0), (1, 1)), mode="reflect")
    rows, n = len(u) - 2, u.shape[1] - 1
    ring = sum(
        padded[1 + di : rows + 1 + di, 1 + dj : n + 2 + dj]
        for di in (-1, 0, 1)
        for dj in (-1, 0, 1)
        if di or dj
    )
    centre = u[1:-1]
    return centre - c * (8 * centre - ring)
