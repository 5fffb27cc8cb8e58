r"""A linear PDE discretised in time, built piece by piece and changeable between steps.

Report section 4.1. A one-step scheme in weak form: given :math:`u^n`, find
:math:`u^{n+1} \in V` with :math:`u^{n+1} = g` on the Dirichlet boundary and

.. math::

    a(u^{n+1}, v) = L(v; u^n) \qquad \forall v \in V_0,

where the bilinear form :math:`a` and the linear form :math:`L` may use the time step
:attr:`TimeProblem.dt` (a :class:`dolfinx.fem.Constant`) and the current solution
:attr:`TimeProblem.u_n`. For implicit Euler on :math:`\partial_t u = \nabla^2 u + f`, say::

    problem = TimeProblem(mesh)
    u, v = ufl.TrialFunction(problem.V), ufl.TestFunction(problem.V)
    dt = problem.dt
    problem.set_dt(0.01)
    problem.set_bilinear_form((u * v + dt * ufl.inner(ufl.grad(u), ufl.grad(v))) * ufl.dx, bcs)
    problem.set_linear_form((problem.u_n + dt * f) * v * ufl.dx)
    problem.set_initial_condition(lambda x: x[0])
    problem.solve(1.0)  # 100 steps

Each step assembles the vector of :math:`L` (or calls the kernel set by
:meth:`TimeProblem.set_rhs`; with lifting of the boundary conditions), solves
:math:`A u^{n+1} = b` into ``u_n`` itself (the old values are the initial guess of the Krylov
solver) and updates the ghost entries. The forms are compiled once by their setters; the matrix
is assembled before the first step and again only after the bilinear form, the boundary
conditions or ``dt`` changed. Every setter may be called between steps and takes effect on the
next one.

Solver: PETSc options (a dict, e.g. ``{"ksp_type": "preonly", "pc_type": "lu"}``) update the
default :data:`DEFAULT_PETSC_OPTIONS`, conjugate gradients with an incomplete Cholesky
preconditioner (block Jacobi with one block per rank in parallel), warm-started. An option
that PETSc rejects is refused at construction, one that no part of the solver reads (a
misspelt key) when the solver is first set up, before the first step: :class:`InvalidValue`.
"""

from __future__ import annotations

import itertools
import math
import time

import dolfinx.fem.petsc
import numpy as np
import ufl
from dolfinx import fem, la
from mpi4py import MPI
from petsc4py import PETSc

from physicsrl.fem.errors import InvalidValue, SimulationDiverged
from physicsrl.fem.values import assign, nonnegative, positive

DEFAULT_PETSC_OPTIONS = {
    "ksp_type": "cg",
    "pc_type": "bjacobi",
    "sub_pc_type": "icc",
    "ksp_rtol": 1e-10,
}
"""CG + block Jacobi with ICC(0) per rank (on one rank plain ICC(0)); warm-started from u^n,
the relative tolerance is on the preconditioned residual and ``||b||``. The Mitchell-Schaeffer
model replaces the preconditioner by Jacobi on more than one rank
(:data:`physicsrl.fem.monodomain.PARALLEL_PETSC_OPTIONS`). Chosen by measurement: see
``benchmarks/README.md``, "Choice of the linear solver"."""

_prefixes = itertools.count()


