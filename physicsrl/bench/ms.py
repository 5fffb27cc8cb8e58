"""``physicsrl-bench ms``: steps of the monodomain Mitchell-Schaeffer model (report 4.3.3).

The report's benchmark on n x n Q1 cells of [-50, 50]^2, dt = 0.03: u = 0 and
w = min(-x/20, 1) for x < 0, 0 for x >= 0; I_app = 50 on |x| < 5, y > 0 during the first 30
steps, then 0 (the current is piecewise constant on cells and evaluated at cell midpoints, so
the region's edges, which run along mesh nodes, select the same cells on any rank count);
``steps`` steps, each one parallel ``advance_time(dt)`` call from the leader (so the
coordination column holds the per-call costs: the parallel call, the step-count check and the
finiteness check of u, not only per-step overhead); ``steps_per_call=k`` advances k steps per
call instead (as a task's decision does: 1667 steps), the steps of a call counted at its mean,
the first call's as the first step. physicsrl computes the right-hand side with its compiled C
kernel; ``rhs=numpy`` selects the numpy kernel and ``rhs=form`` DOLFINx's assembly of the
UFL form (the goals then judge that path). Run in the same job for physicsrl's schemes
(``scheme=implicit``, ``explicit`` or ``both``), with the explicit scheme for its floor
(:mod:`physicsrl.bench.ms_floor`: the fused structured-grid C loop alone on each rank's strip
of the same state; on one rank its final u is compared), and, unless ``baseline=false``, for
the port of the report's code (:mod:`physicsrl.baselines.report_fem`).

Per implementation: setup time (mesh excluded, forms, matrix, initial conditions), the first
step, the mean of the other steps split into linear solve, right-hand side, ionic (gate)
update (implicit), fused pass and ghost update (explicit) and coordination (the rest of the
leader's wall time: the parallel call, timers), the wall time of all steps (``run_s``), the
peak resident memory of each rank so far (``ru_maxrss``: cumulative, so the second
implementation's figure includes the first one's peak), and the largest difference of the
final u from physicsrl's (the first row's). Switching the current off after step 30 is not
timed. The first step includes the matrix's factorisation (ICC for physicsrl, LU for the baseline).
"""

from __future__ import annotations

import resource
import time

import numpy as np
from mpi4py import MPI

from physicsrl.baselines.report_coordinated import ReportCoordinator
from physicsrl.baselines.report_fem import ReportMonodomainMitchellSchaeffer
from physicsrl.bench.ms_floor import StructuredFloor
from physicsrl.coordinated import Coordinator
from physicsrl.fem import MonodomainMitchellSchaeffer, default_ms_mesh
from physicsrl.fem.monodomain import SCHEMES

DT = 0.03
EXTENT = 50.0
STIMULUS_STEPS = 30
PHASES = ("solve", "rhs", "ionic", "explicit", "ghosts")


def w0(x):
    return np.where(x[0] < 0, np.minimum(-x[0] / 20, 1.0), 0.0)


def stimulus(x):
    return np.where((np.abs(x[0]) < 5) & (x[1] > 0), 50.0, 0.0)


def no_current(x):
    return np.zeros(x.shape[1])


def calls(steps: int, per_call: int) -> list[tuple[int, int]]:
    """(first step, steps) of each call: ``per_call`` steps, fewer where the stimulus ends
    (after step STIMULUS_STEPS - 1) or the run does."""
    result, step = [], 0
    while step < steps:
        end = min(step + per_call, steps)
        if step < STIMULUS_STEPS < end:
            end = STIMULUS_STEPS
        result.append((step, end - step))
        step = end
    return result


def _time_steps(coordinator, model, steps: int, per_call: int) -> dict:
    """Run the benchmark's steps from the leader; return the leader's wall time of the first
    step and the mean wall time and phase times per step of the others, in milliseconds."""
    walls, after_first = [], {}
    with coordinator:
        if coordinator.is_leader():
            for step, count in calls(steps, per_call):
                if step == STIMULUS_STEPS:
                    model.set_I_app(no_current)
                start = time.perf_counter()
                model.advance_time(count * DT)
                walls += [(time.perf_counter() - start) / count] * count
                if step == 0:
                    after_first = dict(model.timings)
    return _summary(walls, model.timings, after_first, steps, calls(steps, per_call)[0][1])


