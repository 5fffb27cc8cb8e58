r"""Cell quadrature in numpy: values of finite element functions at quadrature points and
vectors :math:`\int_\Omega f\, v\, dx` assembled from values :math:`f` at those points.

For a scalar Lagrange space :math:`V` and a quadrature rule :math:`(\hat x_q, \hat w_q)` on the
reference cell (basix's default rule of a given degree, the rule FFCx uses for a form with that
``quadrature_degree``), the vector of a linear form with a pointwise integrand is

.. math::

    b_i = \sum_{c} \sum_{q} \hat w_q\, |\det J_c(\hat x_q)|\, f_c(\hat x_q)\, \phi_i(\hat x_q),

the *same* sum DOLFINx evaluates for the UFL form, so both agree to round-off. Everything that
does not depend on the integrand is tabulated once per mesh (:class:`CellQuadrature`):

- the cell -> dof map of the cells this rank owns (ghost cells are skipped, as DOLFINx does;
  ghost dofs receive contributions that the caller adds to their owners with a reverse
  scatter);
- the basis values :math:`\Phi_{qk} = \phi_k(\hat x_q)` (nq, ndofs per cell);
- :math:`|\det J|`: one number per cell when the geometry is affine in every cell (simplices,
  parallelograms), then folded into the scatter matrix, otherwise one per cell and point;
- the scatter, a CSR matrix from the flattened cell vectors to the local dof vector.

The evaluation runs over blocks of :attr:`CellQuadrature.block` cells so that the (block, nq)
work arrays stay in cache: numpy's passes over ``ncells * nq`` arrays would otherwise be bound
by memory bandwidth on large meshes. The small matrix products are done by numpy's ``matmul``
(BLAS); with many MPI ranks per node, limit BLAS to one thread (``OMP_NUM_THREADS=1``), as for
any MPI code.
"""

from __future__ import annotations

import basix
import numpy as np
import scipy.sparse
from dolfinx import fem

from physicsrl.fem.errors import InvalidValue

try:  # y += A x without allocating, as scipy's own ``A @ x`` does internally
    from scipy.sparse._sparsetools import csr_matvec as _csr_matvec
except ImportError:  # pragma: no cover - a future scipy
    _csr_matvec = None

DEFAULT_BLOCK = 4096
"""Cells per block: (4096, 9) float64 work arrays are 295 kB; measured fastest (with 2048) on
250 x 250 Q1 cells, 3x faster than one block of all cells."""


