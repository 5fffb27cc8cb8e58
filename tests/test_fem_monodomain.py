"""The Mitchell-Schaeffer simulator against known answers."""

from __future__ import annotations

import physicsrl.fem  # noqa: F401  (first: loads the MPI library that dolfinx links to)

# isort: split

import numpy as np
import pytest
from dolfinx import mesh
from mpi4py import MPI
from scipy.integrate import solve_ivp

from physicsrl.coordinated import Coordinator
from physicsrl.fem import MonodomainMitchellSchaeffer, SimulationDiverged, plot_field
from physicsrl.fem.resolution import expected_cv_error, planar_front_speed

TAU_IN, TAU_OUT, TAU_OPEN, TAU_CLOSE, U_GATE, D, DT = 0.3, 6.0, 75.0, 80.0, 0.13, 0.013, 0.03


def reaction(u, w):
    """Right-hand sides of the model (3) without diffusion: (du/dt, dw/dt)."""
    du = w * u**2 * (1 - u) / TAU_IN - u / TAU_OUT
    dw = np.where(u < U_GATE, (1 - w) / TAU_OPEN, -w / TAU_CLOSE)
    return du, dw


def upstroke_and_apd(t, u):
    """Time u first reaches 0.5, and the time from then until u falls back below 0.5
    (linear interpolation between samples)."""
    up = np.nonzero(u >= 0.5)[0]
    i, j = up[0], up[-1]
    t_up = t[i - 1] + (0.5 - u[i - 1]) / (u[i] - u[i - 1]) * (t[i] - t[i - 1])
    t_down = t[j] + (u[j] - 0.5) / (u[j] - u[j + 1]) * (t[j + 1] - t[j])
    return t_up, t_down - t_up


@pytest.mark.parametrize("scheme", ["implicit", "explicit"])
def test_uniform_action_potential_matches_the_ode(scheme):
    """Uniform u, w: diffusion leaves a uniform field unchanged (K 1 = 0; implicit: the exact
    integral of a constant reaction; explicit: nodal reaction), so both schemes reduce to
    forward Euler on the ODE. We compare (a) with that discrete map, to 1e-9, and (b) with the
    ODE solved by solve_ivp (rtol 1e-10): starting at u = 0.2, w = 1, the upstroke time (u
    reaches 0.5) agrees within 0.05 time units and the action potential duration (u above
    0.5) within 1 %, forward Euler's O(dt) error at dt = 0.03."""
    domain = mesh.create_rectangle(
        MPI.COMM_WORLD, [[0, 0], [1, 1]], [1, 1], mesh.CellType.quadrilateral
    )
    ms = MonodomainMitchellSchaeffer(Coordinator(), domain, u0=0.2, w0=1.0, scheme=scheme)
    steps = 12000
    samples = np.empty(steps + 1)
    samples[0] = 0.2
    with ms.coordinator:
        for n in range(steps):
            ms.advance_time(DT)
            samples[n + 1] = ms.u_n().x.array[0]
    assert np.ptp(ms.u_n().x.array) < 1e-12

    u, w = 0.2, 1.0
    euler = [u]
    for _ in range(steps):
        du, dw = reaction(u, w)
        u, w = u + DT * du, w + DT * dw
        euler.append(u)
    np.testing.assert_allclose(samples, euler, atol=1e-9)

    t = np.arange(steps + 1) * DT
    ode = solve_ivp(
        lambda _, y: reaction(*y),
        (0, t[-1]),
        [0.2, 1.0],
        t_eval=t,
        rtol=1e-10,
        atol=1e-12,
        max_step=0.05,
    )
    up, apd = upstroke_and_apd(t, samples)
    up_ode, apd_ode = upstroke_and_apd(t, ode.y[0])
    assert abs(up - up_ode) < 0.05, (up, up_ode)
    assert abs(apd - apd_ode) < 0.01 * apd_ode, (apd, apd_ode)


