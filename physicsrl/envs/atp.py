r"""The anti-tachycardia pacing (ATP) task (report section 4.3.4) on the monodomain
Mitchell-Schaeffer model (:class:`~physicsrl.fem.MonodomainMitchellSchaeffer`).

Time in the model's units (ms in the report), lengths in mm, u dimensionless. Durations are
rounded to whole time steps: with dt = 0.03 a decision interval of 50 is 1667 steps (50.01).

Reset (draws on the leader: ``c`` ~ U(``reset.centre_x``), ``h`` ~ U(``reset.half_width``),
``b`` ~ U(``reset.bottom``)): u0 = 0, w0 = min(-(x - c) / ``w_slope``, 1) for x < c else 0;
``reset.current`` applied on the rectangle \|x - c\| < h, y > b for ``stimulus_time``, then
``rest_time`` without current, so that a spiral runs when the agent starts. A draw whose state
is not finite is replaced by a new draw. With ``reset.pool`` > 0 the draws come from a fixed
pool of that many draws (generated from ``reset.pool_seed``), which makes snapshots pay off in
training too. Snapshots (:mod:`physicsrl.envs.snapshots`) skip the induction of draws seen
before.

Step: action 0 waits ``decision_interval``; action 1 shocks: ``shock.current`` on the disk of
radius ``shock.radius`` around ``shock.centre`` for ``shock.duration``, then no current for the
rest of the interval. Success when the integral of u over the domain is below
``success_threshold`` after a step. After ``max_decisions`` decisions without success, up to
``extra_waits`` further intervals are simulated within the same step (no action) to see whether
the arrhythmia stops by itself. The episode is *terminated* on success or after that (failure);
it is *truncated* with ``diverged`` set if the state stops being finite. Stimulus regions are
cell averages (:mod:`physicsrl.envs.regions`), the same on any number of ranks.

Events for the reward: ``shock``, ``success``, ``failure``, ``steps`` (decisions plus extra
waits so far).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import ClassVar

import numpy as np

from physicsrl.coordinated import Coordinator, parallel
from physicsrl.envs.baselines import atp_baselines
from physicsrl.envs.config import integer, interval, number, positive, vector
from physicsrl.envs.observations import Observation
from physicsrl.envs.regions import CellAverage, disk, half_plane_gate, rectangle_above
from physicsrl.envs.snapshots import SnapshotCache
from physicsrl.envs.task import TASKS, SquareMesh, Task, Transition
from physicsrl.fem import MonodomainMitchellSchaeffer, SimulationDiverged
from physicsrl.fem.integrals import WeightedIntegrals, form_rows

WAIT, SHOCK = 0, 1


@dataclass(frozen=True)
class MSModel:
    """Mitchell-Schaeffer parameters (report section 4.3): time constants, gate threshold,
    diffusivity (mm^2/ms) and time step."""

    dt: float = 0.03
    tau_in: float = 0.3
    tau_out: float = 6.0
    tau_open: float = 75.0
    tau_close: float = 80.0
    u_gate: float = 0.13
    D: float = 0.013

    def __post_init__(self):
        for name in ("dt", "tau_in", "tau_out", "tau_open", "tau_close", "D"):
            positive(name, getattr(self, name))
        number("u_gate", self.u_gate)


@dataclass(frozen=True)
class ResetStimulus:
    """How a reset induces the arrhythmia (see the module docstring)."""

    centre_x: tuple[float, float] = (-10.0, 10.0)
    half_width: tuple[float, float] = (2.0, 4.0)
    bottom: tuple[float, float] = (10.0, 30.0)
    w_slope: float = 20.0
    current: float = 50.0
    stimulus_time: float = 15.0
    rest_time: float = 85.0
    pool: int = 0
    pool_seed: int = 0

    def __post_init__(self):
        for name in ("centre_x", "bottom"):
            object.__setattr__(self, name, interval(name, getattr(self, name)))
        object.__setattr__(self, "half_width", interval("half_width", self.half_width, low=0.0))
        positive("w_slope", self.w_slope)
        number("current", self.current)
        number("stimulus_time", self.stimulus_time, low=0.0)
        number("rest_time", self.rest_time, low=0.0)
        integer("pool", self.pool)
        integer("pool_seed", self.pool_seed)


@dataclass(frozen=True)
class Shock:
    """The agent's shock: ``current`` on the disk (``centre``, ``radius``) for ``duration``."""

    current: float = 50.0
    centre: tuple[float, float] = (0.0, 25.0)
    radius: float = 25.0
    duration: float = 25.0

    def __post_init__(self):
        number("current", self.current)
        object.__setattr__(self, "centre", vector("centre", self.centre, 2))
        positive("radius", self.radius)
        number("duration", self.duration, low=0.0)


