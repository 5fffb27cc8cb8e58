r"""The monodomain Mitchell-Schaeffer model of cardiac tissue (report section 4.3).

Model (equation 3): the transmembrane potential :math:`u` (dimensionless, rest 0, excited
about 1) and the gate variable :math:`w \in [0, 1]` on a domain :math:`\Omega` (lengths and
times in the caller's units, ms and mm in the report's examples):

.. math::

    \partial_t u = D \nabla^2 u + J_\mathrm{in}(w, u) + J_\mathrm{out}(u) + I_\mathrm{app},
    \qquad \nabla u \cdot n = 0 \text{ on } \partial\Omega,

    \frac{dw}{dt} = \begin{cases} (1 - w) / \tau_\mathrm{open} & u < u_\mathrm{gate} \\
                                  -w / \tau_\mathrm{close} & u \ge u_\mathrm{gate} \end{cases},
    \qquad J_\mathrm{in} = \frac{w u^2 (1 - u)}{\tau_\mathrm{in}},
    \qquad J_\mathrm{out} = -\frac{u}{\tau_\mathrm{out}} .

Scheme (equations 4 and 5): forward Euler for :math:`w`, backward Euler for the diffusion of
:math:`u` with the reaction taken at the old time. Step :math:`n \to n + 1`:

1. :math:`w^{n+1}_i = w^n_i + \Delta t\, g(u^n_i, w^n_i)` at every node :math:`i`, with
   :math:`g` the right-hand side of the gate equation. For Lagrange spaces (P1, Q1, ...) this
   pointwise update of the dof values *is* the interpolation of the forward-Euler expression.
   Ghost entries are updated alike on every rank, so no communication is needed.
2. Find :math:`u^{n+1} \in V` such that for all :math:`v \in V`

   .. math::

       \int_\Omega u^{n+1} v + \Delta t D\, \nabla u^{n+1} \cdot \nabla v \, dx
       = \int_\Omega \Big(u^n + \Delta t \big(J_\mathrm{in}(w^n, u^n) + J_\mathrm{out}(u^n)
         + I_\mathrm{app}\big)\Big) v \, dx .

   The reaction term is integrated exactly: the integrand :math:`w u^3 v` has degree
   :math:`5p` for Lagrange degree :math:`p` (per direction on quadrilaterals), so the
   quadrature has degree :math:`5p` (3 x 3 Gauss points on a Q1 cell); this is exact on affine
   cells. (Interpolating the reaction at the nodes or lumping the mass matrix changes the scheme:
   the wave then dies on the 60 x 60 grid.) The matrix is assembled once; the linear solver is
   warm-started from :math:`u^n` (:class:`TimeProblem`). The right-hand side is computed by a
   C quadrature kernel (:class:`MitchellSchaefferRHS` on
   :class:`~physicsrl.fem.quadrature.CellQuadrature` tables, compiled once by
   :mod:`physicsrl.fem.kernels`; a numpy version when no C compiler is found): the same
   quadrature sum as DOLFINx's assembly of the UFL form, ``rhs="form"``, equal to round-off,
   and about 10x faster (benchmarks/README.md). The gate update of step 1 is a C loop too.

``scheme="explicit"`` replaces steps 1-2 by the explicit lumped-mass scheme of
:mod:`physicsrl.fem.explicit` (no linear solve; stable for dt below a limit computed from the
mesh, with ``substeps`` sub-steps per dt); its O(h^2) difference from the scheme above vanishes
on grids that resolve the front (:mod:`physicsrl.fem.resolution`).

The applied current :math:`I_\mathrm{app}` is piecewise constant on cells (DG0): a callable is
evaluated at cell midpoints, so a stimulus region whose edges run along mesh nodes stimulates
the same cells on any number of ranks.

Batching: the state is two arrays of local dof values, ``u`` and ``w``, and every per-step
operation is either pointwise (the gate update), a quadrature kernel reading them, or a solve
with a matrix that does not depend on the state, so B independent replicas on one mesh stack
the state as (B, n) arrays and share the operators:
:class:`~physicsrl.fem.batched.BatchedMonodomain` runs both schemes that way on torch.
"""

from __future__ import annotations

import time

import numpy as np
import ufl
from dolfinx import fem, mesh
from mpi4py import MPI
from petsc4py import PETSc

