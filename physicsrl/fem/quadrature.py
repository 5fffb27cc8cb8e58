r"""Cell quadrature tables, and their evaluation in numpy: values of finite element functions
at quadrature points and vectors :math:`\int_\Omega f\, v\, dx` assembled from values
:math:`f` at those points.

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
  parallelograms), otherwise one per cell and point (computed by a C loop of
  :mod:`physicsrl.fem.kernels` when one is given, in one pass without temporaries).

These tables are all a compiled kernel needs (e.g. ``ms_rhs`` of :mod:`physicsrl.fem.kernels`).
The numpy evaluation (:meth:`CellQuadrature.values`, :meth:`~CellQuadrature.integrate`,
:meth:`~CellQuadrature.scatter`) builds more on first use: intp dofs, the test table with the
weights (and the per-cell |det J| folded into the scatter), and the scatter, a CSR matrix from
the flattened cell vectors to the local dof vector. It runs over blocks of
:attr:`CellQuadrature.block` cells so that the (block, nq) work arrays stay in cache: numpy's
passes over ``ncells * nq`` arrays would otherwise be bound by memory bandwidth on large
meshes. The small matrix products are done by numpy's ``matmul`` (BLAS); with many MPI ranks
per node, limit BLAS to one thread (``OMP_NUM_THREADS=1``), as for any MPI code.
"""

from __future__ import annotations

import basix
import numpy as np
import scipy.sparse
from dolfinx import fem

