"""Structured grids of Q1 cells: the Kronecker operators and the fast-diagonalisation solve."""

from __future__ import annotations

import physicsrl.fem  # noqa: F401  (first: loads the MPI library that dolfinx links to)

# isort: split

import numpy as np
import pytest
import scipy.sparse.linalg
import ufl
from dolfinx import fem, mesh
from mpi4py import MPI

from physicsrl.fem.grid import grid_of


def space_and_operators(cell_type):
    """P1 on a 7 x 5 rectangle [-50, 50] x [-40, 50] (cells 14.3 x 18 mm), its M and K."""
    domain = mesh.create_rectangle(MPI.COMM_SELF, [[-50.0, -40.0], [50.0, 50.0]], [7, 5], cell_type)
    V = fem.functionspace(domain, ("Lagrange", 1))
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    return (
        V,
        fem.assemble_matrix(fem.form(u * v * ufl.dx)).to_scipy(),
        fem.assemble_matrix(fem.form(ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx)).to_scipy(),
    )


@pytest.mark.parametrize("c", [1e-3, 0.39, 50.0])
def test_fast_diagonalisation_solves_the_assembled_system(c):
    """(M + c K) x = b by fast diagonalisation equals scipy's sparse LU on DOLFINx's assembled
    matrices, on rectangular (not square) cells, for a stiff and a mass-dominated c."""
    V, M, K = space_and_operators(mesh.CellType.quadrilateral)
    grid = grid_of(V, M, K)
    assert grid is not None and (len(grid.x), len(grid.y)) == (8, 6)
    qx, qy, d = grid.fast_diagonalisation(c)
    b = np.random.default_rng(1).standard_normal(M.shape[0])
    expected = scipy.sparse.linalg.spsolve((M + c * K).tocsc(), b)
    g = b[grid.order].reshape(d.shape)
    x = np.empty_like(b)
    x[grid.order] = (qy @ ((qy.T @ g @ qx) / d) @ qx.T).ravel()
    np.testing.assert_allclose(x, expected, rtol=1e-10, atol=1e-13 * np.abs(expected).max())


def test_triangles_on_grid_nodes_are_not_a_q1_grid():
    """Triangles have grid nodes but other operators: refused when the matrices are given."""
    V, M, K = space_and_operators(mesh.CellType.triangle)
    assert grid_of(V) is not None
    assert grid_of(V, M, K) is None
