"""The heat environment and the time problem against known answers."""

from __future__ import annotations

import physicsrl.fem  # noqa: F401  (first: loads the MPI library that dolfinx links to)

# isort: split

import numpy as np
import pytest
import ufl
from dolfinx import fem, mesh
from mpi4py import MPI

from physicsrl.coordinated import Coordinator
from physicsrl.fem import HeatEnvironment, SimulationDiverged, TimeProblem
from physicsrl.fem.heat import resolution, transient_integral


def square(n: int) -> mesh.Mesh:
    return mesh.create_rectangle(MPI.COMM_WORLD, [[-2.0, -2.0], [2.0, 2.0]], [n, n])


def l2_error(u: fem.Function, exact) -> float:
    """||u - exact||_L2 with ``exact`` a UFL expression, quadrature degree 6."""
    error = fem.form((u - exact) ** 2 * ufl.dx(metadata={"quadrature_degree": 6}))
    return np.sqrt(MPI.COMM_WORLD.allreduce(fem.assemble_scalar(error)))


def test_spatial_convergence_is_second_order():
    """u_e = sin(x) cos(y) is steady for f = 2 u_e, u_D = u_e. Starting from u_e, the P1
    solution after 50 implicit Euler steps differs from u_e by O(h^2) in L2: the observed
    orders between 8, 16, 32 and 64 cells per side lie in [1.9, 2.1]."""
    errors = []
    for n in (8, 16, 32, 64):
        env = HeatEnvironment(
            Coordinator(),
            square(n),
            dt=0.02,
            u0=lambda x: np.sin(x[0]) * np.cos(x[1]),
            u_D=lambda x: np.sin(x[0]) * np.cos(x[1]),
            f=lambda x: 2 * np.sin(x[0]) * np.cos(x[1]),
        )
        with env.coordinator:
            env.advance_time(1.0)
        x = ufl.SpatialCoordinate(env.domain)
        errors.append(l2_error(env.u_n(), ufl.sin(x[0]) * ufl.cos(x[1])))
    orders = np.log2(np.array(errors[:-1]) / errors[1:])
    assert np.all((orders > 1.9) & (orders < 2.1)), orders


def test_time_convergence_is_first_order():
    """u_e = e^{-t} (x + y + 5) lies in P1 at every time, so only the time error remains:
    with f = -u_e and u_D = u_e updated before every step (implicit Euler takes them at
    t_{n+1}), the L2 error at t = 1 halves with dt (observed orders in [0.9, 1.1])."""
    errors = []
    for dt in (0.1, 0.05, 0.025):
        env = HeatEnvironment(Coordinator(), square(4), dt=dt, u0=lambda x: x[0] + x[1] + 5)
        with env.coordinator:
            for n in range(round(1 / dt)):
                t = (n + 1) * dt
                env.set_boundary_value(lambda x, t=t: np.exp(-t) * (x[0] + x[1] + 5))
                env.set_source(lambda x, t=t: -np.exp(-t) * (x[0] + x[1] + 5))
                env.advance_time(dt)
        x = ufl.SpatialCoordinate(env.domain)
        errors.append(l2_error(env.u_n(), np.exp(-1.0) * (x[0] + x[1] + 5)))
    orders = np.log2(np.array(errors[:-1]) / errors[1:])
    assert np.all((orders > 0.9) & (orders < 1.1)), orders


def test_quadrant_integrals_order_and_values():
    """On [-2, 2]^2 the quadrant integrals of u = x are (-4, 4, -4, 4) and of u = y are
    (-4, -4, 4, 4) in the documented order; of a constant 3 they are 12 each and agree with
    compute_ufl_form."""
    env = HeatEnvironment(Coordinator(), u0=lambda x: x[0])
    with env.coordinator:
        np.testing.assert_allclose(env.quadrant_integrals(), [-4, 4, -4, 4], atol=1e-12)
        env.set_initial_condition(lambda x: x[1])
        np.testing.assert_allclose(env.quadrant_integrals(), [-4, -4, 4, 4], atol=1e-12)
        env.set_initial_condition(3.0)
        np.testing.assert_allclose(env.quadrant_integrals(), [12.0] * 4, rtol=1e-12)
        assert env.compute_ufl_form(env.u_n() * ufl.dx) == pytest.approx(48.0, rel=1e-12)