def nagumo_speed() -> float:
    """Travelling-front speed of u_t = D u_xx + F(u) with w = 1 ahead of the front.

    F(u) = u^2 (1 - u) / tau_in - u / tau_out = k u (u - a)(b - u) with k = 1 / tau_in and
    a < b the roots of u^2 - u + r, r = tau_in / tau_out: a, b = (1 -+ sqrt(1 - 4 r)) / 2.
    With u = b s: s_t = D s_xx + k b^2 s (s - a/b)(1 - s), the normalised Nagumo equation,
    whose front speed is sqrt(D k b^2 / 2) (1 - 2 a / b). Hence c = sqrt(D k / 2) (b - 2 a)
    (= 0.12389 for the default parameters).
    """
    k, r = 1 / TAU_IN, TAU_IN / TAU_OUT
    a, b = (1 - np.sqrt(1 - 4 * r)) / 2, (1 + np.sqrt(1 - 4 * r)) / 2
    return np.sqrt(D * k / 2) * (b - 2 * a)


def front_speed(h: float, dt: float, **model) -> float:
    """:func:`planar_front_speed` with the gate frozen (tau_close = 1e9) unless ``model``
    says otherwise."""
    return planar_front_speed(h, dt, **{"tau_close": 1e9, **model})


def test_conduction_velocity_converges_to_the_nagumo_speed():
    """A planar front with the gate frozen (tau_close -> infinity, so w = 1 in and ahead of
    the front, as the Nagumo reduction assumes; with tau_close = 80 w decays within the front
    and the front is about 1 % slower) travels at the speed of :func:`nagumo_speed`: within
    0.3 % for h = 0.04, 0.02, 0.01 (dt = h / 5; the front is about sqrt(D tau_in) = 0.06
    wide) and within 0.1 % on the finest."""
    c = nagumo_speed()
    errors = [abs(front_speed(h, h / 5) - c) / c for h in (0.04, 0.02, 0.01)]
    assert max(errors) < 3e-3, errors
    assert errors[-1] < 1e-3, errors


@pytest.fixture(scope="module")
def converged_cv() -> float:
    """Planar conduction velocity of the default parameters (tau_close = 80) as h, dt -> 0:
    the implicit scheme at h = 0.01, dt = 0.002 (where the frozen-gate front is within 0.1 %
    of the Nagumo speed, test above)."""
    return front_speed(0.01, 0.002, tau_close=TAU_CLOSE)


@pytest.mark.parametrize(
    "scheme, h", [(s, h) for s in ("explicit", "implicit") for h in (0.2, 0.1, 0.075, 0.05)]
)
def test_expected_cv_error_is_the_simulated_one(converged_cv, scheme, h):
    """The CV error that the resolution report states for a mesh (the table of
    ``physicsrl/fem/cv_error.csv``, log-interpolated in h / width: h = 0.075 lies between two
    rows) is the one a planar front on a strip of h x h cells at dt = 0.03 (the tasks' step)
    shows against the converged speed, within 0.2 points; the explicit scheme is within 2.5 %
    for h <= 0.1 (about 2.3 front widths, the resolved tasks' 1000 x 1000 grid). On
    triangles (the squares cut along a diagonal) the table's is the larger in magnitude of a
    front along their edges and one along their hypotenuses (the implicit scheme's is 2.5
    times larger there at h = 0.2), within 0.3 points (the interpolation's error at 0.075)."""
    ratio = h * np.sqrt(2) / np.sqrt(D * TAU_IN)  # the cell diagonal against the front width
    error = front_speed(h, DT, tau_close=TAU_CLOSE, scheme=scheme) / converged_cv - 1
    assert error == pytest.approx(expected_cv_error(scheme, ratio), abs=2e-3)
    if scheme == "explicit" and h <= 0.1:
        assert abs(error) < 0.025, error
    triangles = [
        front_speed(h, DT, tau_close=TAU_CLOSE, scheme=scheme, cell_type="triangle", along=along)
        / converged_cv
        - 1
        for along in ("edges", "hypotenuses")
    ]
    worst = max(triangles, key=abs)
    assert worst == pytest.approx(expected_cv_error(scheme, ratio, "triangle"), abs=3e-3)
    if scheme == "implicit" and h == 0.2:
        assert triangles[1] > 2.4 * triangles[0] > 0.1


