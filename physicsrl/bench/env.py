"""``physicsrl-bench env``: throughput of the ATP environment (issue 4).

One ATP episode (default task: 60 x 60 Q1, dt = 0.03, catheter observation) with a fixed
policy (shock at decisions 0, ``shock_every``, ...), ``decisions`` decisions long (success test
and extra waits off, so that every run simulates the same time; snapshots off, so the reset
induces), driven three ways on the same ranks:

- ``torchrl env``: ``env.rollout`` through :class:`~physicsrl.envs.PhysicsEnv`. The TorchRL
  overhead is the rollout's wall time minus the time inside the task's parallel calls (timed
  around them in the same run, so the figure is free of run-to-run noise), per step;
- ``task, direct``: the same task calls (one parallel ``reset``, one parallel ``step`` per
  decision) without TorchRL;
- ``report numerics`` (unless ``baseline=false``): the same draws and actions with the port of
  the report's simulator (:mod:`physicsrl.baselines.report_fem`: new expressions and a direct
  solver at every step, one coordinated call per time step) and the report's observation
  (a form per electrode built at every decision). It runs ``baseline_decisions`` decisions; its
  episode time is extrapolated to ``decisions``.

Columns: ``reset_s`` (inducing the arrhythmia, 100 time units), ``step_s`` (one decision, 50
time units), ``steps_per_s``, ``episode_s`` (reset + decisions), ``overhead_ms`` and
``overhead_pct`` (TorchRL, per step), ``speedup`` (report numerics' episode time / this row's).
"""

from __future__ import annotations

import time

import numpy as np
from mpi4py import MPI

from physicsrl.baselines.report_coordinated import ReportCoordinator
from physicsrl.baselines.report_fem import ReportMonodomainMitchellSchaeffer
from physicsrl.coordinated import Coordinator
from physicsrl.envs import load_config, make_env
from physicsrl.envs.baselines import Schedule

FIXED_LENGTH = ["env.success_threshold=-1e30", "env.extra_waits=0", "env.snapshots.capacity=0"]


class _Timed:
    """Wraps a bound method; accumulates the wall time spent in it."""

    def __init__(self, method):
        self.method, self.seconds = method, 0.0

    def __call__(self, *args):
        start = time.perf_counter()
        try:
            return self.method(*args)
        finally:
            self.seconds += time.perf_counter() - start


def _row(name: str, reset_s: float, step_s: float, decisions: int, **extra) -> dict:
    return {
        "driver": name,
        "ranks": MPI.COMM_WORLD.size,
        "decisions": decisions,
        "reset_s": round(reset_s, 3),
        "step_s": round(step_s, 4),
        "steps_per_s": round(1 / step_s, 3),
        "episode_s": round(reset_s + decisions * step_s, 2),
        **extra,
    }


# The report's numerics: callables picklable for its coordinator (module-level classes).
class _Gate:
    def __init__(self, c: float, slope: float):
        self.c, self.slope = c, slope

    def __call__(self, x):
        return np.clip(-(x[0] - self.c) / self.slope, 0.0, 1.0)


class _Rectangle:
    def __init__(self, current: float, c: float, h: float, b: float):
        self.current, self.c, self.h, self.b = current, c, h, b

    def __call__(self, x):
        return np.where((np.abs(x[0] - self.c) < self.h) & (x[1] > self.b), self.current, 0.0)


class _Disk:
    def __init__(self, current: float, centre, radius: float):
        self.current, self.centre, self.radius = current, tuple(centre), radius

    def __call__(self, x):
        inside = (x[0] - self.centre[0]) ** 2 + (x[1] - self.centre[1]) ** 2 < self.radius**2
        return np.where(inside, self.current, 0.0)


class _Zero:
    def __call__(self, x):
        return np.zeros(x.shape[1])


def _report_observation(model, positions: np.ndarray, mu: float) -> np.ndarray:
    """The report's catheter: one form per electrode, built at every call (collective)."""
    import ufl
    from dolfinx import fem

    domain, u = model.domain, model.u_n()
    x = ufl.SpatialCoordinate(domain)
    values = []
    for cx, cy in positions:
        kernel = ufl.exp(-mu * ufl.sqrt((x[0] - cx) ** 2 + (x[1] - cy) ** 2))
        values.append(fem.assemble_scalar(fem.form(kernel * u * ufl.dx)))
    values.append(fem.assemble_scalar(fem.form(u * ufl.dx)))
    return domain.comm.allreduce(np.array(values), op=MPI.SUM)


