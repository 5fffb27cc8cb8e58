r"""Stimulus regions as cell-averaged indicators, the same on any number of ranks.

A region is a UFL predicate of the coordinates and some parameters (``fem.Constant``). Its
indicator is averaged over each cell by quadrature of degree ``degree`` and stored as a DG0
function (the space of the monodomain model's applied current):

.. math:: \chi_K = \frac{1}{|K|} \int_K \mathbb{1}[\text{predicate}(x)]\, dx .

Quadrature points lie strictly inside the cells, so a region whose edge runs along mesh nodes or
edges (the shock disk of radius 25 centred at (0, 25) passes through nodes of the 60 x 60 grid)
gives the same values whatever the partition; node coordinates differ by ~1e-17 between serial
and parallel meshes, so an indicator evaluated at nodes would not. The averaged indicator also
depends continuously on the region's parameters. The form is compiled once; each evaluation is
one vector assembly over the cells.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import ufl
from dolfinx import fem
from dolfinx import mesh as dmesh
from petsc4py import PETSc


class CellAverage:
    """``region(amplitude, *parameters)`` -> DG0 function ``amplitude x`` the cell averages of
    the indicator of ``predicate(x, *constants)`` (see the module docstring). Collective.

    ``predicate`` receives ``ufl.SpatialCoordinate`` and ``parameters`` constants and returns a
    UFL condition.
    """

    def __init__(self, mesh: dmesh.Mesh, predicate: Callable, parameters: int, degree: int):
        Q = fem.functionspace(mesh, ("DG", 0))
        self.constants = [fem.Constant(mesh, PETSc.ScalarType(0.0)) for _ in range(parameters)]
        indicator = ufl.conditional(
            predicate(ufl.SpatialCoordinate(mesh), *self.constants), 1.0, 0.0
        )
        v = ufl.TestFunction(Q)
        dx = ufl.dx(domain=mesh, metadata={"quadrature_degree": degree})
        self._form = fem.form(indicator * v * dx)
        self._n = Q.dofmap.index_map.size_local
        self._volume = fem.assemble_vector(fem.form(v * dx)).array[: self._n].copy()
        self.function = fem.Function(Q, name="region")

    def __call__(self, amplitude: float, *parameters: float) -> fem.Function:
        for constant, value in zip(self.constants, parameters, strict=True):
            constant.value = value
        b = fem.assemble_vector(self._form)
        self.function.x.array[: self._n] = amplitude * b.array[: self._n] / self._volume
        self.function.x.scatter_forward()
        return self.function


def rectangle_above(x, centre_x, half_width, bottom):
    """|x - centre_x| < half_width and y > bottom (the reset stimulus of the ATP task)."""
    return ufl.And(ufl.lt(abs(x[0] - centre_x), half_width), ufl.gt(x[1], bottom))


def disk(x, centre_x, centre_y, radius):
    """(x - centre_x)^2 + (y - centre_y)^2 < radius^2 (the ATP shock)."""
    return ufl.lt((x[0] - centre_x) ** 2 + (x[1] - centre_y) ** 2, radius**2)


def half_plane_gate(centre_x: float, slope: float) -> Callable[[np.ndarray], np.ndarray]:
    """w0(x) = min(-(x - centre_x) / slope, 1) for x < centre_x, else 0: a continuous function,
    so nodal evaluation is safe (report section 4.3.4)."""

    def w0(x: np.ndarray) -> np.ndarray:
        return np.clip(-(x[0] - centre_x) / slope, 0.0, 1.0)

    return w0