@pytest.mark.parametrize("scheme", ["explicit", "implicit"])
def test_expected_cv_error_between_the_tables_steps_is_the_simulated_one(converged_cv, scheme):
    """At dt = 0.01, between the table's steps 0.0075 and 0.015, and h = 0.075, between two of
    its rows, the CV error the resolution report states (interpolated in both) is the one a
    planar front shows, within 0.2 points; the error the table holds for dt = 0.03 is not (the
    step's share of the error is larger than that)."""
    h, dt = 0.075, 0.01
    ratio = h * np.sqrt(2) / np.sqrt(D * TAU_IN)
    error = front_speed(h, dt, tau_close=TAU_CLOSE, scheme=scheme) / converged_cv - 1
    assert error == pytest.approx(expected_cv_error(scheme, ratio, dt=dt), abs=2e-3)
    assert abs(error - expected_cv_error(scheme, ratio, dt=DT)) > 2e-3


@pytest.mark.parametrize("cell_type", ["quadrilateral", "triangle"])
def test_a_task_checks_the_explicit_limit_on_a_small_copy_of_its_mesh(cell_type):
    """The stability limit a task's config checks before any mesh is built (on 4 x 4 cells of
    the same side) is the simulator's on the whole mesh (24 x 24 cells)."""
    from physicsrl.envs.task import SquareMesh

    square = SquareMesh(24, 50.0, cell_type)
    coordinator = Coordinator(MPI.COMM_SELF)
    ms = MonodomainMitchellSchaeffer(coordinator, square.create(MPI.COMM_SELF), scheme="explicit")
    assert square.explicit_limit(D) == pytest.approx(ms._explicit.dt_max, rel=1e-12)


def test_explicit_scheme_refuses_an_unstable_dt():
    """On 100 x 100 cells of the unit square (h = 0.01) the explicit limit is
    3 h^2 / (8 D) = 2.9e-3 (Gershgorin): dt = 0.03 is refused with one line naming dt, the
    limit and the mesh; 11 sub-steps of 0.03 / 11 run, and a step of u = 0 stays 0."""
    domain = mesh.create_unit_square(MPI.COMM_WORLD, 100, 100, mesh.CellType.quadrilateral)
    with pytest.raises(ValueError, match=r"dt / substeps = 0\.03 .* 0\.002885 .*10000 cells") as e:
        MonodomainMitchellSchaeffer(Coordinator(), domain, scheme="explicit")
    assert "\n" not in str(e.value)
    ms = MonodomainMitchellSchaeffer(Coordinator(), domain, scheme="explicit", substeps=11)
    assert ms._explicit.dt_max == pytest.approx(3 * 0.01**2 / (8 * D), rel=1e-9)
    with ms.coordinator:
        ms.advance_time(DT)
    assert ms.t == pytest.approx(DT) and not ms.u_n().x.array.any()
    with pytest.raises(ValueError, match="substeps"):
        MonodomainMitchellSchaeffer(Coordinator(), domain, substeps=2)
    ms = MonodomainMitchellSchaeffer(
        Coordinator(), domain, scheme="explicit", substeps=np.int64(11)
    )
    assert type(ms.substeps) is int
    with pytest.raises(ValueError, match="scheme"):
        MonodomainMitchellSchaeffer(Coordinator(), domain, scheme="crank-nicolson")


def reentry(n: int = 60, stimulus_time: float = 30.0) -> MonodomainMitchellSchaeffer:
    """The report's reentry set-up (section 4.3.3) on n x n Q1 cells: u = 0,
    w = min(-x/20, 1) for x < 0 else 0, I_app = 50 on |x| < 5, y > 0 for ``stimulus_time``."""
    return MonodomainMitchellSchaeffer(
        Coordinator(),
        physicsrl.fem.default_ms_mesh(n=n),
        u0=0.0,
        w0=lambda x: np.where(x[0] < 0, np.minimum(-x[0] / 20, 1), 0.0),
        I_app=lambda x: np.where((np.abs(x[0]) < 5) & (x[1] > 0), 50.0, 0.0),
    )