from physicsrl.coordinated import Coordinated, Coordinator, parallel
from physicsrl.fem import kernels as compiled
from physicsrl.fem.errors import InvalidValue
from physicsrl.fem.explicit import ExplicitStep
from physicsrl.fem.kernels import pointer
from physicsrl.fem.quadrature import CellQuadrature
from physicsrl.fem.resolution import resolution
from physicsrl.fem.time_problem import TimeProblem
from physicsrl.fem.values import assign, finite, integer, positive

SCHEMES = ("implicit", "explicit")
"""The time schemes of :class:`MonodomainMitchellSchaeffer` (the first is the default)."""


def scheme_substeps(scheme: str, substeps) -> int:
    """``substeps`` as an int, or :class:`InvalidValue` unless ``scheme`` is one of
    :data:`SCHEMES` and ``substeps`` an integer >= 1, 1 unless the scheme is explicit."""
    if scheme not in SCHEMES:
        raise InvalidValue(f"scheme must be one of {SCHEMES}, got {scheme!r}")
    substeps = integer("substeps", substeps)
    if scheme != "explicit" and substeps > 1:
        raise InvalidValue(f"substeps must be 1 unless scheme='explicit', got {substeps}")
    return substeps


PARALLEL_PETSC_OPTIONS = {"pc_type": "jacobi"}
"""Solver options on more than one rank, updating
:data:`~physicsrl.fem.time_problem.DEFAULT_PETSC_OPTIONS` (CG, rtol 1e-10): CG + Jacobi
instead of block Jacobi/ICC(0), 1.5-2.3x faster per solve on 2 ranks at 1000 x 1000 and
2000 x 2000 cells (measurements: benchmarks/README.md, "Choice of the linear solver")."""


def default_ms_mesh(comm: MPI.Comm = MPI.COMM_WORLD, n: int = 60, L: float = 50.0) -> mesh.Mesh:
    """The square [-L, L]^2 split into n x n quadrilaterals (the report's training grid)."""
    return mesh.create_rectangle(comm, [[-L, -L], [L, L]], [n, n], mesh.CellType.quadrilateral)