@dataclass(frozen=True)
class Snapshots:
    """Snapshot cache settings: at most ``capacity`` states (0: off), saved to / loaded from
    ``directory`` (null: memory only)."""

    capacity: int = 100
    directory: str | None = None

    def __post_init__(self):
        integer("capacity", self.capacity)
        if self.directory is not None and not isinstance(self.directory, str):
            raise ValueError(f"directory must be a path or null, got {self.directory!r}")


@dataclass(frozen=True)
class ATPConfig:
    """Settings of ``conf/env/ms.yaml`` (see the module docstring)."""

    mesh: SquareMesh = field(default_factory=lambda: SquareMesh(60, 50.0, "quadrilateral"))
    model: MSModel = field(default_factory=MSModel)
    reset: ResetStimulus = field(default_factory=ResetStimulus)
    shock: Shock = field(default_factory=Shock)
    decision_interval: float = 50.0
    success_threshold: float = 100.0
    max_decisions: int = 15
    extra_waits: int = 20
    region_quadrature_degree: int = 6
    snapshots: Snapshots = field(default_factory=Snapshots)

    def __post_init__(self):
        positive("decision_interval", self.decision_interval)
        number("success_threshold", self.success_threshold)
        integer("max_decisions", self.max_decisions, 1)
        integer("extra_waits", self.extra_waits)
        integer("region_quadrature_degree", self.region_quadrature_degree, 1)
        if self.shock.duration > self.decision_interval:
            raise ValueError(
                f"shock.duration must be <= decision_interval = {self.decision_interval}, "
                f"got {self.shock.duration!r}"
            )