def _summary(
    walls: list[float], timings: dict, after_first: dict, steps: int, first: int = 1
) -> dict:
    """The first call's (its ``first`` steps') and the other steps' mean wall time and phases
    per step, in ms, from the leader."""
    others = max(steps - first, 1)
    phases = {k: (v - after_first.get(k, 0.0)) / others * 1e3 for k, v in timings.items()}
    step = float(np.mean(walls[first:])) * 1e3 if len(walls) > first else float("nan")
    result = {"first_step_ms": walls[0] * 1e3 if walls else 0.0, "step_ms": step}
    result["run_s"] = float(np.sum(walls))
    result.update({f"{k}_ms": v for k, v in phases.items()})
    result["coordination_ms"] = step - sum(phases.values())
    return MPI.COMM_WORLD.bcast(result, root=0)


def _measure(name: str, build, steps: int, per_call: int) -> tuple[dict, object]:
    """Build (timed) and run one implementation; its row and the model."""
    comm = MPI.COMM_WORLD
    comm.Barrier()
    start = time.perf_counter()
    coordinator, model = build()
    comm.Barrier()
    setup = time.perf_counter() - start
    times = _time_steps(coordinator, model, steps, per_call)
    row = {
        "implementation": name,
        "ranks": comm.size,
        "dofs": model.u_n().function_space.dofmap.index_map.size_global,
        "steps": steps,
        "setup_s": round(setup, 3),
        "first_step_ms": round(times["first_step_ms"], 3),
        "step_ms": round(times["step_ms"], 4),
        "run_s": round(times["run_s"], 3),
    }
    for phase in (*PHASES, "coordination"):
        row[f"{phase}_ms"] = round(times.get(f"{phase}_ms", 0.0), 4)
    peaks = comm.allgather(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    row["peak_rss_mib"] = "/".join(f"{p:.0f}" for p in peaks)
    return row, model


def _floor(model, steps: int, per_call: int) -> dict | None:
    """The floor's row: the kernel alone on this rank's strip of the grid
    (:class:`StructuredFloor`), with the same initial state, current and steps as ``model``
    (built with the explicit scheme, not yet run), all ranks at once, no transfers and no halo
    exchange (each strip's edges mirrored: on several ranks only its time is comparable). Its
    final u (this rank's owned dofs) is compared with the model's on one rank. None where the
    model found no strips (fewer than two node rows per rank)."""
    comm = MPI.COMM_WORLD
    start = time.perf_counter()
    explicit = model._explicit
    if explicit.grid is None:
        return None
    strips, c = explicit.grid
    owned = explicit.owned
    floor = StructuredFloor(
        strips.shape[0] - 2,
        strips.width - 1,
        c,
        dt=DT,
        tau_in=float(model.tau_in.value),
        tau_out=float(model.tau_out.value),
        tau_open=model.tau_open,
        tau_close=model.tau_close,
        u_gate=model.u_gate,
    )
    floor.buffers[0][:] = strips.scatter(model.u_n().x.array[:owned])
    floor.w[:] = strips.scatter(model.w_n().x.array[:owned])[1:-1].ravel()
    floor.current = strips.scatter(explicit.current)[1:-1].ravel()
    setup = time.perf_counter() - start
    walls = []
    for step, count in calls(steps, per_call):
        if step == STIMULUS_STEPS:
            floor.current = None
        comm.Barrier()
        begin = time.perf_counter()
        floor.advance(count)
        wall = comm.allreduce(time.perf_counter() - begin, op=MPI.MAX)
        walls += [wall / count] * count
    times = _summary(walls, {}, {}, steps, calls(steps, per_call)[0][1])
    u = np.empty(owned)
    strips.gather(floor.buffers[0], u)
    return {
        "implementation": "floor (structured C loop)",
        "ranks": comm.size,
        "dofs": comm.allreduce(owned),
        "steps": steps,
        "setup_s": round(setup, 3),
        "first_step_ms": round(times["first_step_ms"], 3),
        "step_ms": round(times["step_ms"], 4),
        "run_s": round(times["run_s"], 3),
        "u": u,
    }


def run(cfg) -> list[dict]:
    """The rows (physicsrl's schemes, the floor, the baseline) of one benchmark run; the same
    on every rank."""
    n, steps, baseline = int(cfg.grid.n), int(cfg.steps), bool(cfg.baseline)
    per_call = int(cfg.steps_per_call)
    rhs = str(cfg.rhs)
    schemes = SCHEMES if cfg.scheme == "both" else (cfg.scheme,)  # checked by physicsrl-bench
    comm = MPI.COMM_WORLD
    domain = default_ms_mesh(comm, n, EXTENT)

    def ours(scheme):
        coordinator = Coordinator(comm)
        return coordinator, MonodomainMitchellSchaeffer(
            coordinator, domain, u0=0.0, w0=w0, I_app=stimulus, dt=DT, rhs=rhs, scheme=scheme
        )

    def theirs():
        coordinator = ReportCoordinator(comm)
        return coordinator, ReportMonodomainMitchellSchaeffer(
            coordinator, domain, no_current, w0, stimulus, dt=DT
        )

    builds = {
        ("physicsrl" if rhs == "compiled" else f"physicsrl (rhs={rhs})")
        + ("" if s == "implicit" else f" {s}"): (lambda s=s: ours(s))
        for s in schemes
    }
    if baseline:
        builds["report (baseline)"] = theirs
    rows, models = [], []
    for name, build in builds.items():
        floor = _floor(build()[1], steps, per_call) if name.endswith("explicit") else None
        row, model = _measure(name, build, steps, per_call)
        rows.append(row)
        models.append(model)
        if floor is not None:
            u = floor.pop("u")
            if comm.size == 1:
                floor["max_abs_diff_u"] = float(np.abs(u - model.u_n().x.array[: len(u)]).max())
            rows.append(floor)
            models.append(None)
    owned = models[0].u_n().function_space.dofmap.index_map.size_local
    reference = models[0].u_n().x.array[:owned]
    for row, model in zip(rows, models, strict=True):
        row["grid"] = f"{n}x{n}"
        if model is not None and model is not models[0]:
            difference = np.abs(model.u_n().x.array[:owned] - reference).max(initial=0)
            row["max_abs_diff_u"] = float(comm.allreduce(difference, op=MPI.MAX))
        row["speedup"] = round(rows[0]["step_ms"] / row["step_ms"], 2)
    return rows


def goals(rows: list[dict]) -> list[tuple[str, bool]]:
    """The issues' goals that this run measures, each with whether it was met."""
    by_name = {row["implementation"]: row for row in rows}
    first, grid, ranks = rows[0], rows[0]["grid"], rows[0]["ranks"]
    result = []
    ours = {  # physicsrl's rows, whichever right-hand side ("physicsrl (rhs=numpy) explicit")
        name.endswith(" explicit"): row
        for name, row in by_name.items()
        if name.startswith("physicsrl")
    }
    implicit, explicit = ours.get(False), ours.get(True)
    floor, report = by_name.get("floor (structured C loop)"), by_name.get("report (baseline)")
    if implicit and grid == "60x60" and ranks == 1:
        step = implicit["step_ms"]
        result.append((f"60x60, 1 rank: implicit {step} ms/step <= 0.3", step <= 0.3))
    if implicit and report:
        ratio = round(report["step_ms"] / implicit["step_ms"], 2)
        result.append((f"{grid}, {ranks} ranks: {ratio}x the baseline >= 10x", ratio >= 10))
    if implicit and explicit and grid == "1000x1000" and ranks == 1:
        ratio = round(implicit["step_ms"] / explicit["step_ms"], 1)
        result.append(
            (f"{grid}, 1 rank: explicit {ratio}x faster than implicit >= 25x", ratio >= 25)
        )
    if explicit and floor and grid == "1000x1000" and ranks == 1:
        ratio = round(explicit["step_ms"] / floor["step_ms"], 2)
        result.append((f"{grid}, 1 rank: explicit {ratio}x the floor <= 2.5x", ratio <= 2.5))
    if explicit and grid == "3000x3000" and ranks == 2 and first["steps"] == 100:
        run = explicit["run_s"]
        result.append((f"{grid}, 2 ranks, 100 steps: explicit {run} s <= 15 s", run <= 15))
    return result
