r"""How well a mesh resolves the Mitchell-Schaeffer front, and what that costs in accuracy.

The excitation front of the monodomain model is about :math:`\sqrt{D \tau_\mathrm{in}}` wide
(0.062 mm for the report's D = 0.013 mm^2/ms, :math:`\tau_\mathrm{in}` = 0.3 ms). The planar
conduction velocity (CV) a scheme computes depends on h against that width;
``benchmarks/ms_cv.py`` measures its relative error against the converged CV for both schemes
and both cell types, each in the worse of the directions it measures (:func:`front_strip`:
along the cells' edges and, on triangles, along their hypotenuses), at each time step of
:data:`TABLE_DTS`, and writes the table :data:`TABLE` (``cv_error.csv`` beside this module, the
one place the numbers live). :func:`resolution` interpolates it, linearly in
:math:`\log(h / \text{width})` and then linearly in dt (both schemes' errors are about first
order in dt); a step shorter than the table's shortest reads that step's rows (the error is
then theirs or smaller). :func:`report` prints it and warns when the error is above
:data:`MAX_CV_ERROR`, or when the table does not cover the mesh and step: h / width beyond its
coarsest row (the error is then that row's or worse), a cell type it has no rows for, or a
step longer than its longest (its time-step error adds to the table's). The heat equation's
counterpart is :class:`physicsrl.fem.heat.HeatResolution`; :func:`report` prints either.
"""

from __future__ import annotations

import csv
import functools
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import basix.ufl
import numpy as np
from dolfinx import mesh
from mpi4py import MPI

MAX_CV_ERROR = 0.05
"""Expected relative planar CV error above which :func:`report` warns."""

TABLE_DTS = (0.0075, 0.015, 0.03)
"""The time steps of :data:`TABLE`'s measurements, ascending (the longest: the tasks' dt)."""

TABLE = Path(__file__).with_name("cv_error.csv")
"""Columns ``scheme``, ``cell_type``, ``dt``, ``h_over_width``, ``cv_error`` (relative, signed:
-1 when no wave propagates), written by ``benchmarks/ms_cv.py``."""


@dataclass(frozen=True)
class Resolution:
    """A mesh against the front: largest cell diameter ``h``, front width
    :math:`\\sqrt{D \\tau_\\mathrm{in}}`, the time step ``dt``, and the expected relative planar
    CV error of ``scheme`` from :data:`TABLE`'s rows of the cell type (clamped to them);
    ``uncovered`` names what of this mesh and step the table does not cover (module
    docstring), empty if nothing."""

    scheme: str
    cell_type: str
    cells: int
    h: float
    dt: float
    front_width: float
    cv_error: float
    uncovered: tuple[str, ...] = ()
    beyond: bool = False  # h / width above the table's coarsest row

    @property
    def ratio(self) -> float:
        return self.h / self.front_width

    @property
    def mesh(self) -> str:
        return f"{self.cells} cells, h = {self.h:.4g}"

    @property
    def expected(self) -> str:
        """The expected CV error in words: the table's, or its coarsest row's "or worse"."""
        return f"{self.cv_error:+.1%}{' or worse' if self.beyond else ''}"

    @property
    def warning(self) -> str | None:
        """The one-line warning if the expected CV error exceeds :data:`MAX_CV_ERROR` or the
        table does not cover this mesh and step."""
        if abs(self.cv_error) > MAX_CV_ERROR:
            return (
                f"the mesh does not resolve the front (h/width = {self.ratio:.3g}, expected "
                f"planar CV error {self.expected}, above {MAX_CV_ERROR:.0%}{self._not_covered}):"
                " the dynamics are numerical; refine the mesh, or set "
                "env.model.warn_resolution=false"
            )
        if self.uncovered:
            return (
                f"the table of planar CV errors does not cover this mesh and step "
                f"({'; '.join(self.uncovered)}): the error can exceed its {self.expected}; "
                "check the front speed, or set env.model.warn_resolution=false"
            )
        return None

    @property
    def _not_covered(self) -> str:
        return f"; not in the table: {'; '.join(self.uncovered)}" if self.uncovered else ""

    def __str__(self) -> str:
        return (
            f"resolution: h = {self.h:.3g}, front width sqrt(D tau_in) = {self.front_width:.3g},"
            f" h/width = {self.ratio:.3g}: expected planar CV error {self.expected}"
            f" ({self.scheme} scheme, dt = {self.dt:g}, {self.cells} {self.cell_type} cells"
            f"{self._not_covered})"
        )