@TASKS.register("atp")
class ATPTask(Task):
    """Simulator side of the ATP task (see the module docstring). Construct on every rank."""

    Config: ClassVar[type] = ATPConfig
    n_actions: ClassVar[int] = 2
    events: ClassVar[frozenset[str]] = frozenset({"shock", "success", "failure", "steps"})
    flags: ClassVar[tuple[str, ...]] = ("success",)
    pairs = ("catheter", "atp")
    action_counts = {"shocks": 1}

    def baselines(self, env, seeds, seed):
        return atp_baselines(env, seeds, seed)

    def __init__(self, coordinator: Coordinator, config: ATPConfig, observation: Observation):
        self.config, self.observation = config, observation
        self.max_steps = config.max_decisions
        domain = config.mesh.create(coordinator.comm)
        self.simulator = MonodomainMitchellSchaeffer(coordinator, domain, **asdict(config.model))
        self.register_coordinator(coordinator)
        V = self.simulator.V
        # Row 0: the integral of u over the domain (success test); then the observation's rows.
        self.integrals = WeightedIntegrals(V, np.vstack([form_rows(V, [1.0]), observation.rows(V)]))
        degree = config.region_quadrature_degree
        self.stimulus = CellAverage(domain, rectangle_above, 3, degree)
        shock = config.shock
        self.shock = CellAverage(domain, disk, 3, degree)(
            shock.current, *shock.centre, shock.radius
        ).copy()
        settings = repr((config.mesh, config.model, config.reset, degree))
        self.snapshots = SnapshotCache(
            config.snapshots.capacity, config.snapshots.directory, settings, coordinator.comm
        )
        self.snapshots.load(self.simulator.u_n().x.array.size)
        self.pool = self._pool()
        self.decisions = 0
        self.intervals = 0  # decision intervals simulated since the reset (with extra waits)

    # draws ---------------------------------------------------------------------------------
    def _uniform(self, rng: np.random.Generator) -> tuple[float, float, float]:
        r = self.config.reset
        return tuple(float(rng.uniform(*bounds)) for bounds in (r.centre_x, r.half_width, r.bottom))

    def _pool(self) -> list[tuple[float, float, float]]:
        rng = np.random.default_rng(self.config.reset.pool_seed)
        return [self._uniform(rng) for _ in range(self.config.reset.pool)]

    def draw(self, rng: np.random.Generator) -> tuple[float, float, float]:
        """(c, h, b): the centre, half-width and bottom of the reset stimulus."""
        return self.pool[int(rng.integers(len(self.pool)))] if self.pool else self._uniform(rng)

    # episodes --------------------------------------------------------------------------------
    def _induce(self, c: float, h: float, b: float) -> None:
        """Simulate the reset's induction from scratch (collective; may raise
        SimulationDiverged)."""
        r, sim = self.config.reset, self.simulator
        sim.set_initial_condition(0.0, half_plane_gate(c, r.w_slope))
        sim.reset()
        sim.set_I_app(self.stimulus(r.current, c, h, b))
        self._run(r.stimulus_time)
        sim.set_I_app(0.0)
        self._run(r.rest_time)

    def _restore(self, key: tuple) -> None:
        u, w = self.snapshots.get(key)
        sim = self.simulator
        sim.set_I_app(0.0)
        sim.u_n().x.array[:] = u
        sim.w_n().x.array[:] = w
        sim.problem.t = self.config.reset.stimulus_time + self.config.reset.rest_time

    @parallel
    def reset(self, c: float, h: float, b: float) -> np.ndarray | None:
        key = (c, h, b)
        if key in self.snapshots:
            self._restore(key)
        else:
            try:
                self._induce(c, h, b)
            except SimulationDiverged:
                return None
            self.snapshots.put(key, self.simulator.u_n().x.array, self.simulator.w_n().x.array)
        self.decisions = self.intervals = 0
        return self.integrals(self.simulator.u_n())[1:]

    @parallel
    def prefill(self, draws: list[tuple[float, float, float]]) -> int:
        """Induce and store the states of ``draws`` not yet cached; the number induced."""
        induced = 0
        for key in draws:
            if tuple(key) not in self.snapshots and self.reset(*key) is not None:
                induced += 1
        return induced

    @parallel
    def save_snapshots(self) -> None:
        """Write the snapshot cache to its directory (one file per rank)."""
        self.snapshots.save()

    def _run(self, duration: float) -> None:
        """Advance ``duration`` rounded to a whole number of steps (50 / 0.03 is not whole)."""
        dt = self.simulator.dt
        self.simulator.advance_time(round(duration / dt) * dt)

    def _advance(self, shock: bool) -> None:
        """One decision interval, with the shock at its start if ``shock``."""
        sim, dt = self.simulator, self.simulator.dt
        steps = round(self.config.decision_interval / dt)
        if shock:
            on = round(self.config.shock.duration / dt)
            sim.set_I_app(self.shock)
            sim.advance_time(on * dt)
            sim.set_I_app(0.0)
            steps -= on
        sim.advance_time(steps * dt)

    @parallel
    def step(self, action: int) -> Transition:
        if action not in (WAIT, SHOCK):
            raise ValueError(f"action must be 0 (wait) or 1 (shock), got {action!r}")
        shock = action == SHOCK
        self.decisions += 1
        self.intervals += 1
        try:
            self._advance(shock)
            values = self.integrals(self.simulator.u_n())
            success = values[0] < self.config.success_threshold
            if not success and self.decisions >= self.config.max_decisions:
                for _ in range(self.config.extra_waits):
                    self._advance(False)
                    self.intervals += 1
                    values = self.integrals(self.simulator.u_n())
                    if success := values[0] < self.config.success_threshold:
                        break
        except SimulationDiverged:
            events = {"shock": shock, "success": False, "failure": False, "steps": self.intervals}
            observation = np.zeros(self.observation.size)
            return Transition(observation, events, self.decisions, truncated=True, diverged=True)
        failure = not success and self.decisions >= self.config.max_decisions
        events = {
            "shock": shock,
            "success": bool(success),
            "failure": failure,
            "steps": self.intervals,
        }
        return Transition(
            values[1:],
            events,
            self.decisions,
            terminated=bool(success) or failure,
            flags={"success": bool(success)},
        )
