r"""Integrals of a finite element function against many fixed weights, in one pass.

For weights :math:`g_1, \dots, g_K` and :math:`u_h = \sum_i u_i \phi_i \in V`,

.. math::

    I_k = \int_\Omega g_k\, u_h \, dx = \sum_i u_i \int_\Omega g_k \phi_i \, dx = (B u)_k,
    \qquad B_{ki} = \int_\Omega g_k \phi_i \, dx .

The rows of :math:`B` are assembled once (each weight a UFL expression, integrated by
quadrature); afterwards every evaluation is one dense product with the owned entries of
:math:`u` and one ``Allreduce`` of :math:`K` numbers, the same on every rank count.

Weights that are indicators of regions should be UFL conditionals on
:func:`ufl.SpatialCoordinate`: they are evaluated at quadrature points, which lie inside the
cells, so a region whose edge runs along mesh nodes selects the same cells on any number of
ranks (node coordinates differ by ~1e-17 between serial and parallel meshes; an indicator
interpolated at the nodes would not).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import ufl
from dolfinx import fem, la
from mpi4py import MPI

from physicsrl.fem.errors import InvalidValue


class WeightedIntegrals:
    """``integrals(u)`` -> array (K,) of :math:`\\int_\\Omega g_k u \\, dx` (see module docstring).

    Parameters
    ----------
    V:
        The function space of the integrands ``u`` (scalar).
    weights:
        K UFL expressions :math:`g_k` on ``V``'s mesh.
    quadrature_degree:
        Degree of the quadrature of :math:`g_k \\phi_i` (default: UFL's estimate).

    Memory: K x (owned dofs) doubles per rank.
    """

    def __init__(
        self, V: fem.FunctionSpace, weights: Sequence, quadrature_degree: int | None = None
    ):
        self.V = V
        self._n = V.dofmap.index_map.size_local * V.dofmap.bs
        metadata = {} if quadrature_degree is None else {"quadrature_degree": quadrature_degree}
        dx = ufl.dx(domain=V.mesh, metadata=metadata)
        v = ufl.TestFunction(V)
        self._B = np.empty((len(weights), self._n))
        for k, g in enumerate(weights):
            b = fem.assemble_vector(fem.form(g * v * dx))
            b.scatter_reverse(la.InsertMode.add)
            self._B[k] = b.array[: self._n]
        self._local = np.empty(len(weights))

    def __call__(self, u: fem.Function) -> np.ndarray:
        """The K integrals of ``u`` (a function on ``V``), the same array on every rank.

        Collective.
        """
        if u.function_space != self.V:
            raise InvalidValue("u: the function does not live on the weights' function space")
        np.matmul(self._B, u.x.array[: self._n], out=self._local)
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