class CellQuadrature:
    """Quadrature tables of a scalar Lagrange space on this rank's owned cells.

    Parameters
    ----------
    V:
        A scalar Lagrange space (P or Q, any degree without dof transformations).
    degree:
        The quadrature degree; the rule is ``basix.make_quadrature(cell, degree)``.
    block:
        Cells per block of the evaluation (see the module docstring).

    Attributes
    ----------
    num_cells, num_points, num_dofs:
        Owned cells, quadrature points per cell, dofs per cell.
    affine:
        Whether :math:`|\\det J|` is constant in every cell (then stored per cell only).
    """

    def __init__(self, V: fem.FunctionSpace, degree: int, block: int = DEFAULT_BLOCK):
        domain = V.mesh
        tdim = domain.topology.dim
        gdim = domain.geometry.dim
        if V.dofmap.bs != 1 or V.element.num_sub_elements or V.value_size != 1:
            raise InvalidValue("CellQuadrature: V must be a scalar space")
        if V.element.needs_dof_transformations:
            raise InvalidValue("CellQuadrature: V's element needs dof transformations")
        if len(domain.geometry.cmaps) != 1:
            raise InvalidValue("CellQuadrature: meshes of one cell type only")
        self.block = int(block)
        cell = domain.basix_cell()
        points, weights = basix.make_quadrature(cell, int(degree))
        nc = domain.topology.index_map(tdim).size_local
        dofs = np.asarray(V.dofmap.list[:nc], dtype=np.intp)
        self.num_cells, self.num_dofs = dofs.shape
        self.num_points = len(weights)
        self.num_local_dofs = V.dofmap.index_map.size_local + V.dofmap.index_map.num_ghosts
        self._dofs = dofs
        phi = V.element.basix_element.tabulate(0, points)[0, :, :, 0]  # (nq, nd)
        self._phi_t = np.ascontiguousarray(phi.T)  # (nd, nq): point values from dof values

        # |det J| at every point, in blocks of cells (the coordinates of all cells at once
        # would be a large temporary).
        cmap = domain.geometry.cmaps[0]
        coordinate_element = basix.create_element(
            basix.ElementFamily.P, cell, cmap.degree, basix.LagrangeVariant(cmap.variant)
        )
        dphi = coordinate_element.tabulate(1, points)[1 : tdim + 1, :, :, 0]  # (tdim, nq, nx)
        x = domain.geometry.x[:, :gdim]
        gdofs = domain.geometry.dofmaps[0][:nc]
        det = np.empty((nc, self.num_points))
        dphi_t = [np.ascontiguousarray(dphi[j].T) for j in range(tdim)]  # (nx, nq) each
        for start in range(0, nc, 65536):
            coords = x[gdofs[start : start + 65536]]  # (b, nx, gdim)
            # J[i][j] = d x_i / d X_j at the points, (b, nq) each
            J = [[coords[:, :, i] @ dphi_t[j] for j in range(tdim)] for i in range(gdim)]
            det[start : start + 65536] = _abs_det(J, gdim, tdim)
        spread = np.abs(det - det[:, :1]).max(initial=0.0)
        self.affine = bool(spread <= 1e-13 * np.abs(det).max(initial=1.0))
        if self.affine:
            # sum_q w_q |det J_c| f_cq phi_k(x_q) = |det J_c| (f_c . (w * phi))_k
            self._test = np.ascontiguousarray(weights[:, None] * phi)  # (nq, nd)
            self._weights = None
            scale = np.repeat(det[:, 0], self.num_dofs)
        else:
            self._test = np.ascontiguousarray(phi)
            self._weights = det * weights  # (nc, nq)
            scale = np.ones(nc * self.num_dofs)
        del det
        flat = dofs.ravel()
        self._scatter = scipy.sparse.csr_matrix(
            (scale, (flat, np.arange(flat.size))),
            shape=(self.num_local_dofs, flat.size),
        )
        self._scatter.sum_duplicates()
        self._local = np.empty((nc, self.num_dofs))  # cell vectors
        b = min(self.block, max(nc, 1))
        self._gathered = np.empty((b, self.num_dofs))
        self._work = [np.empty((b, self.num_points)) for _ in range(4)]

    def blocks(self):
        """The (start, stop) cell ranges of the blocks."""
        return [
            (s, min(s + self.block, self.num_cells)) for s in range(0, self.num_cells, self.block)
        ]

    def values(self, array: np.ndarray, start: int, stop: int, out: np.ndarray) -> np.ndarray:
        """Values at the quadrature points of cells start..stop of the function with local dof
        values ``array``, written to ``out[: stop - start]`` (shape (>= stop - start, nq))."""
        n = stop - start
        gathered = self._gathered[:n]
        np.take(array, self._dofs[start:stop], out=gathered)
        return np.matmul(gathered, self._phi_t, out=out[:n])

    def integrate(self, values: np.ndarray, start: int, stop: int) -> None:
        """Store the cell vectors of cells start..stop for integrand values ``values``
        (shape (stop - start, nq)); ``values`` is overwritten. :meth:`scatter` then adds all
        cell vectors to a dof vector."""
        if self._weights is not None:
            values *= self._weights[start:stop]
        np.matmul(values, self._test, out=self._local[start:stop])

    def scatter(self, b: np.ndarray) -> None:
        """``b += `` the cell vectors stored by :meth:`integrate` (``b``: local dof values,
        owned and ghost; ghost entries receive partial sums to be added to their owners)."""
        S = self._scatter
        local = self._local.reshape(-1)
        if _csr_matvec is not None:
            _csr_matvec(S.shape[0], S.shape[1], S.indptr, S.indices, S.data, local, b)
        else:  # pragma: no cover
            b += S @ local

    def cell_values(self, function: fem.Function) -> np.ndarray:
        """The owned cells' values of a piecewise constant (DG0) function, in cell order."""
        dofs = function.function_space.dofmap.list[: self.num_cells, 0]
        return function.x.array[dofs]

    def work(self, i: int) -> np.ndarray:
        """Work array ``i`` (0..3) of shape (block, nq)."""
        return self._work[i]


def _abs_det(J, gdim: int, tdim: int) -> np.ndarray:
    """|det J| (or sqrt(det(J^T J)) for a manifold) from the nested lists of arrays J[i][j]."""
    if gdim == tdim == 1:
        return np.abs(J[0][0])
    if gdim == tdim == 2:
        return np.abs(J[0][0] * J[1][1] - J[0][1] * J[1][0])
    if gdim == tdim == 3:
        return np.abs(
            J[0][0] * (J[1][1] * J[2][2] - J[1][2] * J[2][1])
            - J[0][1] * (J[1][0] * J[2][2] - J[1][2] * J[2][0])
            + J[0][2] * (J[1][0] * J[2][1] - J[1][1] * J[2][0])
        )
    full = np.stack([np.stack(row, axis=-1) for row in J], axis=-2)  # (b, nq, gdim, tdim)
    return np.sqrt(np.linalg.det(np.einsum("bqij,bqik->bqjk", full, full)))