def _report_episode(env, draws, actions) -> tuple[float, float]:
    """Reset and ``actions`` with the report's numerics; (reset seconds, seconds per step)."""
    cfg, comm = env.task.config, MPI.COMM_WORLD
    r, s, m = cfg.reset, cfg.shock, cfg.model
    coordinator = ReportCoordinator(comm)
    model = ReportMonodomainMitchellSchaeffer(
        coordinator,
        cfg.mesh.create(comm),
        _Zero(),
        _Gate(draws[0], r.w_slope),
        _Zero(),
        tau_in=m.tau_in,
        tau_out=m.tau_out,
        tau_open=m.tau_open,
        tau_close=m.tau_close,
        u_gate=m.u_gate,
        D=m.D,
        dt=m.dt,
    )
    positions, mu = env.task.observation.positions(), env.task.observation.mu

    def run(duration):
        for _ in range(round(duration / m.dt)):
            model.advance_time(m.dt)

    times = []
    with coordinator:
        if coordinator.is_leader():
            start = time.perf_counter()
            model.set_I_app(_Rectangle(r.current, *draws[:3]))
            run(r.stimulus_time)
            model.set_I_app(_Zero())
            run(draws[3])
            times.append(time.perf_counter() - start)
            for action in actions:
                start = time.perf_counter()
                rest = cfg.decision_interval
                if action:
                    model.set_I_app(_Disk(s.current, s.centre, s.radius))
                    run(s.duration)
                    model.set_I_app(_Zero())
                    rest -= s.duration
                run(rest)
                times.append(time.perf_counter() - start)
    observe_time = _time_report_observation(model, positions, mu)
    times = comm.bcast(times, root=0)
    return times[0], float(np.mean(times[1:])) + observe_time


def _time_report_observation(model, positions, mu) -> float:
    """Seconds of one report-style observation, after one untimed call that fills the JIT
    cache (collective)."""
    comm = MPI.COMM_WORLD
    _report_observation(model, positions, mu)
    comm.Barrier()
    start = time.perf_counter()
    _report_observation(model, positions, mu)
    comm.Barrier()
    return comm.bcast(time.perf_counter() - start, root=0)


def run(cfg) -> list[dict]:
    comm = MPI.COMM_WORLD
    decisions = int(cfg.decisions)
    overrides = [*cfg.overrides, *FIXED_LENGTH, f"env.max_decisions={decisions}"]
    overrides.append(f"max_memory_gb={cfg.max_memory_gb}")
    coordinator = Coordinator(comm)
    env = make_env(load_config("ms", overrides=overrides, seed=int(cfg.seed)), coordinator)
    task = env.task
    policy = Schedule(range(0, decisions, int(cfg.shock_every)))
    actions = [int(d in policy.steps) for d in range(decisions)]
    draws = task.draw(np.random.default_rng(int(cfg.seed)))
    rows = []
    with coordinator:
        if coordinator.is_leader():
            # TorchRL rollout, with the task's parallel calls timed from inside.
            reset, step = _Timed(task.reset), _Timed(task.step)
            task.reset, task.step = reset, step
            env.set_seed(int(cfg.seed))
            start = time.perf_counter()
            rollout = env.rollout(decisions, policy, break_when_any_done=False)
            wall = time.perf_counter() - start
            del task.reset, task.step
            assert rollout["action"].tolist() == actions
            overhead = (wall - reset.seconds - step.seconds) / decisions
            env_step = (wall - reset.seconds) / decisions
            rows.append(
                _row(
                    "torchrl env",
                    reset.seconds,
                    env_step,
                    decisions,
                    overhead_ms=round(overhead * 1e3, 3),
                    overhead_pct=round(100 * overhead / env_step, 3),
                )
            )
            # The same task calls, directly.
            start = time.perf_counter()
            task.reset(*draws)
            reset_s = time.perf_counter() - start
            start = time.perf_counter()
            for action in actions:
                task.step(action)
            rows.append(
                _row("task, direct", reset_s, (time.perf_counter() - start) / decisions, decisions)
            )
    rows = comm.bcast(rows, root=0)
    if cfg.baseline:
        n = min(int(cfg.baseline_decisions), decisions)
        reset_s, step_s = _report_episode(env, draws, actions[:n])
        rows.append(_row("report numerics", reset_s, step_s, decisions, measured_decisions=n))
        for row in rows:
            row["speedup"] = round(rows[-1]["episode_s"] / row["episode_s"], 2)
    grid = f"{task.config.mesh.cells}x{task.config.mesh.cells}"
    for row in rows:
        row["grid"] = grid
    return rows


def goals(rows: list[dict]) -> list[tuple[str, bool]]:
    """The issue's goal: TorchRL's overhead at most 10% of a step."""
    env = rows[0]
    return [
        (
            f"TorchRL overhead {env['overhead_ms']} ms = {env['overhead_pct']}% of a step <= 10%",
            env["overhead_pct"] <= 10,
        )
    ]
