r"""Fused integrals of a finite element function against fixed weights: one reduction per use.

For weights :math:`g_1, \dots, g_K` and :math:`u_h = \sum_i u_i \phi_i`,

.. math::

    I_k = \int_\Omega g_k\, u_h \, dx = (B u)_k, \qquad B_{ki} = \int_\Omega g_k \phi_i \, dx .

The rows of :math:`B` (owned dofs of this rank) are computed once, by one of two methods:

- :func:`form_rows`: :math:`g_k` a UFL expression, integrated by the mesh's quadrature. Right
  for weights that are smooth on the scale of the cells, or indicators of regions bounded by
  mesh lines (quadrature points lie inside the cells, so the same cells are selected on any
  number of ranks).
- :func:`point_rows`: :math:`B_{ki} = \sum_p \omega_{kp} \phi_i(x_{kp})` for quadrature points
  :math:`x_{kp}` and weights :math:`\omega_{kp}` chosen by the caller (e.g. a polar rule around
  an electrode). The basis functions are tabulated exactly at the points, so the result does not
  depend on where the mesh nodes are; right for kernels narrower than a cell. Each point is
  counted once, on the lowest rank that owns a cell containing it.

:class:`WeightedIntegrals` stacks rows of both kinds: every evaluation is one dense product
with the owned entries of :math:`u` and one ``Allreduce`` of K numbers, identical up to rounding
on any number of ranks. Rows may weigh different functions on the same space (``variables``:
row k integrates the function ``variables[k]`` of the call, e.g. u and the gate w of a
two-variable model), still with one ``Allreduce``.

Weights that are indicators of regions should be UFL conditionals on
:func:`ufl.SpatialCoordinate` (:func:`quadrant_weights`): evaluated at quadrature points inside
the cells, they select the same cells on any number of ranks, whereas node coordinates differ by
~1e-17 between serial and parallel meshes.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import ufl
from dolfinx import fem, geometry, la
from mpi4py import MPI

from physicsrl.fem.errors import InvalidValue


def _owned(V: fem.FunctionSpace) -> int:
    return V.dofmap.index_map.size_local * V.dofmap.bs


def form_rows(
    V: fem.FunctionSpace, weights: Sequence, quadrature_degree: int | None = None
) -> np.ndarray:
    """Array (K, owned dofs): :math:`\\int g_k \\phi_i dx` for UFL expressions ``weights``.

    Collective. ``quadrature_degree`` defaults to UFL's estimate.
    """
    metadata = {} if quadrature_degree is None else {"quadrature_degree": quadrature_degree}
    dx = ufl.dx(domain=V.mesh, metadata=metadata)
    v = ufl.TestFunction(V)
    rows = np.empty((len(weights), _owned(V)))
    for k, g in enumerate(weights):
        b = fem.assemble_vector(fem.form(g * v * dx))
        b.scatter_reverse(la.InsertMode.add)
        rows[k] = b.array[: rows.shape[1]]
    return rows


def point_rows(V: fem.FunctionSpace, points: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Array (K, owned dofs): :math:`\\sum_p \\omega_{kp} \\phi_i(x_{kp})`.

    ``points`` has shape (K, P, 2 or 3) and ``weights`` shape (K, P), the same on every rank.
    Points outside the mesh contribute nothing; ValueError (on every rank) if all points of a
    row are outside. Scalar Lagrange spaces. Collective.
    """
    mesh = V.mesh
    K, P = weights.shape
    xyz = np.zeros((K * P, 3))
    xyz[:, : points.shape[-1]] = points.reshape(K * P, -1)
    tdim = mesh.topology.dim
    owned_cells = np.arange(mesh.topology.index_map(tdim).size_local, dtype=np.int32)
    tree = geometry.bb_tree(mesh, tdim, entities=owned_cells)
    colliding = geometry.compute_colliding_cells(
        mesh, geometry.compute_collisions_points(tree, xyz), xyz
    )
    cell = np.full(K * P, -1, dtype=np.int64)
    for p in range(K * P):
        links = colliding.links(p)
        if len(links):
            cell[p] = links[0]
    # Each point belongs to the lowest rank that found it.
    comm = mesh.comm
    here = np.where(cell >= 0, comm.rank, comm.size)
    first = np.empty_like(here)
    comm.Allreduce(here, first, op=MPI.MIN)
    cell[first != comm.rank] = -1
    outside = np.flatnonzero((first == comm.size).reshape(K, P).all(axis=1))
    if len(outside):
        raise ValueError(f"points: every point of row {outside[0]} lies outside the mesh")

    cmap = mesh.geometry.cmaps[0]
    element = V.element.basix_element
    gdofs = (
        mesh.geometry.dofmaps(0) if callable(mesh.geometry.dofmaps) else mesh.geometry.dofmaps[0]
    )
    work = fem.Function(V)
    result = np.empty((K, _owned(V)))
    for k in range(K):
        work.x.array[:] = 0.0
        mine = np.flatnonzero(cell[k * P : (k + 1) * P] >= 0)
        cells = cell[k * P + mine]
        for c in np.unique(cells):
            at = mine[cells == c]
            reference = cmap.pull_back(
                xyz[k * P + at, : mesh.geometry.dim], mesh.geometry.x[gdofs[c], : mesh.geometry.dim]
            )
            phi = element.tabulate(0, reference)[0, :, :, 0]  # (points, basis functions)
            np.add.at(work.x.array, V.dofmap.cell_dofs(c), weights[k, at] @ phi)
        work.x.scatter_reverse(la.InsertMode.add)
        result[k] = work.x.array[: result.shape[1]]
    return result