class MonodomainMitchellSchaeffer(Coordinated):
    """The monodomain Mitchell-Schaeffer model on every rank, driven by the leader.

    Parameters
    ----------
    coordinator:
        The coordinator to register with (construct on every rank, in the same order).
    domain:
        Any 2D or 3D DOLFINx mesh (default: :func:`default_ms_mesh`, 60 x 60 Q1 on [-50, 50]^2).
    V:
        The function space of u and w (default: Lagrange degree 1 on ``domain``).
    u0, w0, I_app:
        Initial potential, initial gate and applied current: each a number, a callable ``f(x)``
        with ``x`` of shape (3, n) returning shape (n,), a ``fem.Expression`` or a
        ``fem.Function``. Defaults: the resting state u = 0, w = 1, no current.
    tau_in, tau_out, tau_open, tau_close:
        Time constants (> 0) of the currents and of the gate.
    u_gate:
        Potential at which the gate switches from opening to closing.
    D:
        Diffusivity (> 0), length^2 / time.
    dt:
        Time step (> 0).
    quadrature_degree:
        Quadrature degree of the right-hand side, an integer >= 1 (default: 5 x the element
        degree, exact).
    scheme:
        ``"implicit"`` (default, the report's, steps 1-2 above) or ``"explicit"``
        (:mod:`physicsrl.fem.explicit`): refused with :class:`InvalidValue` if dt / substeps
        exceeds its stability limit on this mesh.
    substeps:
        Explicit sub-steps of dt / substeps per time step (``"explicit"`` only; 1 otherwise).
    rhs:
        How the right-hand side is computed: ``"compiled"`` (default) by
        :class:`MitchellSchaefferRHS` with a C loop (:mod:`physicsrl.fem.kernels`, built once
        and cached; falls back to ``"numpy"`` with a warning if there is no C compiler; the
        gate update is then compiled too), ``"numpy"`` by the same class's vectorised numpy
        kernel, or ``"form"`` by DOLFINx's assembler from the UFL form. All evaluate the same
        quadrature sum and agree to round-off (with ``scheme="explicit"``, ``"compiled"``
        selects the C pass, the others its numpy version); the kernels are faster than the
        assembler (no coefficient packing, no geometry recomputed per step; about 2.5x for
        numpy and 10x for C, benchmarks/README.md).
    petsc_options:
        Linear solver options (see :class:`TimeProblem`, and :data:`PARALLEL_PETSC_OPTIONS`
        on more than one rank); ``{"ksp_type": "preonly", "pc_type": "lu"}`` for a direct
        solver.
    namespace:
        The coordinator namespace (default: the next integer).

    Attributes
    ----------
    timings:
        Seconds spent in the gate updates (``"ionic"``), right-hand sides (``"rhs"``) and
        linear solves (``"solve"``), accumulated over all steps; with ``scheme="explicit"``
        in the fused passes (``"explicit"``) and ghost updates (``"ghosts"``) instead.
    """

    def __init__(
        self,
        coordinator: Coordinator,
        domain: mesh.Mesh | None = None,
        V: fem.FunctionSpace | None = None,
        *,
        u0=0.0,
        w0=1.0,
        I_app=0.0,
        tau_in: float = 0.3,
        tau_out: float = 6.0,
        tau_open: float = 75.0,
        tau_close: float = 80.0,
        u_gate: float = 0.13,
        D: float = 0.013,
        dt: float = 0.03,
        quadrature_degree: int | None = None,
        scheme: str = "implicit",
        substeps: int = 1,
        rhs: str = "compiled",
        petsc_options: dict | None = None,
        namespace=None,
    ):
        self.register_coordinator(coordinator, namespace)
        substeps = scheme_substeps(scheme, substeps)
        if quadrature_degree is not None:
            quadrature_degree = integer("quadrature_degree", quadrature_degree)
        if rhs not in ("compiled", "numpy", "form"):
            raise InvalidValue(f"rhs must be 'compiled', 'numpy' or 'form', got {rhs!r}")
        self.scheme, self.substeps = scheme, substeps
        parameters = {
            "tau_in": tau_in,
            "tau_out": tau_out,
            "tau_open": tau_open,
            "tau_close": tau_close,
            "D": D,
            "dt": dt,
        }
        for name, value in parameters.items():
            positive(name, value)
        self.u_gate = finite("u_gate", u_gate)
        self.tau_open, self.tau_close = float(tau_open), float(tau_close)
        if domain is None:
            domain = default_ms_mesh() if V is None else V.mesh
        self.domain = domain
        if domain.comm.size > 1:
            petsc_options = {**PARALLEL_PETSC_OPTIONS, **(petsc_options or {})}
        self.problem = TimeProblem(domain, V, petsc_options)
        V = self.V = self.problem.V
        self.timings = self.problem.timings
        self.timings["ionic"] = 0.0

        # State: u^n lives in the time problem; w^n and the initial gate here.
        self._w = fem.Function(V, name="w")
        self._w0 = fem.Function(V, name="w0")
        self._I_app = fem.Function(fem.functionspace(domain, ("DG", 0)), name="I_app")
        self.problem.set_initial_condition(u0)
        assign(self._w0, w0, "w0")
        self._w.x.array[:] = self._w0.x.array
        assign(self._I_app, I_app, "I_app")

        # Forms (equation 5); parameters are constants so that one compiled kernel serves all.
        def constant(value):
            return fem.Constant(domain, PETSc.ScalarType(value))

        k, u_n, w = self.problem.dt, self.problem.u_n, self._w
        u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
        tau_in_c, tau_out_c, D_c = constant(tau_in), constant(tau_out), constant(D)
        J_in = w * u_n**2 * (1 - u_n) / tau_in_c
        J_out = -u_n / tau_out_c
        degree = (
            5 * V.ufl_element().embedded_superdegree
            if quadrature_degree is None
            else quadrature_degree
        )
        dx_exact = ufl.dx(domain=domain, metadata={"quadrature_degree": degree})
        self.problem.set_dt(dt)
        self.tau_in, self.tau_out, self.D = tau_in_c, tau_out_c, D_c  # fem.Constant
        self.resolution = resolution(domain, D, tau_in, scheme, dt)
        self._kernels = compiled.load(domain.comm) if rhs == "compiled" else None
        self._explicit = None
        if scheme == "explicit":
            self._explicit = ExplicitStep(
                self.problem.u_n,
                w,
                D=D,
                tau_in=tau_in,
                tau_out=tau_out,
                tau_open=tau_open,
                tau_close=tau_close,
                u_gate=u_gate,
                dt=dt / substeps,
                kernels=self._kernels,
                timings=self.timings,
            )
            self._explicit.check_stable(self.resolution.mesh)
            self._explicit.set_current(self._I_app)
            return
        self.problem.set_bilinear_form(
            (u * v + k * D_c * ufl.inner(ufl.grad(u), ufl.grad(v))) * ufl.dx
        )
        kernels = self._kernels
        if rhs == "form":
            self.problem.set_linear_form((u_n + k * (J_in + J_out + self._I_app)) * v * dx_exact)
        else:
            self.rhs = MitchellSchaefferRHS(
                CellQuadrature(V, degree, kernels=kernels),
                u_n,
                w,
                self._I_app,
                k,
                self.tau_in,
                self.tau_out,
                kernels,
            )
            self.problem.set_rhs(self.rhs)

        # The gate's next values are written to a work array before the step (they need u^n)
        # and copied to w after it (the step's right-hand side needs w^n).
        self._next_w = np.empty(w.x.array.size)
        if kernels is None:  # the numpy update's work arrays
            self._open = np.empty(w.x.array.size, dtype=bool)
            self._other = np.empty(w.x.array.size)

    # the state --------------------------------------------------------------------------
    def u_n(self) -> fem.Function:
        """The potential now (this rank's part)."""
        return self.problem.u_n

    def w_n(self) -> fem.Function:
        """The gate variable now (this rank's part)."""
        return self._w

    @property
    def t(self) -> float:
        """Time since the initial condition."""
        return self.problem.t

    @property
    def dt(self) -> float:
        return float(self.problem._dt_value)

    # changing the problem ---------------------------------------------------------------
    @parallel
    def set_I_app(self, value) -> None:
        """Set the applied current (piecewise constant on cells); it acts from the next step."""
        assign(self._I_app, value, "I_app")
        if self._explicit is not None:
            self._explicit.set_current(self._I_app)

    @parallel
    def set_initial_condition(self, u0, w0) -> None:
        """Set the initial (u, w); applied now if at t = 0, else at the next reset."""
        self.problem.set_initial_condition(u0)
        assign(self._w0, w0, "w0")
        if not self.problem.started:
            self._w.x.array[:] = self._w0.x.array

    # running ----------------------------------------------------------------------------
    @parallel
    def advance_time(self, T: float) -> None:
        """Advance T time units (a whole number of steps); raises ``SimulationDiverged`` on
        every rank if u stops being finite."""
        steps = self.problem.steps(T)
        if self._explicit is not None:
            self._explicit.advance(steps * self.substeps)
            self.problem.record_steps(steps)
            self.problem.check_finite()
            return
        w, next_w = self._w.x.array, self._next_w
        gate = self._gate_function()
        timings, step, clock = self.timings, self.problem.step, time.perf_counter
        for _ in range(steps):
            start = clock()
            gate()  # next_w = w^{n+1}, from u^n and w^n
            middle = clock()
            step()  # u^{n+1}, from u^n and w^n
            restart = clock()
            np.copyto(w, next_w)
            timings["ionic"] += (middle - start) + (clock() - restart)
        self.problem.check_finite()

    def _gate_function(self):
        """A function writing w^{n+1} (forward Euler on the gate equation, every local dof)
        into ``self._next_w``: w^n + dt (1 - w^n) / tau_open = a_open w^n + b_open where
        u^n < u_gate, else w^n - dt w^n / tau_close = a_close w^n."""
        dt = self.dt
        a_open, b_open, a_close = (
            1.0 - dt / self.tau_open,
            dt / self.tau_open,
            1.0 - dt / self.tau_close,
        )
        u, w, next_w, u_gate = self.problem.u_n.x.array, self._w.x.array, self._next_w, self.u_gate
        if self._kernels is not None:
            ffi, gate = self._kernels.ffi, self._kernels.lib.ms_gate
            args = (w.size, pointer(ffi, u), pointer(ffi, w), pointer(ffi, next_w), u_gate)
            args = (*args, a_open, b_open, a_close)
            return lambda: gate(*args)
        is_open, other = self._open, self._other

        def gate():
            np.less(u, u_gate, out=is_open)
            np.multiply(w, a_close, out=next_w)
            np.multiply(w, a_open, out=other)
            np.add(other, b_open, out=other)
            np.copyto(next_w, other, where=is_open)

        return gate

    @parallel
    def reset(self) -> None:
        """Return to the initial condition at t = 0 (I_app is kept), then call
        :meth:`handle_reset`."""
        self.problem.reset()
        self._w.x.array[:] = self._w0.x.array
        self.handle_reset()

    def handle_reset(self) -> None:
        """Override to customise resets (runs on every rank, inside :meth:`reset`); draw random
        numbers with :func:`physicsrl.coordinated.random` / ``randint`` so that ranks agree."""


