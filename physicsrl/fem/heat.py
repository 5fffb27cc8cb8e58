r"""The heat equation as a reinforcement-learning environment (report section 4.2).

.. math::

    \partial_t u = \nabla^2 u + f \quad \text{in } \Omega \times (0, T], \qquad
    u = u_D \quad \text{on } \partial\Omega, \qquad u = u_0 \quad \text{at } t = 0 .

Implicit Euler with time step :math:`\Delta t`, in weak form: find :math:`u^{n+1} \in V`,
:math:`u^{n+1} = u_D` on :math:`\partial\Omega`, such that for all :math:`v \in V_0`

.. math::

    \int_\Omega u^{n+1} v + \Delta t\, \nabla u^{n+1} \cdot \nabla v \, dx
    = \int_\Omega (u^n + \Delta t f)\, v \, dx .

Units are those of the caller (the equation has unit diffusivity). Subclasses add the agent's
side (observations, actions, rewards); this class owns the simulation and exposes it through
``@parallel`` methods, so that the leader drives all ranks.

How well a mesh and ``dt`` resolve the solution (:func:`resolution`): a constant initial
value :math:`c + d` gives the solution from :math:`c` plus :math:`d\, z`, the transient

.. math::

    \partial_t z = \nabla^2 z, \qquad z = 0 \text{ on } \partial\Omega, \qquad z = 1
    \text{ at } t = 0 .

On the square :math:`[-a, a]^2` it separates, and its integral is

.. math::

    \int_\Omega z\, dx = S(t)^2, \qquad
    S(t) = \sum_{m \text{ odd}} \frac{16 a}{\pi^2 m^2}\, e^{-(m \pi / 2a)^2 t}

(:func:`transient_integral`). The scheme is linear, so the difference of two runs from
:math:`u_0 = 1` and :math:`u_0 = 0` is its :math:`z_h`, whatever :math:`u_D` and :math:`f`; its
integral against the exact one measures the error in space and time together.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import ufl
from dolfinx import fem, mesh
from mpi4py import MPI

from physicsrl.coordinated import Coordinated, Coordinator, parallel
from physicsrl.fem.errors import InvalidValue
from physicsrl.fem.integrals import WeightedIntegrals, form_rows, quadrant_weights
from physicsrl.fem.resolution import largest_cell_diameter
from physicsrl.fem.time_problem import TimeProblem
from physicsrl.fem.values import assign, positive


def default_heat_mesh(comm: MPI.Comm = MPI.COMM_WORLD) -> mesh.Mesh:
    """The square [-2, 2]^2 split into 50 x 50 x 2 triangles."""
    return mesh.create_rectangle(comm, [[-2.0, -2.0], [2.0, 2.0]], [50, 50], mesh.CellType.triangle)


class HeatEnvironment(Coordinated):
    """The heat equation on every rank, driven by the leader.

    Parameters
    ----------
    coordinator:
        The coordinator to register with (construct on every rank, in the same order).
    domain:
        The mesh (default: :func:`default_heat_mesh`).
    V:
        The function space (default: Lagrange degree 1 on ``domain``).
    dt:
        Time step, > 0.
    u0, u_D, f:
        Initial condition, boundary value and source: each a number, a callable ``f(x)`` with
        ``x`` of shape (3, n) returning shape (n,), a ``fem.Expression`` or a ``fem.Function``.
    petsc_options:
        Linear solver options (see :class:`TimeProblem`).
    namespace:
        The coordinator namespace (default: the next integer).

    Values passed to the ``@parallel`` setters from the leader are pickled to the other ranks
    (lambdas through cloudpickle); ``fem`` objects can be passed only on one rank or from
    inside another parallel method.
    """

    def __init__(
        self,
        coordinator: Coordinator,
        domain: mesh.Mesh | None = None,
        V: fem.FunctionSpace | None = None,
        dt: float = 0.01,
        u0=0.0,
        u_D=1.0,
        f=0.0,
        petsc_options: dict | None = None,
        namespace=None,
    ):
        self.register_coordinator(coordinator, namespace)
        if domain is None:
            domain = default_heat_mesh() if V is None else V.mesh
        self.domain = domain
        self.problem = TimeProblem(self.domain, V, petsc_options)
        V = self.V = self.problem.V
        self._u_D = fem.Function(V, name="u_D")
        self._f = fem.Function(V, name="f")
        assign(self._u_D, u_D, "u_D")
        assign(self._f, f, "f")

        tdim = self.domain.topology.dim
        self.domain.topology.create_connectivity(tdim - 1, tdim)
        facets = mesh.exterior_facet_indices(self.domain.topology)
        bc = fem.dirichletbc(self._u_D, fem.locate_dofs_topological(V, tdim - 1, facets))

        u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
        k = self.problem.dt
        self.problem.set_dt(dt)
        self.problem.set_bilinear_form(
            (u * v + k * ufl.inner(ufl.grad(u), ufl.grad(v))) * ufl.dx, [bc]
        )
        self.problem.set_linear_form((self.problem.u_n + k * self._f) * v * ufl.dx)
        self.problem.set_initial_condition(u0)
        self._quadrants = WeightedIntegrals(V, form_rows(V, quadrant_weights(self.domain)))

    # the state --------------------------------------------------------------------------
    def u_n(self) -> fem.Function:
        """The temperature now (this rank's part)."""
        return self.problem.u_n

    @property
    def t(self) -> float:
        """Time since the initial condition."""
        return self.problem.t

    # changing the problem ---------------------------------------------------------------
    @parallel
    def set_source(self, f) -> None:
        """Set the source term f; it acts from the next step on."""
        assign(self._f, f, "f")

    @parallel
    def set_boundary_value(self, u_D) -> None:
        """Set the Dirichlet value u_D; it acts from the next step on."""
        assign(self._u_D, u_D, "u_D")

    @parallel
    def set_initial_condition(self, u0) -> None:
        """Set u0; applied now if at t = 0 (e.g. inside :meth:`handle_reset`), else on reset."""
        self.problem.set_initial_condition(u0)

    # running ----------------------------------------------------------------------------
    @parallel
    def advance_time(self, T: float) -> None:
        """Advance T time units (a whole number of steps); raises ``SimulationDiverged``."""
        self.problem.solve(T)

    @parallel
    def reset(self) -> None:
        """Return to the initial condition at t = 0, then call :meth:`handle_reset`."""
        self.problem.reset()
        self.handle_reset()

    def handle_reset(self) -> None:
        """Override to customise resets (runs on every rank, inside :meth:`reset`).

        Draw random numbers with :func:`physicsrl.coordinated.random` / ``randint`` so that all
        ranks agree, and call e.g. :meth:`set_initial_condition`.
        """

    # observing --------------------------------------------------------------------------
    def compute_ufl_form(self, form: ufl.Form) -> float:
        """The value of a functional (a UFL form of rank 0) over the whole domain.

        Collective: call it on every rank (e.g. inside a ``@parallel`` method); every rank gets
        the global value. Compiles the form at each call: for repeated observations prefer
        :class:`WeightedIntegrals`.
        """
        local = fem.assemble_scalar(fem.form(form))
        return self.domain.comm.allreduce(local, op=MPI.SUM)

    @parallel
    def quadrant_integrals(self) -> np.ndarray:
        """Array (4,) of the integral of u over the quadrants around the origin, in the order
        (x<0, y<0), (x>0, y<0), (x<0, y>0), (x>0, y>0)."""
        return self._quadrants(self.problem.u_n)


MAX_TRANSIENT_ERROR = 0.05
"""Relative error of the transient's integral above which :class:`HeatResolution` warns."""


def transient_integral(t, extent: float, modes: int = 2000) -> np.ndarray:
    """The exact integral of the transient z (module docstring) over [-extent, extent]^2 at
    times ``t`` (shape (k,), >= 0), from the first ``modes`` odd terms of S(t) (at t = 0 they
    miss about 4 extent / (pi^2 modes) of S(0) = 2 extent; nothing measurable from t = 0.01)."""
    t = np.atleast_1d(np.asarray(t, dtype=float))
    if extent <= 0 or not (t >= 0).all():
        raise ValueError(f"need extent > 0 and times t >= 0, got extent {extent}, t {t.tolist()}")
    m = np.arange(1, 2 * modes, 2)[:, None]
    decay = np.exp(-((m * np.pi / (2 * extent)) ** 2) * t)
    return (16 * extent / (np.pi**2 * m**2) * decay).sum(axis=0) ** 2


@dataclass(frozen=True)
class HeatResolution:
    """A mesh and time step against the heat equation's transient: the largest cell diameter
    ``h``, ``dt``, the number of ``cells``, and the signed relative ``errors`` (shape (k,)) of
    the computed integral of the transient against :func:`transient_integral` at ``times``
    (shape (k,))."""

    cells: int
    h: float
    dt: float
    times: np.ndarray
    errors: np.ndarray

    @property
    def error(self) -> float:
        """The largest relative error in magnitude."""
        return float(np.abs(self.errors).max())

    @property
    def warning(self) -> str | None:
        """The one-line warning if :attr:`error` exceeds :data:`MAX_TRANSIENT_ERROR`."""
        if self.error <= MAX_TRANSIENT_ERROR:
            return None
        worst = float(self.errors[np.abs(self.errors).argmax()])
        return (
            f"the mesh and time step do not resolve the transient (its integral off by up to "
            f"{worst:+.2%}, above {MAX_TRANSIENT_ERROR:.0%}): refine env.dt or env.mesh.cells"
        )

    def __str__(self) -> str:
        worst = int(np.abs(self.errors).argmax())
        return (
            f"resolution: h = {self.h:.3g}, dt = {self.dt:.3g}: the integral of the transient at "
            f"t = {self.times[0]:.3g} to {self.times[-1]:.3g} is off the exact one by at most "
            f"{self.errors[worst]:+.2%} (at t = {self.times[worst]:.3g}; {self.cells} cells)"
        )


def resolution(simulator: HeatEnvironment, extent: float, times) -> HeatResolution:
    """The :class:`HeatResolution` of ``simulator``, whose mesh is the square
    [-extent, extent]^2, at ``times`` (ascending, > 0, whole numbers of its dt).

    Two runs of its own problem, from u0 = 1 and u0 = 0 (module docstring). Collective: call it
    on every rank, outside the coordinator's dispatch (at construction, say). It leaves the
    simulator at u0 = 0 and the last time: set the initial condition and reset afterwards.
    """
    problem, domain = simulator.problem, simulator.domain
    comm = domain.comm
    extent = positive("extent", extent)
    times = np.array(times, dtype=float, ndmin=1)
    if times.ndim != 1 or not times.size or not np.isfinite(times).all() or times[0] <= 0:
        raise InvalidValue(f"times must be finite times > 0, at least one, got {times.tolist()}")
    if np.any(np.diff(times) <= 0):
        raise InvalidValue(f"times must be ascending, got {times.tolist()}")
    x = domain.geometry.x[:, :2]
    bounds = np.concatenate([-x.min(axis=0, initial=np.inf), x.max(axis=0, initial=-np.inf)])
    comm.Allreduce(MPI.IN_PLACE, bounds, op=MPI.MAX)  # (-x_min, -y_min, x_max, y_max)
    if not np.allclose(bounds, extent, rtol=1e-12, atol=0):
        raise InvalidValue(f"extent: the mesh is not the square [-{extent}, {extent}]^2")
    integral = fem.form(problem.u_n * ufl.dx)
    runs = []
    for u0 in (1.0, 0.0):
        problem.set_initial_condition(u0)
        problem.reset()
        values = []
        for t in times:
            problem.solve(t - problem.t)
            values.append(comm.allreduce(fem.assemble_scalar(integral), op=MPI.SUM))
        runs.append(values)
    errors = np.subtract(*runs) / transient_integral(times, extent) - 1
    cells = domain.topology.index_map(domain.topology.dim).size_global
    dt = float(problem.dt.value)
    return HeatResolution(cells, largest_cell_diameter(domain), dt, times, errors)
