"""The batched torch time loop against the DOLFINx/PETSc and compiled C paths."""

from __future__ import annotations

import physicsrl.fem  # noqa: F401  (first: loads the MPI library that dolfinx links to)

# isort: split

import numpy as np
import pytest
import torch
from dolfinx import mesh
from mpi4py import MPI

from physicsrl.coordinated import Coordinator
from physicsrl.envs.atp import MSModel
from physicsrl.envs.regions import half_plane_gate
from physicsrl.envs.task import SquareMesh
from physicsrl.fem import InvalidValue, MonodomainMitchellSchaeffer
from physicsrl.fem.batched import BatchedMonodomain
from physicsrl.fem.resolution import planar_front_speed

MODEL = MSModel().numerics()  # the report's parameters (implicit)
DT = MODEL["dt"]


def induction(c):
    """Replica c's initial state and current: the ATP reset's gate ramp and a stimulus strip."""
    return (
        0.0,
        half_plane_gate(c, 20.0),
        lambda x: np.where((np.abs(x[0] - c) < 3.0) & (x[1] > 10.0), 50.0, 0.0),
    )


@pytest.mark.parametrize("cell", ["quadrilateral", "triangle"])
@pytest.mark.parametrize("scheme", ["implicit", "explicit"])
def test_replicas_equal_the_dolfinx_path(scheme, cell):
    """Three replicas with different initial gates and stimuli, 150 steps with the current then
    60 without, on 24 x 18 cells of [-50, 50] x [-50, 25] (a grid need not be square for the
    structured paths): each replica equals its own run of
    MonodomainMitchellSchaeffer on the same draws. Implicit: the PETSc path (CG + ICC, rtol
    1e-10) against the direct solve (quadrilaterals: a structured grid) or the batched CG +
    Jacobi (triangles; rtol 1e-10), so they agree to the tolerance of the PETSc path's own 1
    vs 2 rank tests, 1e-6 (u is O(1); measured: 1.1e-7); explicit: the compiled C pass, to
    round-off (1e-12), with the 9-point stencil on quadrilaterals and the CSR product on
    triangles."""
    domain = mesh.create_rectangle(
        MPI.COMM_SELF, [[-50, -50], [50, 25]], [24, 18], getattr(mesh.CellType, cell)
    )
    batched = BatchedMonodomain(domain, **{**MODEL, "scheme": scheme}, device="cpu")
    assert (batched._grid is not None) == (cell == "quadrilateral")
    centres = (-8.0, 0.0, 6.5)
    expected_u, expected_w, currents = [], [], []
    for c in centres:
        u0, w0, stimulus = induction(c)
        ms = MonodomainMitchellSchaeffer(
            Coordinator(MPI.COMM_SELF), domain, u0=u0, w0=w0, I_app=stimulus, scheme=scheme
        )
        currents.append(ms._I_app.x.array.copy())
        with ms.coordinator:
            ms.advance_time(150 * DT)
            ms.set_I_app(0.0)
            ms.advance_time(60 * DT)
        expected_u.append(ms.u_n().x.array.copy())
        expected_w.append(ms.w_n().x.array.copy())
    u = torch.zeros(len(centres), batched.num_dofs, dtype=torch.float64)
    w = torch.stack([batched.nodal(induction(c)[1]) for c in centres])
    batched.advance(u, w, torch.tensor(np.array(currents)), 150)
    batched.advance(u, w, None, 60)
    assert np.abs(np.array(expected_u)).max() > 0.5  # the stimulus excited the tissue
    tolerance = 1e-6 if scheme == "implicit" else 1e-12
    np.testing.assert_allclose(u.numpy(), expected_u, rtol=0, atol=tolerance)
    np.testing.assert_allclose(w.numpy(), expected_w, rtol=0, atol=tolerance)


def planar_wave(dtype, scheme="explicit", samples=1200, every=10, cells=150, length=15.0):
    """The scheme on the strip [0, length] x [0, length / cells] (h = 0.1), u = 1 on
    x < 1 at t = 0: (conduction velocity between x = 5 and x = 10, action potential duration
    at x = 10), from the times u crosses 0.5 (linear interpolation between samples taken
    every ``every`` steps)."""
    domain = mesh.create_rectangle(
        MPI.COMM_SELF,
        [[0.0, 0.0], [length, length / cells]],
        [cells, 1],
        mesh.CellType.quadrilateral,
    )
    sim = BatchedMonodomain(domain, **{**MODEL, "scheme": scheme}, device="cpu", dtype=dtype)
    x = sim.V.tabulate_dof_coordinates()[:, 0]
    probes = [int(np.flatnonzero(np.isclose(x, p))[0]) for p in (5.0, 10.0)]
    u = sim.nodal(lambda x: (x[0] < 1.0).astype(float))[None].clone()
    w = torch.ones_like(u)
    trace = np.empty((samples + 1, 2))
    trace[0] = u[0, probes].numpy()
    for n in range(samples):
        sim.advance(u, w, None, every)
        trace[n + 1] = u[0, probes].numpy()
    step = every * DT
    t = np.arange(samples + 1) * step

    def crossings(values):
        above = values >= 0.5
        up, down = np.flatnonzero(~above[:-1] & above[1:]), np.flatnonzero(above[:-1] & ~above[1:])
        assert len(up) == 1 and len(down) == 1, "one action potential expected at each probe"
        return [
            t[i] + (0.5 - values[i]) / (values[i + 1] - values[i]) * step for i in (up[0], down[0])
        ]

    (up_5, _), (up_10, down_10) = crossings(trace[:, 0]), crossings(trace[:, 1])
    return 5.0 / (up_10 - up_5), down_10 - up_10