def topological_charges(ms: MonodomainMitchellSchaeffer) -> np.ndarray:
    """Winding numbers of the phase atan2(w - 1/2, u - 1/2) around every grid square of a
    structured Q1 mesh (serial): +-1 at a phase singularity (a spiral's tip), 0 elsewhere."""
    xy = ms.V.tabulate_dof_coordinates()[:, :2]
    order = np.lexsort((xy[:, 0], xy[:, 1]))
    side = round(np.sqrt(len(order)))
    phase = np.arctan2(ms.w_n().x.array - 0.5, ms.u_n().x.array - 0.5)[order].reshape(side, side)
    loop = [phase[:-1, :-1], phase[:-1, 1:], phase[1:, 1:], phase[1:, :-1], phase[:-1, :-1]]
    total = sum(np.angle(np.exp(1j * (b - a))) for a, b in zip(loop[:-1], loop[1:], strict=True))
    return np.rint(total / (2 * np.pi)).astype(int)


def test_reentry_forms_a_persistent_spiral(tmp_path):
    """After the report's S1-S2 stimulus (30 time units) the wave re-enters: the centre and the
    centres of the four quadrants are each excited (u rising through 1/2, sampled every 3 time
    units) at least twice by t = 450, where a wave that does not rotate passes each point once
    and leaves the domain within about 450; and at t = 450 the excitation persists and its
    phase field has singularities (nonzero winding numbers: spiral tips). The net winding
    number at a given time is not checked: on this grid (h/width 38) tips pair and meet the
    boundary, so it changes with the CPU's rounding (+1 at t = 450 on earlier machines, 0 on an
    AVX-512 Xeon). The same set-up with w = 1 everywhere (no refractory side: a wave that does
    not re-enter) excites these points at most once and dies out."""
    ms = reentry()
    xy = ms.V.tabulate_dof_coordinates()[:, :2]
    centres = np.array([(0, 0), (25, 25), (-25, 25), (-25, -25), (25, -25)])
    probes = [int(np.argmin(((xy - c) ** 2).sum(axis=1))) for c in centres]
    excited = np.zeros(len(probes), dtype=int)
    with ms.coordinator:
        ms.advance_time(30.0)
        ms.set_I_app(0.0)
        before = ms.u_n().x.array[probes]
        for _ in range(140):
            ms.advance_time(3.0)
            now = ms.u_n().x.array[probes]
            excited += (before < 0.5) & (now >= 0.5)
            before = now
        assert excited.min() >= 2, excited
        assert (ms.u_n().x.array > 0.5).mean() > 0.1
        assert np.count_nonzero(topological_charges(ms)) >= 1
    plot_field(ms.u_n(), tmp_path / "u.png", "u", t=ms.t)
    assert (tmp_path / "u.png").stat().st_size > 1000


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"dt": 0.0}, "dt"),
        ({"tau_in": -0.3}, "tau_in"),
        ({"tau_close": float("inf")}, "tau_close"),
        ({"D": 0}, "D"),
        ({"u_gate": float("nan")}, "u_gate"),
        ({"u0": lambda x: np.ones(3)}, "u0"),
        ({"w0": float("nan")}, "w0"),
        ({"I_app": lambda x: np.full(x.shape[1], np.inf)}, "I_app"),
        ({"dt": True}, "dt"),
        ({"quadrature_degree": -1}, "quadrature_degree"),  # crashed the process (SIGFPE)
        ({"quadrature_degree": 2.5}, "quadrature_degree"),
        ({"scheme": "explicit", "substeps": True}, "substeps"),
    ],
)
def test_bad_input_raises_value_error_naming_it(kwargs, name):
    domain = mesh.create_unit_square(MPI.COMM_WORLD, 2, 2, mesh.CellType.quadrilateral)
    with pytest.raises(ValueError, match=name):
        MonodomainMitchellSchaeffer(Coordinator(), domain, **kwargs)


