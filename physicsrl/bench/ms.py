"""``physicsrl-bench ms``: steps of the monodomain Mitchell-Schaeffer model (report 4.3.3).

The report's benchmark on n x n Q1 cells of [-50, 50]^2, dt = 0.03: u = 0 and
w = min(-x/20, 1) for x < 0, 0 for x >= 0; I_app = 50 on |x| < 5, y > 0 during the first 30
steps, then 0 (the current is piecewise constant on cells and evaluated at cell midpoints, so
the region's edges, which run along mesh nodes, select the same cells on any rank count);
``steps`` steps, each one parallel ``advance_time(dt)`` call from the leader (so the
coordination column holds the per-call costs: the parallel call, the step-count check and the
finiteness check of u, not only per-step overhead). physicsrl computes the right-hand side
with its compiled C kernel; ``+rhs=numpy`` selects the numpy kernel and ``+rhs=form``
DOLFINx's assembly of the UFL form. Run for
physicsrl and, unless ``baseline=false``, for the port of the report's code
(:mod:`physicsrl.baselines.report_fem`) in the same job.

Per implementation: setup time (mesh excluded, forms, matrix, initial conditions), the first
step, the mean of the other steps split into linear solve, right-hand side, ionic (gate)
update and coordination (the rest of the leader's wall time: the parallel call, timers), the
peak resident memory of each rank so far (``ru_maxrss``: cumulative, so the second
implementation's figure includes the first one's peak), and the largest difference of the
final u from physicsrl's. Switching the current off after step 30 is not timed. The first step
includes the matrix's factorisation (ICC for physicsrl, LU for the baseline).
"""

from __future__ import annotations

import resource
import time

import numpy as np
from mpi4py import MPI

from physicsrl.baselines.report_coordinated import ReportCoordinator
from physicsrl.baselines.report_fem import ReportMonodomainMitchellSchaeffer
from physicsrl.coordinated import Coordinator
from physicsrl.fem import MonodomainMitchellSchaeffer, default_ms_mesh

DT = 0.03
STIMULUS_STEPS = 30
SETTINGS = {"grid.n": (int, 2), "steps": (int, 1), "baseline": (bool, None)}


def w0(x):
    return np.where(x[0] < 0, np.minimum(-x[0] / 20, 1.0), 0.0)


def stimulus(x):
    return np.where((np.abs(x[0]) < 5) & (x[1] > 0), 50.0, 0.0)


def no_current(x):
    return np.zeros(x.shape[1])


def _time_steps(coordinator, model, steps: int) -> dict:
    """Run the benchmark's steps from the leader; return the leader's wall time of the first
    step and the mean wall time and phase times per step of the others, in milliseconds."""
    walls, after_first = [], {}
    with coordinator:
        if coordinator.is_leader():
            for step in range(steps):
                if step == STIMULUS_STEPS:
                    model.set_I_app(no_current)
                start = time.perf_counter()
                model.advance_time(DT)
                walls.append(time.perf_counter() - start)
                if step == 0:
                    after_first = dict(model.timings)
    others = max(steps - 1, 1)
    phases = {k: (v - after_first.get(k, 0.0)) / others * 1e3 for k, v in model.timings.items()}
    step = float(np.mean(walls[1:])) * 1e3 if len(walls) > 1 else float("nan")
    result = {"first_step_ms": walls[0] * 1e3 if walls else 0.0, "step_ms": step}
    result.update({f"{k}_ms": v for k, v in phases.items()})
    result["coordination_ms"] = step - sum(phases.values())
    return MPI.COMM_WORLD.bcast(result, root=0)


def _measure(name: str, build, steps: int) -> tuple[dict, object]:
    """Build (timed) and run one implementation; its row and the model."""
    comm = MPI.COMM_WORLD
    comm.Barrier()
    start = time.perf_counter()
    coordinator, model = build()
    comm.Barrier()
    setup = time.perf_counter() - start
    times = _time_steps(coordinator, model, steps)
    row = {
        "implementation": name,
        "ranks": comm.size,
        "dofs": model.u_n().function_space.dofmap.index_map.size_global,
        "steps": steps,
        "setup_s": round(setup, 3),
        "first_step_ms": round(times["first_step_ms"], 3),
        "step_ms": round(times["step_ms"], 4),
    }
    for phase in ("solve", "rhs", "ionic", "coordination"):
        row[f"{phase}_ms"] = round(times[f"{phase}_ms"], 4)
    peaks = comm.allgather(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    row["peak_rss_mib"] = "/".join(f"{p:.0f}" for p in peaks)
    return row, model


def run(cfg) -> list[dict]:
    """The rows (physicsrl, then the baseline) of one benchmark run; the same on every rank."""
    n, steps, baseline = int(cfg.grid.n), int(cfg.steps), bool(cfg.baseline)
    rhs = str(cfg.get("rhs", "compiled"))  # "+rhs=numpy" / "+rhs=form": the other paths
    comm = MPI.COMM_WORLD
    domain = default_ms_mesh(comm, n)

    def ours():
        coordinator = Coordinator(comm)
        return coordinator, MonodomainMitchellSchaeffer(
            coordinator, domain, u0=0.0, w0=w0, I_app=stimulus, dt=DT, rhs=rhs
        )

    def theirs():
        coordinator = ReportCoordinator(comm)
        return coordinator, ReportMonodomainMitchellSchaeffer(
            coordinator, domain, no_current, w0, stimulus, dt=DT
        )

    row, model = _measure(
        "physicsrl" if rhs == "compiled" else f"physicsrl (rhs={rhs})", ours, steps
    )
    row["grid"] = f"{n}x{n}"
    rows = [row]
    if baseline:
        row, other = _measure("report (baseline)", theirs, steps)
        row["grid"] = f"{n}x{n}"
        owned = model.u_n().function_space.dofmap.index_map.size_local
        difference = np.abs(other.u_n().x.array[:owned] - model.u_n().x.array[:owned]).max(
            initial=0
        )
        row["max_abs_diff_u"] = float(comm.allreduce(difference, op=MPI.MAX))
        rows.append(row)
        for r in rows:
            r["speedup"] = round(rows[1]["step_ms"] / r["step_ms"], 2)
    return rows


def goals(rows: list[dict]) -> list[tuple[str, bool]]:
    """The issue's goals, each with whether this run met it."""
    ours = rows[0]
    result = []
    if ours["grid"] == "60x60" and ours["ranks"] == 1:
        result.append((f"60x60, 1 rank: {ours['step_ms']} ms/step <= 0.3", ours["step_ms"] <= 0.3))
    if len(rows) > 1:
        speedup = ours["speedup"]
        result.append(
            (
                f"{ours['grid']}, {ours['ranks']} ranks: {speedup}x the baseline >= 10x",
                speedup >= 10,
            )
        )
    return result