class MitchellSchaefferRHS:
    r"""The right-hand side of step 2 (module docstring) by quadrature: ``rhs(b)`` writes

    .. math::

        b_i = \int_\Omega \Big(u^n + \Delta t \big(\frac{w^n (u^n)^2 (1 - u^n)}{\tau_\mathrm{in}}
              - \frac{u^n}{\tau_\mathrm{out}} + I_\mathrm{app}\big)\Big) \phi_i \, dx

    over this rank's owned cells into the local array ``b`` (ghost entries: partial sums), with
    the quadrature of ``quadrature``; the constants are read at every call.

    With ``kernels`` (the compiled module of :mod:`physicsrl.fem.kernels`) one C loop over the
    cells does everything (``ms_rhs``: gather, point values, integrand, cell vector, scatter),
    about 20 ns per Q1 cell. Without, numpy per block of cells: u and w at the points (a gather
    and a small matrix product each), the integrand in Horner form
    :math:`k\,(u (u w (1 - u) + a / k) + \tau_\mathrm{in} I)` with
    :math:`k = \Delta t / \tau_\mathrm{in}` and :math:`a = 1 - \Delta t / \tau_\mathrm{out}`
    (six in-place passes, the factor :math:`k` applied to ``b`` at the end), and the cell
    vectors (one product); then one sparse product scatters them. No allocation per call.
    """

    def __init__(self, quadrature: CellQuadrature, u, w, I_app, dt, tau_in, tau_out, kernels=None):
        self.quadrature = quadrature
        self._u, self._w, self._I_app = u, w, I_app
        # 0-d views of the constants' storage (Constant.value builds a wrapper per access)
        self._dt, self._tau_in, self._tau_out = (c._cpp_object.value for c in (dt, tau_in, tau_out))
        self._I_dofs = np.ascontiguousarray(
            I_app.function_space.dofmap.list[: quadrature.num_cells, 0], dtype=np.int32
        )
        self._kernels = kernels
        if kernels is None:
            self._I_dofs = self._I_dofs.astype(np.intp)
            self._I = np.empty(quadrature.num_cells)
            self._blocks = quadrature.blocks()
            return
        q, ffi = quadrature, kernels.ffi
        # The arrays behind the pointers are kept alive by self and the functions.
        self._arrays = (u.x.array, w.x.array, I_app.x.array)
        u_p, w_p, i_p = (pointer(ffi, a) for a in self._arrays)
        self._args = (
            q.num_cells,
            q.num_dofs,
            q.num_points,
            pointer(ffi, q.dofs, "int32_t *"),
            pointer(ffi, q.phi),
            pointer(ffi, q.point_weights),
            0 if q.affine else q.num_points,
            ffi.NULL if q.cell_det is None else pointer(ffi, q.cell_det),
            u_p,
            w_p,
            i_p,
            pointer(ffi, self._I_dofs, "int32_t *"),
        )
        self._b = None  # the last output array and its pointer
        self._b_pointer = None

    def __call__(self, b: np.ndarray) -> None:
        dt, tau_in, tau_out = float(self._dt), float(self._tau_in), float(self._tau_out)
        if self._kernels is None:
            self._numpy(b, dt, tau_in, tau_out)
            return
        if b is not self._b:
            self._b, self._b_pointer = b, pointer(self._kernels.ffi, b)
        self._kernels.lib.ms_rhs(*self._args, dt, tau_in, tau_out, self._b_pointer, b.size)

    def _numpy(self, b: np.ndarray, dt: float, tau_in: float, tau_out: float) -> None:
        q = self.quadrature
        k = dt / tau_in
        c = (1.0 - dt / tau_out) / k
        current = self._I
        np.take(self._I_app.x.array, self._I_dofs, out=current)
        current *= tau_in
        u, w = self._u.x.array, self._w.x.array
        uq, wq, f = q.work(0), q.work(1), q.work(2)
        for start, stop in self._blocks:
            n = stop - start
            U = q.values(u, start, stop, uq)
            W = q.values(w, start, stop, wq)
            F = f[:n]
            np.subtract(1.0, U, out=F)
            F *= W
            F *= U
            F += c
            F *= U
            F += current[start:stop, None]
            q.integrate(F, start, stop)
        b[:] = 0.0
        q.scatter(b)
        b *= k
