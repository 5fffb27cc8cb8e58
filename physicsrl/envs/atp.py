r"""The anti-tachycardia pacing (ATP) task (report section 4.3.4) on the monodomain
Mitchell-Schaeffer model (:class:`~physicsrl.fem.MonodomainMitchellSchaeffer`).

Time in the model's units (ms in the report), lengths in mm, u dimensionless. Durations are
rounded to whole time steps: with dt = 0.03 a decision interval of 50 is 1667 steps (50.01).

Reset (draws on the leader: ``c`` ~ U(``reset.centre_x``), ``h`` ~ U(``reset.half_width``),
``b`` ~ U(``reset.bottom``)): u0 = 0, w0 = min(-(x - c) / ``w_slope``, 1) for x < c else 0;
``reset.current`` applied on the rectangle \|x - c\| < h, y > b for ``stimulus_time``, then
``rest_time`` without current, so that a spiral runs when the agent starts (a pair [low, high]
draws the rest ~ U(low, high) too: the agent then takes over at a random phase of the
reentry). A draw whose state is not finite is replaced by a new draw. With ``reset.pool`` > 0
training's draws come from a fixed pool of that many draws (generated from
``reset.pool_seed``), which makes snapshots pay off in training too; held-out episodes
(:func:`~physicsrl.config.is_held_out` of the seed of the env's generator; an unseeded
generator's random entropy counts as its seed) still draw uniformly, so that an evaluation
never replays a training draw. Snapshots (:mod:`physicsrl.envs.snapshots`) skip the induction
of draws seen before.

That induction (``induction: report``) works only on coarse grids: the stimulated strip lies in
tissue with w < 0.2, which is not excitable, and only the grid's cell averages and numerical
diffusion carry the excitation into excitable tissue (on a 1000 x 1000 grid it dies out on most
draws; /work/shared/reference/physics-notes.md). ``induction: cross_field`` induces reentry by
physics, the S1-S2 cross-field protocol (``cross_field.*``): from rest (u = 0, w = 1), S1 is
``current`` on the strip y > ``s1_bottom`` for ``stimulus_time``, a planar wave travelling
down (-y) with a refractory tail ~20 mm long behind its front. At
``s1_time + delay`` (``delay`` ~ U(``s2_delay``)), S2 is ``current`` on the rectangle
x < ``edge``, y > ``bottom`` (``edge`` ~ U(``s2_edge``), ``bottom`` ~ U(``s2_bottom``)) for
``stimulus_time``: it excites the recovered tissue above the tail; the S2 wave cannot enter the
tail, and its end at (``edge``, the tail's top) curls into a spiral as the tail recovers.
``rest_time`` later the agent starts (a pair: drawn, as for the report's induction). The S1
state at ``s1_time`` is the same for every draw: it is simulated once per task and kept in
memory.

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

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields
from typing import ClassVar

import numpy as np

from physicsrl.checks import choice, integer, interval, number, positive, vector
from physicsrl.config import is_held_out
from physicsrl.coordinated import Coordinator, parallel
from physicsrl.envs.observations import Observation
from physicsrl.envs.regions import CellAverage, disk, half_plane_gate, rectangle_above
from physicsrl.envs.snapshots import SnapshotCache
from physicsrl.envs.task import TASKS, SquareMesh, Task, Transition
from physicsrl.fem import MonodomainMitchellSchaeffer, SimulationDiverged
from physicsrl.fem.integrals import WeightedIntegrals, form_rows
from physicsrl.fem.monodomain import SCHEMES
from physicsrl.fem.resolution import report

WAIT, SHOCK = 0, 1
BACKENDS = ("petsc", "torch")
"""``env.model.backend`` (the first is the default)."""
DTYPES = ("auto", "float64", "float32")
"""``env.model.dtype`` of the torch backend (auto: float32 on CUDA, float64 on the CPU)."""
TORCH_ONLY = ("device", "dtype", "compile", "induce_ahead")
"""The settings of ``env.model`` that only the torch backend reads."""


@dataclass(frozen=True)
class MSModel:
    """Mitchell-Schaeffer parameters (report section 4.3): time constants, gate threshold,
    diffusivity (mm^2/ms), time step, the time scheme with its sub-steps (see
    :class:`~physicsrl.fem.MonodomainMitchellSchaeffer`), whether to warn when the mesh
    does not resolve the front (:func:`physicsrl.fem.resolution.report`), and the backend of
    the time loop: ``petsc`` (DOLFINx/PETSc, distributed over the ranks of a group) or
    ``torch`` (:mod:`physicsrl.envs.batched`: ``replicas`` copies on one rank, on ``device``,
    in ``dtype``, through ``torch.compile`` with ``compile``: see
    :class:`~physicsrl.fem.batched.BatchedMonodomain`; with ``induce_ahead``, ``auto``
    meaning on a CUDA device, each induction also takes every other replica's next draw: on a
    GPU a small batch's step costs about a full one's)."""

    dt: float = 0.03
    tau_in: float = 0.3
    tau_out: float = 6.0
    tau_open: float = 75.0
    tau_close: float = 80.0
    u_gate: float = 0.13
    D: float = 0.013
    scheme: str = "implicit"
    substeps: int = 1
    warn_resolution: bool = True
    backend: str = BACKENDS[0]
    device: str = "cpu"
    dtype: str = DTYPES[0]
    compile: bool = False
    induce_ahead: bool | str = "auto"

    def __post_init__(self):
        for name in ("dt", "tau_in", "tau_out", "tau_open", "tau_close", "D"):
            positive(name, getattr(self, name))
        number("u_gate", self.u_gate)
        if self.scheme not in SCHEMES:
            raise ValueError(f"scheme must be one of {SCHEMES}, got {self.scheme!r}")
        if integer("substeps", self.substeps, 1) != 1 and self.scheme != "explicit":
            raise ValueError(
                f"substeps must be 1 unless scheme=explicit (the implicit scheme takes whole "
                f"steps of dt), got {self.substeps!r}"
            )
        if not isinstance(self.warn_resolution, bool):
            raise ValueError(f"warn_resolution must be true or false, got {self.warn_resolution!r}")
        choice("backend", self.backend, BACKENDS)
        choice("device", self.device, ("cpu", "cuda"))
        choice("dtype", self.dtype, DTYPES)
        if not isinstance(self.compile, bool):
            raise ValueError(f"compile must be true or false, got {self.compile!r}")
        if not (isinstance(self.induce_ahead, bool) or self.induce_ahead == "auto"):
            raise ValueError(f"induce_ahead must be true, false or auto, got {self.induce_ahead!r}")
        torch_only = [f for f in fields(self) if f.name in TORCH_ONLY]
        chosen = [  # false turns off what the PETSc backend does not do anyway
            f"{f.name}={getattr(self, f.name)}"
            for f in torch_only
            if getattr(self, f.name) not in (f.default, False)
        ]
        if self.backend != "torch" and chosen:
            raise ValueError(
                f"{' and '.join(chosen)} need{'s' if len(chosen) == 1 else ''} backend=torch "
                "(the PETSc backend runs in float64 on the CPU, with its own compiled kernels)"
            )

    def numerics(self) -> dict:
        """The simulator's keyword arguments: the parameters, dt, scheme and sub-steps."""
        settings = asdict(self)
        for name in ("warn_resolution", "backend", *TORCH_ONLY):
            del settings[name]
        return settings

    def torch_settings(self) -> dict:
        """:class:`~physicsrl.fem.batched.BatchedMonodomain`'s device, dtype and compilation."""
        dtype = None if self.dtype == DTYPES[0] else self.dtype
        return {"device": self.device, "dtype": dtype, "compiled": self.compile}