from physicsrl.fem.errors import InvalidValue
from physicsrl.fem.kernels import pointer

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
        Cells per block of the numpy evaluation (see the module docstring).
    kernels:
        The compiled module of :mod:`physicsrl.fem.kernels` (computes |det J| in one C loop),
        or ``None`` for numpy.

    Attributes
    ----------
    num_cells, num_points, num_dofs, num_local_dofs:
        Owned cells, quadrature points per cell, dofs per cell, local dofs (owned + ghost).
    dofs:
        (num_cells, num_dofs) int32: the owned cells' local dofs (a view of DOLFINx's map).
    phi:
        (num_points, num_dofs): :math:`\\Phi_{qk} = \\phi_k(\\hat x_q)`.
    affine:
        Whether :math:`|\\det J|` is constant in every cell.
    cell_det, point_weights:
        Affine: ``cell_det`` (num_cells,) holds :math:`|\\det J_c|` and ``point_weights``
        (num_points,) the rule's weights :math:`\\hat w_q`; otherwise ``cell_det`` is ``None``
        and ``point_weights`` (num_cells, num_points) holds
        :math:`\\hat w_q |\\det J_c(\\hat x_q)|`.
    """

    def __init__(self, V: fem.FunctionSpace, degree: int, block: int = DEFAULT_BLOCK, kernels=None):
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
        self.dofs = np.ascontiguousarray(V.dofmap.list[:nc], dtype=np.int32)
        self.num_cells, self.num_dofs = self.dofs.shape
        self.num_points = len(weights)
        self.num_local_dofs = V.dofmap.index_map.size_local + V.dofmap.index_map.num_ghosts
        self.phi = np.ascontiguousarray(
            V.element.basix_element.tabulate(0, points)[0, :, :, 0]
        )  # (nq, nd)

        cmap = domain.geometry.cmaps[0]
        coordinate_element = basix.create_element(
            basix.ElementFamily.P, cell, cmap.degree, basix.LagrangeVariant(cmap.variant)
        )
        dphi = coordinate_element.tabulate(1, points)[1 : tdim + 1, :, :, 0]  # (tdim, nq, nx)
        gdofs = domain.geometry.dofmaps[0][:nc]
        if kernels is not None and gdim == tdim:
            cell_det, spread = self._det_compiled(kernels, domain.geometry.x, gdofs, dphi)
        else:
            cell_det, spread = self._det_numpy(domain.geometry.x[:, :gdim], gdofs, dphi, tdim)
        self.affine = bool(spread <= 1e-13)
        if self.affine:
            self.cell_det = np.ascontiguousarray(cell_det[:, 0])
            self.point_weights = np.ascontiguousarray(weights)
        else:
            if kernels is not None and gdim == tdim:  # the full table
                cell_det = self._det_compiled(kernels, domain.geometry.x, gdofs, dphi, True)[0]
            self.cell_det = None
            self.point_weights = cell_det * weights
        self._numpy = None  # the numpy evaluation's tables, built on first use

    def _det_compiled(self, kernels, x, gdofs, dphi, per_point: bool = False):
        """|det J| by the C loop: (cells, 1) (point 0) or (cells, nq), and the relative
        spread within cells."""
        ffi, lib = kernels.ffi, kernels.lib
        nc, nq = self.num_cells, self.num_points
        gdofs = np.ascontiguousarray(gdofs, dtype=np.int32)
        x = np.ascontiguousarray(x)
        dphi = np.ascontiguousarray(dphi)
        det = np.empty((nc, nq if per_point else 1))
        spread = lib.cell_det(
            nc,
            dphi.shape[0],
            nq,
            dphi.shape[2],
            pointer(ffi, gdofs, "int32_t *"),
            pointer(ffi, x),
            pointer(ffi, dphi),
            pointer(ffi, det),
            int(per_point),
        )
        return det, spread

    def _det_numpy(self, x, gdofs, dphi, tdim):
        """|det J| (cells, nq) in blocks of cells (the coordinates of all cells at once would
        be a large temporary), and the relative spread within cells."""
        nc = self.num_cells
        det = np.empty((nc, self.num_points))
        dphi_t = [np.ascontiguousarray(dphi[j].T) for j in range(tdim)]  # (nx, nq) each
        for start in range(0, nc, 65536):
            coords = x[gdofs[start : start + 65536]]  # (b, nx, gdim)
            # J[i][j] = d x_i / d X_j at the points, (b, nq) each
            J = [[coords[:, :, i] @ dphi_t[j] for j in range(tdim)] for i in range(x.shape[1])]
            det[start : start + 65536] = _abs_det(J, x.shape[1], tdim)
        spread = np.abs(det - det[:, :1]).max(initial=0.0)
        return det, spread / np.abs(det).max(initial=1.0)

    # numpy evaluation -------------------------------------------------------------------
    def _tables(self):
        """The numpy path's tables (built once): intp dofs, (nd, nq) interpolation and
        (nq, nd) test tables, the scatter, cell vectors and work arrays."""
        if self._numpy is not None:
            return self._numpy
        nc, nd, nq = self.num_cells, self.num_dofs, self.num_points
        dofs = self.dofs.astype(np.intp)
        if self.affine:
            # sum_q w_q |det J_c| f_cq phi_k(x_q) = |det J_c| (f_c . (w * phi))_k
            test = self.point_weights[:, None] * self.phi
            scale = np.repeat(self.cell_det, nd)
        else:
            test = self.phi
            scale = np.ones(nc * nd)
        flat = dofs.ravel()
        scatter = scipy.sparse.csr_matrix(
            (scale, (flat, np.arange(flat.size))), shape=(self.num_local_dofs, flat.size)
        )
        scatter.sum_duplicates()
        b = min(self.block, max(nc, 1))
        self._numpy = {
            "dofs": dofs,
            "phi_t": np.ascontiguousarray(self.phi.T),
            "test": np.ascontiguousarray(test),
            "scatter": scatter,
            "local": np.empty((nc, nd)),
            "gathered": np.empty((b, nd)),
            "work": [np.empty((b, nq)) for _ in range(4)],
        }
        return self._numpy

    def blocks(self):
        """The (start, stop) cell ranges of the blocks."""
        return [
            (s, min(s + self.block, self.num_cells)) for s in range(0, self.num_cells, self.block)
        ]

    def values(self, array: np.ndarray, start: int, stop: int, out: np.ndarray) -> np.ndarray:
        """Values at the quadrature points of cells start..stop of the function with local dof
        values ``array``, written to ``out[: stop - start]`` (shape (>= stop - start, nq))."""
        t = self._tables()
        n = stop - start
        gathered = t["gathered"][:n]
        np.take(array, t["dofs"][start:stop], out=gathered)
        return np.matmul(gathered, t["phi_t"], out=out[:n])

    def integrate(self, values: np.ndarray, start: int, stop: int) -> None:
        """Store the cell vectors of cells start..stop for integrand values ``values``
        (shape (stop - start, nq)); ``values`` is overwritten. :meth:`scatter` then adds all
        cell vectors to a dof vector."""
        t = self._tables()
        if not self.affine:
            values *= self.point_weights[start:stop]
        np.matmul(values, t["test"], out=t["local"][start:stop])

    def scatter(self, b: np.ndarray) -> None:
        """``b += `` the cell vectors stored by :meth:`integrate` (``b``: local dof values,
        owned and ghost; ghost entries receive partial sums to be added to their owners)."""
        t = self._tables()
        S = t["scatter"]
        local = t["local"].reshape(-1)
        if _csr_matvec is not None:
            _csr_matvec(S.shape[0], S.shape[1], S.indptr, S.indices, S.data, local, b)
        else:  # pragma: no cover
            b += S @ local

    def work(self, i: int) -> np.ndarray:
        """Work array ``i`` (0..3) of shape (block, nq)."""
        return self._tables()["work"][i]


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