def test_setters_reset_and_divergence():
    """set_I_app acts from the next step, reset returns to (u0, w0); a time step far beyond
    the explicit reaction's stability limit makes u overflow: SimulationDiverged."""
    domain = mesh.create_unit_square(MPI.COMM_WORLD, 2, 2, mesh.CellType.quadrilateral)
    ms = MonodomainMitchellSchaeffer(Coordinator(), domain, u0=0.0, w0=1.0)
    with ms.coordinator:
        ms.advance_time(0.03)
        np.testing.assert_allclose(ms.u_n().x.array, 0.0, atol=1e-14)
        ms.set_I_app(10.0)
        ms.advance_time(0.03)
        np.testing.assert_allclose(ms.u_n().x.array, 0.3, rtol=1e-9)
        with pytest.raises(ValueError, match="I_app"):
            ms.set_I_app(lambda x: np.zeros((x.shape[1], 2)))
        ms.reset()
        assert ms.t == 0.0
        np.testing.assert_array_equal(ms.u_n().x.array, 0.0)
        np.testing.assert_array_equal(ms.w_n().x.array, 1.0)

    unstable = MonodomainMitchellSchaeffer(Coordinator(), domain, u0=2.0, w0=1.0, dt=5.0)
    with unstable.coordinator:
        with pytest.raises(SimulationDiverged):
            unstable.advance_time(50.0)


def _rhs_vectors(domain, degree=1):
    """The right-hand side vectors of the C kernel, the numpy kernel and the UFL form for
    random u, w and a random piecewise constant I_app (all paths on the same mesh and values)."""
    from dolfinx import fem

    V = fem.functionspace(domain, ("Lagrange", degree))
    vectors = []
    for rhs in ("compiled", "numpy", "form"):
        ms = MonodomainMitchellSchaeffer(Coordinator(), domain, V, rhs=rhs, dt=0.05)
        u, w, current = ms.u_n(), ms.w_n(), ms._I_app
        state = np.random.default_rng(7)
        u.x.array[:] = state.uniform(-0.2, 1.2, u.x.array.size)
        w.x.array[:] = state.uniform(0.0, 1.0, w.x.array.size)
        current.x.array[:] = state.uniform(0.0, 50.0, current.x.array.size)
        b = np.zeros(ms.problem._b.array.size)
        if rhs == "compiled":
            assert ms.rhs._kernels is not None  # a C compiler is part of the test environment
        if rhs != "form":
            ms.rhs(b)
        else:
            fem.assemble_vector(b, ms.problem._L)
        vectors.append(b)
    return vectors


