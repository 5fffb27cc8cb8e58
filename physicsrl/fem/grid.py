r"""Structured grids of Q1 cells: their node order, their operators as Kronecker products, and
the direct solve of :math:`(M + c K) x = b` by fast diagonalisation.

On the rectangles of ``mesh.create_rectangle`` (quadrilateral cells) on one rank, the dofs of
the Lagrange degree-1 space are the nodes :math:`(x_j, y_i)` of a tensor grid, :math:`n_x`
nodes per row and :math:`n_y` rows. In grid order (row-major, node :math:`k = i n_x + j`) the
Q1 mass and stiffness matrices are Kronecker products of the 1D P1 matrices of the node
coordinates (exact, with the exact quadrature DOLFINx uses):

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
:func:`square_stencil` checks it against the assembled operator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse
from dolfinx import fem


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


def grid_of(V: fem.FunctionSpace, mass=None, stiffness=None) -> Grid | None:
    """The :class:`Grid` of ``V``'s dofs when ``V`` is a degree-1 Lagrange space on one rank
    whose nodes form a tensor grid, else None. With ``mass`` and ``stiffness`` (V's assembled
    scipy matrices) also None unless they equal the Kronecker products (to 1e-10 relative)."""
    owned = V.dofmap.index_map.size_local
    if V.mesh.comm.size > 1 or V.dofmap.index_map_bs != 1 or V.mesh.geometry.dim != 2 or owned < 4:
        return None
    xy = V.tabulate_dof_coordinates()[:owned, :2]
    scale = float(np.abs(xy).max()) or 1.0
    axes = [np.unique(np.round(xy[:, a] / scale, 12)) * scale for a in (0, 1)]
    if len(axes[0]) * len(axes[1]) != owned or min(len(a) for a in axes) < 2:
        return None
    node = [np.searchsorted(axes[a], np.round(xy[:, a] / scale, 12) * scale) for a in (0, 1)]
    order = np.full(owned, -1)
    order[node[1] * len(axes[0]) + node[0]] = np.arange(owned)
    if (order < 0).any():
        return None
    grid = Grid(order, xy[order[: len(axes[0])], 0], xy[order[:: len(axes[0])], 1])
    if mass is not None:
        for assembled, product in zip((mass, stiffness), grid.operators(), strict=True):
            difference = abs(assembled[order][:, order] - product).max()
            if difference > 1e-10 * abs(assembled).max():
                return None
    return grid


def nine_point_stencil(u: np.ndarray, c: float) -> np.ndarray:
    """The 9-point stencil of the module docstring on the grid values ``u`` (n + 1, n + 1)."""
    n = len(u) - 1
    padded = np.pad(u, 1, mode="reflect")
    ring = sum(
        padded[1 + di : n + 2 + di, 1 + dj : n + 2 + dj]
        for di in (-1, 0, 1)
        for dj in (-1, 0, 1)
        if di or dj
    )
    return u - c * (8 * u - ring)


def square_stencil(V: fem.FunctionSpace, apply, scale: float) -> tuple[Grid, float] | None:
    """(grid, c) when ``V``'s dofs form a grid of square cells on which ``apply`` (owned nodal
    values (n,) -> C times them, numpy) is :func:`nine_point_stencil` with c = ``scale`` / h^2
    (checked on a random vector), else None."""
    grid = grid_of(V)
    if grid is None or len(grid.x) != len(grid.y) or len(grid.x) < 3:
        return None
    h = grid.x[1] - grid.x[0]
    if not all(np.allclose(np.diff(a), h, rtol=1e-9, atol=0) for a in (grid.x, grid.y)):
        return None
    c = scale / h**2
    u = np.random.default_rng(0).random(len(grid.order))
    side = (len(grid.y), len(grid.x))
    expected = nine_point_stencil(u[grid.order].reshape(side), c)
    rows = apply(u)[grid.order].reshape(side)
    return (grid, c) if np.allclose(rows, expected, rtol=0, atol=1e-12) else None