def rest_range(value) -> tuple[float, float]:
    """A ``rest_time`` setting as (low, high): a number t is (t, t), a fixed rest; a pair
    [low, high] is the range the rest is drawn from uniformly."""
    if isinstance(value, Sequence) and not isinstance(value, str):
        return interval("rest_time", value, low=0.0)
    rest = number("rest_time", value, low=0.0)
    return rest, rest


@dataclass(frozen=True)
class ResetStimulus:
    """How a reset induces the arrhythmia (see the module docstring)."""

    centre_x: tuple[float, float] = (-10.0, 10.0)
    half_width: tuple[float, float] = (2.0, 4.0)
    bottom: tuple[float, float] = (10.0, 30.0)
    w_slope: float = 20.0
    current: float = 50.0
    stimulus_time: float = 15.0
    rest_time: float | tuple[float, float] = 85.0  # a pair: drawn uniformly
    pool: int = 0
    pool_seed: int = 0

    def __post_init__(self):
        for name in ("centre_x", "bottom"):
            object.__setattr__(self, name, interval(name, getattr(self, name)))
        object.__setattr__(self, "half_width", interval("half_width", self.half_width, low=0.0))
        positive("w_slope", self.w_slope)
        number("current", self.current)
        number("stimulus_time", self.stimulus_time, low=0.0)
        object.__setattr__(self, "rest_time", rest_range(self.rest_time))
        integer("pool", self.pool)
        integer("pool_seed", self.pool_seed)