@functools.cache  # read once per process: every simulator's construction asks
def cv_table(
    scheme: str, cell_type: str = "quadrilateral", dt: float = TABLE_DTS[-1]
) -> tuple[np.ndarray, np.ndarray]:
    """(h / width ascending, CV error) of ``scheme`` on ``cell_type`` at the time step ``dt``
    (one of :data:`TABLE_DTS`) from :data:`TABLE` (empty arrays for a cell type it has no rows
    for; read-only)."""
    with TABLE.open() as table:
        rows = [
            row
            for row in csv.DictReader(table)
            if (row["scheme"], row["cell_type"]) == (scheme, cell_type)
            and math.isclose(float(row["dt"]), dt)
        ]
    rows.sort(key=lambda row: float(row["h_over_width"]))
    ratios = np.array([float(row["h_over_width"]) for row in rows])
    errors = np.array([float(row["cv_error"]) for row in rows])
    ratios.flags.writeable = errors.flags.writeable = False  # shared by the cache's callers
    return ratios, errors


def expected_cv_error(
    scheme: str, ratio: float, cell_type: str = "quadrilateral", dt: float = TABLE_DTS[-1]
) -> float:
    """The table's CV error of ``scheme`` on ``cell_type`` at h / width = ``ratio`` and the
    time step ``dt`` (interpolated in both, clamped to the table's rows)."""
    steps, at_each_step = [], []
    for step in TABLE_DTS:
        ratios, errors = cv_table(scheme, cell_type, step)
        if len(ratios):
            steps.append(step)
            at_each_step.append(np.interp(math.log(ratio), np.log(ratios), errors))
    return float(np.interp(dt, steps, at_each_step))


def largest_cell_diameter(domain) -> float:
    """The largest distance between two nodes of a cell, over all ranks (collective)."""
    x = domain.geometry.x
    dofmap = domain.geometry.dofmaps[0][: domain.topology.index_map(domain.topology.dim).size_local]
    nodes = x[dofmap]  # (cells, nodes per cell, 3)
    h = 0.0
    for a in range(nodes.shape[1]):
        for b in range(a + 1, nodes.shape[1]):
            h = max(h, float(np.linalg.norm(nodes[:, a] - nodes[:, b], axis=1).max(initial=0)))
    return domain.comm.allreduce(h, op=MPI.MAX)


def resolution(domain, D: float, tau_in: float, scheme: str, dt: float) -> Resolution:
    """The :class:`Resolution` of ``domain`` for the model's D, tau_in and time step
    (collective)."""
    h = largest_cell_diameter(domain)
    width = math.sqrt(D * tau_in)
    cells = domain.topology.index_map(domain.topology.dim).size_global
    cell_type = domain.topology.cell_type.name
    rows = cell_type if len(cv_table(scheme, cell_type)[0]) else "quadrilateral"
    ratios, _ = cv_table(scheme, rows)
    beyond = bool(h / width > ratios[-1])
    uncovered = [f"h/width above its coarsest {ratios[-1]:.3g}"] if beyond else []
    if rows != cell_type:
        uncovered.append(f"{cell_type} cells, it has quadrilaterals and triangles")
    if dt > TABLE_DTS[-1] * (1 + 1e-9):
        uncovered.append(f"dt = {dt:g}, its longest is {TABLE_DTS[-1]:g}")
    error = expected_cv_error(scheme, h / width, rows, dt)
    return Resolution(scheme, cell_type, cells, h, dt, width, error, tuple(uncovered), beyond)


class ResolutionWarning(UserWarning):
    """The mesh does not resolve the solution: its expected error is above the bound of the
    model's resolution class."""


def report(resolution, warn: bool = True) -> None:
    """Print ``resolution`` (a :class:`Resolution`, or any object with ``__str__`` and a
    ``warning`` that is None or one line) on rank 0 of the job (not on the leaders of other
    environment groups: they simulate the same mesh), and a :class:`ResolutionWarning` if it
    has a warning, unless ``warn`` is false (Python's default filter shows each distinct
    warning once per process)."""
    if MPI.COMM_WORLD.rank != 0:
        return
    print(resolution, flush=True)
    if warn and resolution.warning:
        warnings.warn(resolution.warning, ResolutionWarning, stacklevel=2)