def test_reset_calls_the_hook_and_restarts():
    """reset() returns to t = 0 and to the initial condition chosen by handle_reset()."""

    class Levels(HeatEnvironment):
        level = 0

        def handle_reset(self):
            self.level += 1
            self.set_initial_condition(float(self.level))

    env = Levels(Coordinator(), mesh.create_unit_square(MPI.COMM_WORLD, 4, 4))
    with env.coordinator:
        env.advance_time(0.1)
        assert env.t == pytest.approx(0.1)
        env.reset()
        assert env.t == 0.0
        np.testing.assert_array_equal(env.u_n().x.array, 1.0)
        env.advance_time(0.05)
        env.set_initial_condition(7.0)  # mid-run: takes effect at the next reset
        assert not np.allclose(env.u_n().x.array, 7.0)


def test_petsc_options_that_no_solver_part_reads_or_petsc_rejects_are_refused():
    """A misspelt key is refused when the solver is first set up (PETSc reads the inner
    solvers' options only then), naming it; a value PETSc rejects, at construction; a good
    option takes effect."""
    domain = mesh.create_unit_square(MPI.COMM_WORLD, 4, 4)
    env = HeatEnvironment(Coordinator(), domain, petsc_options={"ksp_rtoll": 1e-2})
    with env.coordinator, pytest.raises(ValueError, match=r"reads \['ksp_rtoll'\]"):
        env.advance_time(0.01)
    with pytest.raises(ValueError, match="petsc_options: PETSc refused .*'nonsense'"):
        HeatEnvironment(Coordinator(), domain, petsc_options={"ksp_type": "nonsense"})
    env = HeatEnvironment(Coordinator(), domain, petsc_options={"ksp_rtol": 1e-3})
    with env.coordinator:
        env.advance_time(0.01)
    assert env.problem._ksp.getTolerances()[0] == 1e-3


def test_time_problem_setters_take_effect_and_lu_agrees():
    """du/dt = -c u, uniform: implicit Euler gives u_n = u_0 / (1 + c dt)^n exactly. Changing
    dt and then the bilinear form (c = 1 -> 3) mid-run changes the factor from the next step;
    the direct solver option gives the same numbers."""
    domain = mesh.create_unit_square(MPI.COMM_WORLD, 3, 3)
    for options in (None, {"ksp_type": "preonly", "pc_type": "lu"}):
        problem = TimeProblem(domain, petsc_options=options)
        u, v = ufl.TrialFunction(problem.V), ufl.TestFunction(problem.V)
        problem.set_dt(0.1)
        problem.set_bilinear_form((1 + problem.dt) * u * v * ufl.dx)
        problem.set_linear_form(problem.u_n * v * ufl.dx)
        problem.set_initial_condition(2.0)
        problem.solve(0.3)
        problem.set_dt(0.05)
        problem.solve(0.1)
        problem.set_bilinear_form((1 + 3 * problem.dt) * u * v * ufl.dx)
        problem.solve(0.05)
        expected = 2.0 / 1.1**3 / 1.05**2 / 1.15
        np.testing.assert_allclose(problem.u_n.x.array, expected, rtol=1e-9)
        assert problem.t == pytest.approx(0.45)
        problem.reset()
        np.testing.assert_array_equal(problem.u_n.x.array, 2.0)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"dt": 0.0}, "dt"),
        ({"dt": -1.0}, "dt"),
        ({"u0": float("nan")}, "u0"),
        ({"u_D": lambda x: np.full(x.shape[1], np.inf)}, "u_D"),
        ({"f": lambda x: np.zeros((2, x.shape[1]))}, "f"),
        ({"f": "hot"}, "f"),
        (
            {
                "u0": fem.Function(
                    fem.functionspace(
                        mesh.create_unit_square(MPI.COMM_WORLD, 2, 2), ("Lagrange", 1)
                    )
                )
            },
            "u0",
        ),
    ],
)
def test_bad_input_raises_value_error_naming_it(kwargs, name):
    with pytest.raises(ValueError, match=name):
        HeatEnvironment(Coordinator(), mesh.create_unit_square(MPI.COMM_WORLD, 4, 4), **kwargs)


def test_bad_time_span_and_setter_values():
    """T must be a whole number of steps; a rejected value leaves the state unchanged."""
    env = HeatEnvironment(Coordinator(), mesh.create_unit_square(MPI.COMM_WORLD, 4, 4), u0=2.0)
    with env.coordinator:
        with pytest.raises(ValueError, match="T"):
            env.advance_time(0.015)
        with pytest.raises(ValueError, match="T"):
            env.advance_time(-0.01)
        with pytest.raises(ValueError, match="u0"):
            env.set_initial_condition(lambda x: np.full(x.shape[1], np.nan))
        np.testing.assert_array_equal(env.u_n().x.array, 2.0)