class ResetSampler:
    """``sampler(rng)`` -> the draws of a reset (:meth:`ATPTask.draw`): uniform in the ranges
    of the config's induction, or, for a training generator, one of a fixed pool of
    ``reset.pool`` such draws (generated from ``reset.pool_seed``). The rest before the first
    decision is the last draw."""

    def __init__(self, config: ATPConfig):
        if config.induction == "report":
            r = config.reset
            self.ranges, self.rest = (r.centre_x, r.half_width, r.bottom), r.rest_time
        else:
            f = config.cross_field
            self.ranges, self.rest = (f.s2_delay, f.s2_edge, f.s2_bottom), f.rest_time
        rng = np.random.default_rng(config.reset.pool_seed)
        self.pool = [self._uniform(rng) for _ in range(config.reset.pool)]

    def _uniform(self, rng: np.random.Generator) -> tuple[float, ...]:
        draws = tuple(float(rng.uniform(*bounds)) for bounds in self.ranges)
        low, high = self.rest  # a fixed rest takes no random number: the draws stay as they were
        return (*draws, float(rng.uniform(low, high)) if low < high else low)

    def __call__(self, rng: np.random.Generator) -> tuple[float, ...]:
        if self.pool and not is_held_out(rng.bit_generator.seed_seq.entropy):  # its seed
            return self.pool[int(rng.integers(len(self.pool)))]
        return self._uniform(rng)


@dataclass(frozen=True)
class CrossField:
    """The S1-S2 cross-field induction (see the module docstring); the defaults suit the
    domain [-50, 50]^2: the spiral forms in the upper half, under the shock."""

    s1_bottom: float = 48.0
    s1_time: float = 280.0
    s2_delay: tuple[float, float] = (0.0, 60.0)
    s2_edge: tuple[float, float] = (-15.0, 15.0)
    s2_bottom: tuple[float, float] = (10.0, 20.0)
    current: float = 50.0
    stimulus_time: float = 2.0
    rest_time: float | tuple[float, float] = 50.0  # a pair: drawn uniformly

    def __post_init__(self):
        number("s1_bottom", self.s1_bottom)
        number("s1_time", self.s1_time, low=0.0)
        object.__setattr__(self, "s2_delay", interval("s2_delay", self.s2_delay, low=0.0))
        for name in ("s2_edge", "s2_bottom"):
            object.__setattr__(self, name, interval(name, getattr(self, name)))
        number("current", self.current)
        number("stimulus_time", self.stimulus_time, low=0.0)
        if self.s1_time < self.stimulus_time:
            raise ValueError(
                f"s1_time must be >= stimulus_time = {self.stimulus_time} (S1 lasts "
                f"stimulus_time), got {self.s1_time!r}"
            )
        object.__setattr__(self, "rest_time", rest_range(self.rest_time))