def planar_front_speed(
    h: float,
    dt: float,
    length: float = 4.0,
    T: float = 20.0,
    t_fit: float | None = 6.0,
    cell_type: str = "quadrilateral",
    along: str = "edges",
    **model,
) -> float:
    """Speed of a planar front of :class:`~physicsrl.fem.MonodomainMitchellSchaeffer`
    (``model``: its keyword arguments) along a strip [0, length] of the cells of a grid of
    squares of side h (:func:`front_strip`: ``cell_type``, ``along``), on this process,
    started by u = 1 on x < max(0.3, 3 h): the slope of the front position (where u = 0.5,
    linear interpolation along the strip's wall y = 0) against time over [t_fit, T]
    (``t_fit=None``: the later two thirds of the samples), sampled every 0.5 time units (every
    dt if longer) until the front passes 80 % of the strip; 0 if the front dies (no wave
    propagates)."""
    from physicsrl.coordinated import Coordinator
    from physicsrl.fem.monodomain import MonodomainMitchellSchaeffer

    domain = front_strip(h, length, cell_type, along)
    start = max(0.3, 3 * h)
    ms = MonodomainMitchellSchaeffer(
        Coordinator(MPI.COMM_SELF),
        domain,
        u0=lambda x: np.where(x[0] < start, 1.0, 0.0),
        w0=1.0,
        dt=dt,
        **model,
    )
    xy = ms.V.tabulate_dof_coordinates()
    bottom = np.nonzero(np.isclose(xy[:, 1], 0.0))[0]
    bottom = bottom[np.argsort(xy[bottom, 0])]
    x = xy[bottom, 0]
    times, positions = [], []
    with ms.coordinator:
        while ms.t < T - 1e-9:
            ms.advance_time(max(1, round(0.5 / dt)) * dt)
            u = ms.u_n().x.array[bottom]
            excited = np.nonzero(u > 0.5)[0]
            if excited.size == 0:
                return 0.0
            i = excited.max()
            if x[i] > 0.8 * length:
                break
            times.append(ms.t)
            positions.append(x[i] + (u[i] - 0.5) / (u[i] - u[i + 1]) * (x[i + 1] - x[i]))
    times, positions = np.array(times), np.array(positions)
    if t_fit is None:
        t_fit = times[0] + (times[-1] - times[0]) / 3
    fit = times >= t_fit
    return float(np.polyfit(times[fit], positions[fit], 1)[0])


def front_strip(h: float, length: float, cell_type: str, along: str = "edges") -> mesh.Mesh:
    """A strip along x, [0, length] long, of the cells of a grid of squares of side h (cell
    diameter sqrt(2) h; triangles: each square cut along a diagonal), laid so that a front along
    x runs ``along`` the cells' ``"edges"`` (1 x n squares) or, for triangles, their
    ``"hypotenuses"`` (a row of alternately upward and downward right triangles, sqrt(2) h long
    and h / sqrt(2) high, between two lines of hypotenuses).

    Where the strip's walls are mirror lines of the grid its planar front is the grid's:
    quadrilaterals, triangles along their hypotenuses, and, with the explicit scheme's lumped
    mass, triangles along their edges. With the implicit scheme's consistent mass a row of
    triangles along its edges is slower than the grid (+4.3 % against +4.9 % at h = 0.2), but
    there the hypotenuses' error is the larger down to h = 0.1, and both are below 0.5 % on
    finer grids."""
    if cell_type not in ("quadrilateral", "triangle"):
        raise ValueError(f"cell_type must be quadrilateral or triangle, got {cell_type!r}")
    if along == "edges":
        n, cells = round(length / h), getattr(mesh.CellType, cell_type)
        return mesh.create_rectangle(MPI.COMM_SELF, [[0, 0], [length, h]], [n, 1], cells)
    if (cell_type, along) != ("triangle", "hypotenuses"):
        raise ValueError(f"along must be 'edges', or 'hypotenuses' for triangles, got {along!r}")
    base, height = math.sqrt(2) * h, h / math.sqrt(2)
    n = round(length / base)
    bottom = np.column_stack([base * np.arange(n + 1), np.zeros(n + 1)])
    top = np.column_stack([base * (np.arange(n) + 0.5), np.full(n, height)])
    k = np.arange(n)
    up = np.column_stack([k, k + 1, n + 1 + k])
    down = np.column_stack([k[:-1] + 1, n + 2 + k[:-1], n + 1 + k[:-1]])
    element = basix.ufl.element("Lagrange", "triangle", 1, shape=(2,))
    cells = np.vstack([up, down]).astype(np.int64)
    return mesh.create_mesh(MPI.COMM_SELF, cells, element, np.vstack([bottom, top]))
