"""The report's Mitchell-Schaeffer simulator (section 4.3), ported to DOLFINx 0.11: the baseline
of ``physicsrl-bench ms``.

Kept as in the original: the time problem with a direct solver (``preonly`` + PETSc's default
LU, factorised at the first solve), the matrix assembled once; at every step a new solution
function, copies of the state functions, a new ``fem.Expression`` for the forward-Euler gate
update interpolated into ``w``, and the right-hand side assembled with the quadrature degree
UFL estimates; model parameters compiled into the forms as literals; ``set_I_app`` recompiles
the right-hand side; coordination by :mod:`physicsrl.baselines.report_coordinated`.

Changed so that it solves the same discrete problem as
:class:`physicsrl.fem.MonodomainMitchellSchaeffer`: the reaction uses :math:`w^n` as in the
report's equation (4) (the original updated ``w`` before assembling, so it used
:math:`w^{n+1}`); the applied current is piecewise constant on cells (the original interpolated
it into the potential's space). Timers (``timings``) are added. As in the original,
``advance_time`` accumulates ``t += dt`` in floating point and may take one step more than
``T / dt``: call it one step at a time.
"""

from __future__ import annotations

import time

import dolfinx.fem.petsc
import ufl
from dolfinx import fem
from petsc4py import PETSc

from physicsrl.baselines.report_coordinated import ReportCoordinated, report_parallel


class ReportTimeProblem:
    def __init__(self, domain):
        self.domain = domain
        self._solver = PETSc.KSP().create(domain.comm)
        self._solver.setType(PETSc.KSP.Type.PREONLY)
        self._solver.getPC().setType(PETSc.PC.Type.LU)
        self.u_n = None
        self._is_running = False
        self.timings = {"rhs": 0.0, "solve": 0.0}

    def set_A(self, a, bcs):
        self._bcs = bcs
        self._V = a.arguments()[-1].ufl_function_space()
        self._bilinear_form = fem.form(a)
        self._A = dolfinx.fem.petsc.assemble_matrix(self._bilinear_form, bcs=bcs)
        self._A.assemble()
        self._solver.setOperators(self._A)

    def set_L(self, L):
        self._linear_form = fem.form(L)
        self._b = dolfinx.fem.petsc.create_vector(self._linear_form.function_spaces[0])

    def set_dt(self, dt):
        self.dt = dt

    def set_initial_condition(self, initial_condition):
        self.initial_condition = initial_condition

    def set_u_n(self, u_n):
        self.u_n = u_n
        if not self._is_running and self.initial_condition is not None:
            self.u_n.interpolate(self.initial_condition)

    def reset(self):
        self._is_running = False
        self.u_n.interpolate(self.initial_condition)

    def solve(self, T):
        uh = fem.Function(self._V)
        uh.name = "uh"
        if not self._is_running:
            uh.interpolate(self.initial_condition)
            self._is_running = True
        t = 0
        while t < T:
            t += self.dt
            start = time.perf_counter()
            with self._b.localForm() as loc_b:
                loc_b.set(0)
            dolfinx.fem.petsc.assemble_vector(self._b, self._linear_form)
            dolfinx.fem.petsc.apply_lifting(self._b, [self._bilinear_form], [self._bcs])
            self._b.ghostUpdate(addv=PETSc.InsertMode.ADD_VALUES, mode=PETSc.ScatterMode.REVERSE)
            dolfinx.fem.petsc.set_bc(self._b, self._bcs)
            middle = time.perf_counter()
            self._solver.solve(self._b, uh.x.petsc_vec)
            uh.x.scatter_forward()
            if self.u_n is not None:
                self.u_n.x.array[:] = uh.x.array
            self.timings["rhs"] += middle - start
            self.timings["solve"] += time.perf_counter() - middle
        return uh


class ReportMonodomainMitchellSchaeffer(ReportCoordinated):
    def __init__(
        self,
        coordinator,
        domain,
        initial_condition_u,
        initial_condition_w,
        I_app,
        tau_in=0.3,
        tau_out=6.0,
        tau_open=75.0,
        tau_close=80.0,
        u_gate=0.13,
        D=0.013,
        dt=0.03,
        V=None,
    ):
        self.register_coordinator(coordinator)
        self.dt = dt
        self.domain = domain
        if V is None:
            V = fem.functionspace(domain, ("Lagrange", 1))
        self._V = V
        self._tau_in, self._tau_out = tau_in, tau_out
        self._tau_open, self._tau_close = tau_open, tau_close
        self._u_gate, self._D = u_gate, D
        self.timings = {"ionic": 0.0}

        self._u, self._v = ufl.TrialFunction(V), ufl.TestFunction(V)
        self._u_n = fem.Function(V, name="u_n")
        self._w_n = fem.Function(V, name="w_n")
        self._I_app = fem.Function(fem.functionspace(domain, ("DG", 0)), name="I_app")
        self._problem = ReportTimeProblem(domain)
        self.timings.update(self._problem.timings)
        self._problem.timings = self.timings

        self._I_app.interpolate(I_app)
        self.compute_right_hand_side()
        self.set_A()
        self.set_initial_condition(initial_condition_u, initial_condition_w)
        self._problem.set_dt(dt)
        self._problem.set_u_n(self._u_n)

    def u_n(self):
        return self._u_n

    def w_n(self):
        return self._w_n

    def set_initial_condition(self, initial_u, initial_w):
        self._problem.set_initial_condition(initial_u)
        self._initial_condition_w = initial_w
        self._w_n.interpolate(initial_w)

    @report_parallel
    def set_I_app(self, I_app):
        self._I_app.interpolate(I_app)
        self.compute_right_hand_side()

    def compute_right_hand_side(self):
        J_in = self._w_n * self._u_n * self._u_n * (1 - self._u_n) / self._tau_in
        J_out = -self._u_n / self._tau_out
        L = (self._u_n + self.dt * (J_in + J_out + self._I_app)) * self._v * ufl.dx
        self._problem.set_L(L)

    def set_A(self):
        a = (
            self._u * self._v * ufl.dx
            + self.dt * self._D * ufl.dot(ufl.grad(self._u), ufl.grad(self._v)) * ufl.dx
        )
        self._problem.set_A(a, [])

    @report_parallel
    def advance_time(self, T):
        t = 0
        while t < T:
            start = time.perf_counter()
            current_w = self.w_n().copy()
            current_u = self.u_n().copy()
            self.timings["ionic"] += time.perf_counter() - start

            self._problem.solve(self.dt)  # the right-hand side uses u^n and w^n

            start = time.perf_counter()
            update = ufl.conditional(
                current_u < self._u_gate,
                (1 - current_w) / self._tau_open,
                -current_w / self._tau_close,
            )
            new_w = fem.Expression(
                current_w + self.dt * update, self._V.element.interpolation_points
            )
            self._w_n.interpolate(new_w)
            self.timings["ionic"] += time.perf_counter() - start
            t += self.dt