INDUCTIONS = ("report", "cross_field")
"""How a reset induces the arrhythmia (the first is the default: the report's)."""


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
    """Snapshot cache settings: at most ``capacity`` states in memory (0: none), and a library
    of all of them in ``directory`` (null: none; see :mod:`physicsrl.envs.snapshots`)."""

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
    induction: str = INDUCTIONS[0]
    cross_field: CrossField = field(default_factory=CrossField)
    shock: Shock = field(default_factory=Shock)
    decision_interval: float = 50.0
    success_threshold: float = 100.0
    max_decisions: int = 15
    extra_waits: int = 20
    region_quadrature_degree: int = 6
    snapshots: Snapshots = field(default_factory=Snapshots)
    replicas: int = 1

    def __post_init__(self):
        positive("decision_interval", self.decision_interval)
        number("success_threshold", self.success_threshold)
        integer("max_decisions", self.max_decisions, 1)
        integer("extra_waits", self.extra_waits)
        integer("region_quadrature_degree", self.region_quadrature_degree, 1)
        choice("induction", self.induction, INDUCTIONS)
        integer("replicas", self.replicas, 1)
        if self.model.backend == "petsc" and self.replicas != 1:
            raise ValueError(
                f"replicas must be 1 with model.backend=petsc (replicas need model.backend="
                f"torch; more PETSc environments come from mpi.ranks), got {self.replicas!r}"
            )
        model = self.model
        if round(self.decision_interval / model.dt) < 1:
            raise ValueError(
                f"decision_interval must be at least one time step model.dt = {model.dt}, "
                f"got {self.decision_interval!r}"
            )
        step = model.dt / model.substeps
        if model.scheme == "explicit" and step > (limit := self.mesh.explicit_limit(model.D)):
            raise ValueError(
                f"model.dt / model.substeps = {step:g} exceeds the explicit scheme's stability "
                f"limit {limit:.4g} on {self.mesh.cells} x {self.mesh.cells} cells of side "
                f"{2 * self.mesh.extent / self.mesh.cells:g}: raise model.substeps or use "
                "model.scheme=implicit"
            )
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
    variables: ClassVar[tuple[str, ...]] = ("u", "w")
    action_counts = {"shocks": 1}

    @staticmethod  # the replicas of the torch backend use the class's hooks
    def baselines(env, seeds, seed):
        from physicsrl.envs.baselines import atp_baselines  # torch: imported on use

        return atp_baselines(env, seeds, seed)

    def __init__(self, coordinator: Coordinator, config: ATPConfig, observation: Observation):
        self.config, self.observation = config, observation
        self.max_steps = config.max_decisions
        domain = config.mesh.create(coordinator.comm)
        self.simulator = MonodomainMitchellSchaeffer(coordinator, domain, **config.model.numerics())
        report(self.simulator.resolution, config.model.warn_resolution)
        self.register_coordinator(coordinator)
        V = self.simulator.V
        # Row 0: the integral of u over the domain (success test); then the observation's rows.
        rows = np.vstack([form_rows(V, [1.0]), observation.rows(V)])
        read = self.variables.index(observation.variable)
        self.integrals = WeightedIntegrals(V, rows, [0] + [read] * observation.size)
        degree = config.region_quadrature_degree
        self.stimulus = CellAverage(domain, rectangle_above, 3, degree)
        shock = config.shock
        self.shock = CellAverage(domain, disk, 3, degree)(
            shock.current, *shock.centre, shock.radius
        ).copy()
        induction = config.reset if config.induction == "report" else config.cross_field
        settings = repr((config.mesh, config.model, induction, degree))
        self.snapshots = SnapshotCache(
            config.snapshots.capacity, config.snapshots.directory, settings, coordinator.comm
        )
        self.sampler = ResetSampler(config)
        self._s1_state: tuple[np.ndarray, np.ndarray] | None = None  # cross-field S1 at s1_time
        self.decisions = 0
        self.intervals = 0  # decision intervals simulated since the reset (with extra waits)

    def draw(self, rng: np.random.Generator) -> tuple[float, ...]:
        """The reset's draws: (c, h, b, rest), the centre, half-width and bottom of the
        stimulus and the rest after it (``induction: report``), or (delay, edge, bottom, rest)
        of S2 and the rest after it (``cross_field``)."""
        return self.sampler(rng)

    # episodes --------------------------------------------------------------------------------
    def _induce(self, *draws: float) -> None:
        """Simulate the reset's induction of ``draws`` (see :meth:`draw`) from scratch, but
        for the cross-field S1 once computed (collective; may raise SimulationDiverged)."""
        if self.config.induction == "cross_field":
            self._cross_field(*draws)
            return
        c, h, b, rest = draws
        r, sim = self.config.reset, self.simulator
        sim.set_initial_condition(0.0, half_plane_gate(c, r.w_slope))
        sim.reset()
        self._stimulate(self.stimulus(r.current, c, h, b), r.stimulus_time, rest)

    def _cross_field(self, delay: float, edge: float, bottom: float, rest: float) -> None:
        f, sim = self.config.cross_field, self.simulator
        far = self.config.mesh.extent
        if self._s1_state is None:
            sim.set_initial_condition(0.0, 1.0)
            sim.reset()
            strip = self.stimulus(f.current, 0.0, 2 * far, f.s1_bottom)
            self._stimulate(strip, f.stimulus_time, f.s1_time - f.stimulus_time)
            self._s1_state = (sim.u_n().x.array.copy(), sim.w_n().x.array.copy())
        self._set_state(*self._s1_state, f.s1_time)
        self._run(delay)
        # x < edge: the rectangle |x - c| < h with its left side beyond the domain.
        s2 = self.stimulus(f.current, -far, edge + far, bottom)
        self._stimulate(s2, f.stimulus_time, rest)

    def _stimulate(self, current, duration: float, rest: float) -> None:
        """Apply ``current`` for ``duration``, then nothing for ``rest``."""
        self.simulator.set_I_app(current)
        self._run(duration)
        self.simulator.set_I_app(0.0)
        self._run(rest)

    def _set_state(self, u: np.ndarray, w: np.ndarray, t: float) -> None:
        sim = self.simulator
        sim.set_I_app(0.0)
        sim.u_n().x.array[:] = u
        sim.w_n().x.array[:] = w
        sim.problem.t = t

    def _start_time(self, draws: tuple) -> float:
        """The model time at which the agent starts after a reset with ``draws``: the
        induction's durations, each in whole steps as :meth:`_run` runs them."""
        dt = self.simulator.dt
        if self.config.induction == "report":
            start, durations = 0.0, (self.config.reset.stimulus_time, draws[3])
        else:
            f = self.config.cross_field
            start, durations = f.s1_time, (draws[0], f.stimulus_time, draws[3])
        return start + sum(round(duration / dt) for duration in durations) * dt

    @parallel
    def reset(self, *draws: float) -> np.ndarray | None:
        key = tuple(draws)
        if key in self.snapshots:
            self._set_state(*self.snapshots.get(key), self._start_time(key))
        else:
            try:
                self._induce(*key)
            except SimulationDiverged:
                return None
            self.snapshots.put(key, self.simulator.u_n().x.array, self.simulator.w_n().x.array)
            self.simulator.problem.t = self._start_time(key)  # as a restored reset's, exactly
        self.decisions = self.intervals = 0
        return self.integrals_now()[1:]

    @parallel
    def prefill(self, draws: list[tuple[float, float, float]]) -> int:
        """Induce and store the states of ``draws`` not yet cached; the number induced."""
        induced = 0
        for key in draws:
            if tuple(key) not in self.snapshots and self.reset(*key) is not None:
                induced += 1
        return induced

    def integrals_now(self) -> np.ndarray:
        return self.integrals(self.simulator.u_n(), self.simulator.w_n())

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
            values = self.integrals_now()
            success = values[0] < self.config.success_threshold
            if not success and self.decisions >= self.config.max_decisions:
                for _ in range(self.config.extra_waits):
                    self._advance(False)
                    self.intervals += 1
                    values = self.integrals_now()
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