@pytest.mark.parametrize(
    "cell, degree, perturb",
    [
        (mesh.CellType.quadrilateral, 1, False),
        (mesh.CellType.quadrilateral, 1, True),  # non-affine cells: |det J| per point
        (mesh.CellType.quadrilateral, 2, False),
        (mesh.CellType.triangle, 1, False),
        (mesh.CellType.triangle, 2, True),
    ],
)
def test_kernel_rhs_equals_the_form_rhs(cell, degree, perturb):
    """The C kernel (default ``rhs="compiled"``) and the numpy kernel (``rhs="numpy"``)
    compute the same quadrature sum as DOLFINx's assembly of the UFL form (``rhs="form"``):
    equal to 1e-12 relative on straight and distorted quadrilaterals and triangles, degrees 1
    and 2."""
    domain = mesh.create_rectangle(MPI.COMM_WORLD, [[0, 0], [2, 1]], [7, 5], cell)
    if perturb:
        x = domain.geometry.x
        x[:, 0] += 0.03 * np.sin(3 * x[:, 0]) * np.sin(np.pi * x[:, 1])
        x[:, 1] += 0.02 * np.sin(5 * x[:, 0]) * np.sin(np.pi * x[:, 1])
    compiled, numpy, theirs = _rhs_vectors(domain, degree)
    scale = np.abs(theirs).max()
    assert scale > 0
    np.testing.assert_allclose(compiled, theirs, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(numpy, theirs, rtol=0, atol=1e-12 * scale)


def test_kernel_and_form_paths_give_the_same_simulation():
    """The report's reentry set-up on 20 x 20 cells, 60 steps (30 with the stimulus): u and w
    agree to 1e-12 between the C kernel (with the compiled gate update), the numpy kernel and
    the form assembly."""
    domain = physicsrl.fem.default_ms_mesh(n=20)
    models = [
        MonodomainMitchellSchaeffer(
            Coordinator(),
            domain,
            u0=0.0,
            w0=lambda x: np.where(x[0] < 0, np.minimum(-x[0] / 20, 1), 0.0),
            I_app=lambda x: np.where((np.abs(x[0]) < 5) & (x[1] > 0), 50.0, 0.0),
            rhs=rhs,
        )
        for rhs in ("compiled", "numpy", "form")
    ]
    for ms in models:
        with ms.coordinator:
            ms.advance_time(30 * DT)
            ms.set_I_app(0.0)
            ms.advance_time(30 * DT)
    reference = models[-1]
    assert np.ptp(reference.u_n().x.array) > 0.5
    for ms in models[:-1]:
        np.testing.assert_allclose(ms.u_n().x.array, reference.u_n().x.array, rtol=0, atol=1e-12)
        np.testing.assert_allclose(ms.w_n().x.array, reference.w_n().x.array, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="rhs"):
        MonodomainMitchellSchaeffer(Coordinator(), domain, rhs="fortran")


@pytest.mark.parametrize("cell_type", ["quadrilateral", "triangle"])
def test_explicit_c_and_numpy_steps_agree(cell_type):
    """The explicit scheme's C pass and its numpy version (``rhs="numpy"``) give the same u, w
    to 1e-12 after the report's reentry set-up on 20 x 15 cells of side 5 (30 steps with the
    stimulus, 30 without). On quadrilaterals the C side is the structured-grid stencil
    (``ms_stencil``, the state in grid order; a grid need not be square), on triangles the
    general row pass (``ms_explicit``)."""
    domain = mesh.create_rectangle(
        MPI.COMM_WORLD, [[-50, -50], [50, 25]], [20, 15], getattr(mesh.CellType, cell_type)
    )
    models = [
        MonodomainMitchellSchaeffer(
            Coordinator(),
            domain,
            w0=lambda x: np.where(x[0] < 0, np.minimum(-x[0] / 20, 1), 0.0),
            I_app=lambda x: np.where((np.abs(x[0]) < 5) & (x[1] > 0), 50.0, 0.0),
            scheme="explicit",
            rhs=rhs,
        )
        for rhs in ("compiled", "numpy")
    ]
    for ms in models:
        with ms.coordinator:
            ms.advance_time(30 * DT)
            ms.set_I_app(0.0)
            ms.advance_time(31 * DT)  # odd: the stencil's result comes back from its buffer
    c, numpy = models
    assert c._kernels is not None and numpy._kernels is None
    assert (c._explicit.grid is not None) == (cell_type == "quadrilateral")
    assert np.ptp(c.u_n().x.array) > 0.5
    np.testing.assert_allclose(c.u_n().x.array, numpy.u_n().x.array, rtol=0, atol=1e-12)
    np.testing.assert_allclose(c.w_n().x.array, numpy.w_n().x.array, rtol=0, atol=1e-12)


@pytest.mark.parametrize("scheme", ["implicit", "explicit"])
def test_without_a_c_compiler_the_numpy_kernel_is_used(monkeypatch, tmp_path, scheme):
    """If the C kernels cannot be built, ``rhs="compiled"`` warns once and falls back to the
    numpy kernel and gate update (implicit) or the numpy explicit step, with the same step."""
    from physicsrl.fem import kernels

    def no_compiler(name, target, cdef, source):
        raise OSError("no C compiler")

    monkeypatch.setattr(kernels, "_loaded", False)
    monkeypatch.setattr(kernels, "_module", None)
    monkeypatch.setattr(kernels, "_build", no_compiler)
    monkeypatch.setenv("PHYSICSRL_CACHE_DIR", str(tmp_path))  # no cached module there
    domain = mesh.create_unit_square(MPI.COMM_WORLD, 4, 4, mesh.CellType.quadrilateral)
    with pytest.warns(RuntimeWarning, match="C kernels unavailable"):
        ms = MonodomainMitchellSchaeffer(
            Coordinator(), domain, u0=0.2, w0=1.0, I_app=3.0, scheme=scheme
        )
    assert ms._kernels is None
    with ms.coordinator:
        ms.advance_time(0.03)
    u, w = 0.2, 1.0
    du, dw = reaction(u, w)
    np.testing.assert_allclose(ms.u_n().x.array, u + DT * (du + 3.0), rtol=1e-9)
    np.testing.assert_allclose(ms.w_n().x.array, w + DT * dw, rtol=1e-12)