@pytest.mark.parametrize("scheme", ["implicit", "explicit"])
def test_float32_conduction_velocity_and_apd_match_float64(scheme):
    """The CUDA default precision: a planar wave's conduction velocity and action potential
    duration in float32 are within 0.5% of float64; and the wave is the scheme's: its speed in
    float64 is the PETSc path's planar front speed at the same h and dt within 1% (the two
    measure it differently), its APD of the order of tau_close."""
    cv64, apd64 = planar_wave(torch.float64, scheme)
    cv32, apd32 = planar_wave(torch.float32, scheme)
    model = {key: value for key, value in MODEL.items() if key != "dt"} | {"scheme": scheme}
    petsc = planar_front_speed(0.1, DT, **model)
    assert cv64 == pytest.approx(petsc, rel=0.01)
    assert 100 < apd64 < 400, apd64
    assert abs(cv32 - cv64) < 0.005 * cv64, (cv32, cv64)
    assert abs(apd32 - apd64) < 0.005 * apd64, (apd32, apd64)


def test_explicit_refuses_an_unstable_step():
    domain = SquareMesh(60, 50.0, "quadrilateral").create(MPI.COMM_SELF)
    with pytest.raises(InvalidValue, match="dt / substeps = 100 exceeds"):
        BatchedMonodomain(domain, **{**MODEL, "scheme": "explicit", "dt": 100.0}, device="cpu")
    BatchedMonodomain(
        domain, **{**MODEL, "scheme": "explicit", "dt": 100.0, "substeps": 2}, device="cpu"
    )


def test_bad_arguments_are_refused_naming_them():
    """Settings and the arguments of a step: one :class:`InvalidValue` naming the value, and
    nothing advanced."""
    domain = SquareMesh(4, 50.0, "quadrilateral").create(MPI.COMM_SELF)
    for settings, name in [
        ({"threads": 0}, "threads"),
        ({"rtol": -1.0}, "rtol"),
        ({"dtype": "bogus"}, "dtype"),
        ({"scheme": "explicit", "substeps": True}, "substeps"),
    ]:
        with pytest.raises(InvalidValue, match=name):
            BatchedMonodomain(domain, **{**MODEL, **settings}, device="cpu")
    batched = BatchedMonodomain(domain, **MODEL, device="cpu")
    u = torch.zeros(2, batched.num_dofs, dtype=torch.float64)
    w = torch.ones_like(u)
    with pytest.raises(InvalidValue, match="T must"):
        batched.steps(-1.0)
    for arguments, name in [
        ((u, w, None, -3), "steps"),
        ((u, w, None, 2.5), "steps"),
        ((u[:, :-1], w[:, :-1], None, 1), "u and w"),
        ((u.float(), w.float(), None, 1), "u and w"),
        ((u, w, torch.zeros(2, 5), 1), "current"),
    ]:
        with pytest.raises(InvalidValue, match=name):
            batched.advance(*arguments)
    assert batched.replica_steps == batched.batch_steps == 0


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("compiled", [False, True])
@pytest.mark.parametrize("scheme", ["implicit", "explicit"])
def test_cuda_float32_follows_cpu_float64(scheme, compiled):
    """On a GPU (float32 by default, eager or compiled to Triton) each scheme follows the CPU
    float64 eager path to float32 accuracy over 200 steps of an excited state."""
    domain = SquareMesh(24, 50.0, "quadrilateral").create(MPI.COMM_SELF)
    _, w0, stimulus = induction(0.0)
    results = []
    for device in ("cpu", "cuda"):
        settings = {**MODEL, "scheme": scheme, "compiled": compiled and device == "cuda"}
        sim = BatchedMonodomain(domain, **settings, device=device)
        u = torch.zeros(2, sim.num_dofs, device=device, dtype=sim.dtype)
        w = torch.stack([sim.nodal(w0)] * 2)
        ms = MonodomainMitchellSchaeffer(Coordinator(MPI.COMM_SELF), domain, I_app=stimulus)
        current = sim.tensor(np.array([ms._I_app.x.array] * 2))
        sim.advance(u, w, current, 200)
        results.append(u.double().cpu().numpy())
    # float32 on the CPU differs from float64 by 9e-6 (implicit) and 2e-6 (explicit) of max |u|
    np.testing.assert_allclose(results[1], results[0], atol=5e-5 * np.abs(results[0]).max())


@pytest.mark.parametrize("scheme", ["implicit", "explicit"])
def test_compiled_steps_equal_the_eager_ones(scheme):
    """``compiled=True`` (torch.compile of the fused right-hand side, or of the stencil) gives
    the eager path's state to round-off: two replicas, 150 steps with a stimulus, 30 without,
    on 24 x 24 Q1 cells."""
    domain = SquareMesh(24, 50.0, "quadrilateral").create(MPI.COMM_SELF)
    _, w0, stimulus = induction(0.0)
    ms = MonodomainMitchellSchaeffer(Coordinator(MPI.COMM_SELF), domain, I_app=stimulus)
    results = []
    for compiled in (False, True):
        sim = BatchedMonodomain(domain, **{**MODEL, "scheme": scheme}, compiled=compiled)
        u = torch.zeros(2, sim.num_dofs, dtype=sim.dtype)
        w = torch.stack([sim.nodal(w0), sim.nodal(0.5)])
        sim.advance(u, w, sim.tensor(np.array([ms._I_app.x.array] * 2)), 150)
        sim.advance(u, w, None, 30)
        results.append((u.numpy(), w.numpy()))
    assert np.abs(results[0][0]).max() > 0.5  # excited
    for compiled, eager in zip(results[1], results[0], strict=True):
        np.testing.assert_allclose(compiled, eager, rtol=0, atol=1e-12)