def test_divergence_raises_simulation_diverged():
    """A non-finite source makes u non-finite: advance_time raises SimulationDiverged, which
    is both a CollectiveError and a FloatingPointError."""
    env = HeatEnvironment(Coordinator(), mesh.create_unit_square(MPI.COMM_WORLD, 4, 4))
    env._f.x.array[:] = np.inf  # bypasses the setter's validation
    with env.coordinator:
        with pytest.raises(SimulationDiverged):
            env.advance_time(0.02)
    assert issubclass(SimulationDiverged, FloatingPointError)


def test_transient_integral_is_the_exact_series():
    """At t = 0 the integral of the transient is the square's area (the series converges
    there slowly: 2000 terms leave 0.03% on [-2, 2]^2); at t = 3 it is its slowest mode,
    (16 a / pi^2)^2 exp(-2 (pi / 2a)^2 t), to 1e-6 (the next is 2/9 exp(-8 (pi / 2a)^2 t) of
    it)."""
    for a in (1.0, 2.0):
        assert transient_integral(0.0, a)[0] == pytest.approx(4 * a * a, rel=5e-4)
        late = (16 * a / np.pi**2) ** 2 * np.exp(-2 * (np.pi / (2 * a)) ** 2 * 3.0)
        assert transient_integral(3.0, a)[0] == pytest.approx(late, rel=1e-6)


def test_resolution_report_converges_under_refinement():
    """The report of the heat task's default (50 x 50 P1 triangles, dt = 0.01) at its ten
    decision times is within 1% of the exact transient, dominated by implicit Euler's O(dt)
    error; halving h and quartering dt cuts it at least 3.5-fold. Its line names h, dt and the
    worst error. A mesh that is not the square of the given extent is refused."""
    times = 0.1 * np.arange(1, 11)
    reports = []
    for n, dt in ((50, 0.01), (100, 0.0025)):
        env = HeatEnvironment(Coordinator(), square(n), dt=dt, u0=3.0, u_D=1.0, f=0.5)
        reports.append(resolution(env, 2.0, times))
    coarse, fine = reports
    assert coarse.h == pytest.approx(np.hypot(0.08, 0.08), rel=1e-12)
    assert 0.003 < coarse.error < 0.01 and coarse.error / fine.error > 3.5
    assert coarse.warning is None
    assert f"{coarse.errors[np.abs(coarse.errors).argmax()]:+.2%}" in str(coarse)
    assert "h = 0.113, dt = 0.01" in str(coarse) and "\n" not in str(coarse)
    long_step = resolution(HeatEnvironment(Coordinator(), square(50), dt=0.1), 2.0, times)
    worst = long_step.errors[np.abs(long_step.errors).argmax()]
    assert 0.07 < worst < 0.08 and f"off by up to {worst:+.2%}, above 5%" in long_step.warning
    with pytest.raises(ValueError, match="extent: the mesh is not the square"):
        resolution(env, 1.0, times)


@pytest.mark.parametrize(
    "extent, times, message",
    [
        (-2.0, [0.1], "extent must be a finite number > 0, got -2.0"),
        (2.0, [], r"times must be finite times > 0, at least one, got \[\]"),
        (2.0, [0.0, 0.1], r"times must be finite times > 0"),
        (2.0, [0.2, 0.1], r"times must be ascending, got \[0.2, 0.1\]"),
        (2.0 + 1e-9, [0.1], "extent: the mesh is not the square"),
    ],
)
def test_bad_resolution_arguments_are_refused_before_solving(extent, times, message):
    """One line naming the bad argument, before the simulator moves (its time stays 0); a
    mesh off the extent by 1e-9 is refused too (no absolute tolerance)."""
    env = HeatEnvironment(Coordinator(), square(4), dt=0.1)
    with pytest.raises(ValueError, match=message):
        resolution(env, extent, times)
    assert env.problem.t == 0
    with pytest.raises(ValueError, match="need extent > 0 and times t >= 0"):
        transient_integral([0.1, -0.1], 2.0)
    with pytest.raises(ValueError, match="need extent > 0"):
        transient_integral(0.1, -2.0)