class WeightedIntegrals:
    """``integrals(u, ...)`` -> array (K,) of :math:`(B v_k)_k` for fixed rows :math:`B`, where
    :math:`v_k` is the function ``variables[k]`` of the call (default: every row the first).

    ``rows`` has shape (K, owned dofs of ``V``), e.g. stacked :func:`form_rows` and
    :func:`point_rows`. Memory: K x (owned dofs) doubles per rank.
    """

    def __init__(self, V: fem.FunctionSpace, rows: np.ndarray, variables: Sequence[int] = ()):
        self.V = V
        rows = np.ascontiguousarray(rows, dtype=float)
        if rows.ndim != 2 or rows.shape[1] != _owned(V):
            raise InvalidValue(f"rows: expected shape (K, {_owned(V)}), got {rows.shape}")
        variables = np.asarray(variables if len(variables) else [0] * len(rows), dtype=int)
        if variables.shape != (len(rows),) or variables.min(initial=0) < 0:
            raise InvalidValue(f"variables: expected {len(rows)} indices >= 0, got {variables}")
        self.owned = rows.shape[1]
        self.functions = int(variables.max(initial=0)) + 1
        # (function, its rows' places, their weights): one product per function
        self.blocks = [
            (
                j,
                np.flatnonzero(variables == j),
                rows if self.functions == 1 else rows[variables == j],
            )
            for j in range(self.functions)
        ]
        self._local = np.empty(len(rows))

    def __call__(self, *functions: fem.Function) -> np.ndarray:
        """The K integrals of ``functions`` (each on ``V``), the same array on every rank.

        Collective: one product per function and one ``Allreduce`` of K doubles.
        """
        if len(functions) < self.functions:
            raise InvalidValue(f"expected {self.functions} functions, got {len(functions)}")
        if any(f.function_space != self.V for f in functions):
            raise InvalidValue("functions: one does not live on the weights' function space")
        for j, places, rows in self.blocks:
            self._local[places] = rows @ functions[j].x.array[: self.owned]
        result = np.empty_like(self._local)
        self.V.mesh.comm.Allreduce(self._local, result, op=MPI.SUM)
        return result


def quadrant_weights(mesh, centre: tuple[float, float] = (0.0, 0.0)) -> list:
    """Indicators of the 4 quadrants around ``centre``, in the order
    (x<0, y<0), (x>0, y<0), (x<0, y>0), (x>0, y>0) relative to ``centre``."""
    x = ufl.SpatialCoordinate(mesh)
    left, below = ufl.lt(x[0], centre[0]), ufl.lt(x[1], centre[1])
    right, above = ufl.Not(left), ufl.Not(below)
    return [
        ufl.conditional(ufl.And(horizontal, vertical), 1.0, 0.0)
        for vertical in (below, above)
        for horizontal in (left, right)
    ]