class TimeProblem:
    """Builder and time stepper of a linear one-step scheme (see the module docstring).

    Parameters
    ----------
    mesh:
        The mesh; the only part that cannot change later.
    V:
        The function space of the unknown (default: Lagrange degree 1 on ``mesh``).
    petsc_options:
        PETSc options of the linear solver, updating :data:`DEFAULT_PETSC_OPTIONS` (keys
        without the leading dash; checked as the module docstring says).
    Attributes
    ----------
    V, u_n, dt:
        The space, the current solution (a ``fem.Function``) and the time step (a
        ``fem.Constant``), to be used in the forms.
    t:
        Time since the initial condition.
    timings:
        Seconds spent assembling right-hand sides (``"rhs"``) and solving (``"solve"``).
    """

    def __init__(
        self,
        mesh,
        V: fem.FunctionSpace | None = None,
        petsc_options: dict | None = None,
    ):
        self.mesh = mesh
        self.V = fem.functionspace(mesh, ("Lagrange", 1)) if V is None else V
        if self.V.mesh is not mesh:
            raise InvalidValue("V: the function space lives on another mesh")
        self.u_n = fem.Function(self.V, name="u")
        self.dt = fem.Constant(mesh, PETSc.ScalarType(0.0))
        self.t = 0.0
        self.timings = {"rhs": 0.0, "solve": 0.0}
        self._comm = mesh.comm
        self._owned = self.V.dofmap.index_map.size_local * self.V.dofmap.bs
        self._initial = fem.Function(self.V)  # the initial condition's values
        self._started = False  # a step was taken since construction or the last reset
        self._a: fem.Form | None = None
        self._L: fem.Form | None = None
        self._rhs = None  # a callable filling the local vector instead of assembling _L
        self._bcs: list[fem.DirichletBC] = []
        self._A: PETSc.Mat | None = None
        self._A_stale = True
        self._b = fem.create_vector(self.V)  # la.Vector; its PETSc view is passed to the solver
        # Views cached once: the properties build a new wrapper per access (microseconds each,
        # which add up at a step of a fraction of a millisecond).
        self._b_array, self._b_petsc = self._b.array, self._b.petsc_vec
        self._u_petsc = self.u_n.x.petsc_vec
        self._dt_value = self.dt._cpp_object.value  # 0-d view of the constant's storage
        self._ksp = PETSc.KSP().create(mesh.comm)
        defaults = dict(DEFAULT_PETSC_OPTIONS)
        if mesh.comm.size == 1:  # ICC itself, without the one-block block-Jacobi wrapper
            defaults["pc_type"] = defaults.pop("sub_pc_type")
        self._options = {**defaults, **(petsc_options or {})}
        self._unread = set(petsc_options or ())  # the caller's options no solver part read yet
        self._ksp.setOptionsPrefix(f"physicsrl_time_problem_{next(_prefixes)}_")
        try:
            self._with_options(self._ksp.setFromOptions)
        except PETSc.Error as error:
            raise InvalidValue(
                f"petsc_options: PETSc refused {self._options} (error code {error.ierr})"
            ) from None
        if self._ksp.getType() != PETSc.KSP.Type.PREONLY:
            self._ksp.setInitialGuessNonzero(True)

    def _with_options(self, action) -> None:
        """Run ``action`` with this problem's options in PETSc's database, under its prefix.

        PETSc reads them in two places: the solver's types and tolerances when it is
        configured, the inner solvers' (``sub_pc_type`` of block Jacobi, factor packages) when
        it is set up with its matrix. Both run here; the caller's options that were read are
        struck from :attr:`_unread`.
        """
        database, prefix = PETSc.Options(), self._ksp.getOptionsPrefix()
        for key, value in self._options.items():
            database[prefix + key] = value
        try:
            action()
            self._unread -= {key for key in self._unread if database.used(prefix + key)}
        finally:
            for key in self._options:
                database.delValue(prefix + key)

    # setters ----------------------------------------------------------------------------
    def set_dt(self, dt: float) -> None:
        """Set the time step (> 0); the matrix is re-assembled before the next step."""
        self.dt.value = positive("dt", dt)
        self._A_stale = True

    def set_bilinear_form(self, a: ufl.Form, bcs: list[fem.DirichletBC] = ()) -> None:
        """Set :math:`a(u, v)` (trial and test functions on ``V``) and its Dirichlet conditions.

        The conditions' values may change between steps (they are read at every step); their
        dofs may not without calling this again.
        """
        if len(a.arguments()) != 2 or any(
            arg.ufl_function_space() != self.V for arg in a.arguments()
        ):
            raise InvalidValue("a: expected a bilinear form with trial and test functions on V")
        self._a = fem.form(a)
        self._bcs = list(bcs)
        self._A_stale = True

    def set_linear_form(self, L: ufl.Form) -> None:
        """Set :math:`L(v)` (test function on ``V``); it is assembled at every step."""
        if len(L.arguments()) != 1 or L.arguments()[0].ufl_function_space() != self.V:
            raise InvalidValue("L: expected a linear form with a test function on V")
        self._L = fem.form(L)
        self._rhs = None

    def set_rhs(self, rhs) -> None:
        """Set a callable ``rhs(b)`` that writes the vector of :math:`L` into ``b``, this rank's
        local array (owned then ghost entries; every entry to be written): the contributions of
        the cells this rank owns, as DOLFINx's assembler computes them. Ghost entries are then
        added to their owners. An alternative to :meth:`set_linear_form` (the later call wins)
        for a right-hand side computed without a UFL form, e.g. by
        :class:`physicsrl.fem.quadrature.CellQuadrature`.
        """
        if not callable(rhs):
            raise InvalidValue("rhs: expected a callable rhs(b)")
        self._rhs = rhs
        self._L = None

    def set_initial_condition(self, value, name: str = "u0") -> None:
        """Set the initial condition: a number, callable, ``fem.Expression`` or ``fem.Function``.

        It is evaluated now and applied to ``u_n`` at once if no step was taken since
        construction or the last :meth:`reset`, otherwise at the next reset. ``name`` names
        the value in error messages. Collective.
        """
        assign(self._initial, value, name)
        if not self._started:
            self.u_n.x.array[:] = self._initial.x.array

    # stepping ---------------------------------------------------------------------------
    @property
    def started(self) -> bool:
        """Whether a step was taken since construction or the last :meth:`reset`."""
        return self._started

    def reset(self) -> None:
        """Return to the initial condition at t = 0."""
        self.u_n.x.array[:] = self._initial.x.array
        self.t = 0.0
        self._started = False

    def steps(self, T: float) -> int:
        """The number of steps of ``dt`` in ``T`` time units; error unless it is an integer."""
        dt = float(self._dt_value)
        if dt <= 0:
            raise InvalidValue("dt: call set_dt before solving")
        n = round(nonnegative("T", T) / dt)
        if abs(n * dt - T) > 1e-9 * max(T, dt):
            raise InvalidValue(f"T = {T!r} is not a whole number of time steps dt = {dt}")
        return n

    def solve(self, T: float) -> None:
        """Advance ``T`` time units, ``round(T / dt)`` steps. Collective.

        Raises :class:`SimulationDiverged` on every rank if the solution is not finite
        afterwards or the linear solver failed.
        """
        for _ in range(self.steps(T)):
            self.step()
        self.check_finite()

    def step(self) -> None:
        """Advance one time step of ``dt``. Collective."""
        if self._a is None or (self._L is None and self._rhs is None):
            raise InvalidValue("set the bilinear and linear forms before solving")
        start = time.perf_counter()
        if self._A_stale:
            self._assemble_matrix()
        b = self._b_array
        if self._rhs is not None:
            self._rhs(b)
        else:
            b[:] = 0.0
            fem.assemble_vector(b, self._L)
        if self._bcs:
            fem.apply_lifting(b, [self._a], [self._bcs])
        self._b.scatter_reverse(la.InsertMode.add)
        for bc in self._bcs:
            bc.set(b)
        middle = time.perf_counter()
        self._ksp.solve(self._b_petsc, self._u_petsc)
        self.u_n.x.scatter_forward()
        end = time.perf_counter()
        timings = self.timings
        timings["rhs"] += middle - start
        timings["solve"] += end - middle
        self.t += float(self._dt_value)
        self._started = True
        reason = self._ksp.getConvergedReason()  # the same on every rank
        if reason < 0:
            raise SimulationDiverged(
                f"the linear solver failed at t = {self.t:g} (reason {reason})"
            )

    def record_steps(self, steps: int) -> None:
        """Count ``steps`` steps of ``dt`` taken by a caller that updated ``u_n`` itself (an
        explicit scheme, which needs no linear solve)."""
        self.t += steps * float(self._dt_value)
        self._started = self._started or steps > 0

    def check_finite(self) -> None:
        """Raise :class:`SimulationDiverged` on every rank unless ``u_n`` is finite (collective)."""
        owned = self.u_n.x.array[: self._owned]
        # The sum is finite iff every entry is, unless it overflows: then check entry-wise.
        ok = math.isfinite(float(np.add.reduce(owned))) or bool(np.isfinite(owned).all())
        if self._comm.size > 1:
            ok = self._comm.allreduce(ok, op=MPI.LAND)
        if not ok:
            raise SimulationDiverged(f"the solution is not finite at t = {self.t:g}")

    def _assemble_matrix(self) -> None:
        if self._A is not None:
            self._A.destroy()
        self._A = dolfinx.fem.petsc.assemble_matrix(self._a, bcs=self._bcs)
        self._A.assemble()
        self._ksp.setOperators(self._A)
        self._A_stale = False
        if self._options is not None:  # the first matrix: set the solver up with the options
            self._with_options(self._ksp.setUp)
            self._options, unread = None, sorted(self._unread)
            if unread:
                raise InvalidValue(f"petsc_options: no part of the solver reads {unread}")

    def __del__(self):
        for obj in (getattr(self, "_A", None), getattr(self, "_ksp", None)):
            if obj is not None:
                obj.destroy()
