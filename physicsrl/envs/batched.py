r"""The ATP task with B replicas on one process: a TorchRL environment of ``batch_size=[B]``.

The task of :mod:`physicsrl.envs.atp` (same config, observation, reward, draws and events), its
time loop on torch (:class:`~physicsrl.fem.batched.BatchedMonodomain`, CPU or CUDA) for all
replicas at once, on this process's own copy of the mesh (``MPI.COMM_SELF``). Under MPI each
rank is a group of B replicas (``mpi.ranks_per_env=1``) and the learner sees N x B members
(:class:`~physicsrl.envs.groups.GroupedEnv`).

- Reset honours TorchRL's ``"_reset"`` mask: only the replicas it selects start a new episode
  (their rows of u and w are written from the snapshot library, or induced: the distinct new
  draws of the call in one batch, by either induction); the others keep their state. With
  ``env.model.induce_ahead`` (``auto``: on CUDA) that batch also induces the next draw of every
  other replica (read from a copy of its generator, so its episodes stay the same), and the
  replicas whose episodes end later start from those states: on a GPU, where a step of a few
  replicas costs about what a full batch's does, the episodes that end one by one then cost no
  induction.
- Step: every replica takes its action for one decision interval (shocks as a (B, cells)
  current on the replicas that shock); replicas that reach ``max_decisions`` without success
  run up to ``extra_waits`` further intervals in a sub-batch. A replica whose state stops being
  finite ends its episode as truncated with ``diverged`` set, as in
  :class:`~physicsrl.envs.env.PhysicsEnv`.
- Cost: :attr:`simulated` holds, per phase, the seconds spent so far, the replica-steps
  (steps of dt times replicas) simulated and the batch-steps (steps of dt, each advancing one
  batch, whatever its size: replica-steps / batch-steps is the phase's mean batch):
  ``induction`` (resets), ``decisions`` (every replica's interval and its observation) and
  ``waits`` (the last decision's sub-batch); training reports them.
- Seeds: the replicas are the members of a batch (:class:`~physicsrl.envs.members.Members`):
  replica i draws its episodes from its own generator, seeded with ``member_seed(seed, i)``,
  so replica i runs the episodes of :class:`~physicsrl.envs.env.PhysicsEnv` seeded with that
  seed (member i of N simulator groups): the same draws, and the same transitions to the
  solver's tolerance. Held-out seeds give the same evaluation rows on either backend.

Keys are those of :class:`~physicsrl.envs.env.PhysicsEnv` with a leading batch dimension B.
Built by :func:`physicsrl.envs.make_env` when ``env.model.backend`` is ``torch``.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

import numpy as np
import torch
from mpi4py import MPI
from torchrl.data import Bounded, Categorical, Composite, Unbounded

from physicsrl.envs.atp import SHOCK, WAIT, ATPConfig, ATPTask, ResetSampler
from physicsrl.envs.members import Members
from physicsrl.envs.observations import Observation
from physicsrl.envs.regions import CellAverage, disk, half_plane_gate, rectangle_above
from physicsrl.envs.rewards import Reward
from physicsrl.envs.snapshots import SnapshotCache
from physicsrl.envs.task import ResetDiverged
from physicsrl.fem.batched import BatchedMonodomain, per_replica
from physicsrl.fem.integrals import form_rows
from physicsrl.fem.resolution import report


class BatchedATPEnv(Members):
    """B replicas of the ATP task (see the module docstring).

    Parameters
    ----------
    config, observation, reward:
        As for :class:`~physicsrl.envs.atp.ATPTask` and :class:`~physicsrl.envs.env.PhysicsEnv`;
        B is ``config.replicas``, the device ``config.model.device``.
    seed:
        Seed of the batch (replica i: ``member_seed(seed, i)``; None: from the OS).
    max_reset_attempts:
        Draws tried per replica and reset before giving up when states come out non-finite.
    """

    task = ATPTask  # its hooks (baselines, action counts, scores) are class-level

    def __init__(
        self,
        config: ATPConfig,
        observation: Observation,
        reward: Reward,
        seed: int | None = None,
        max_reset_attempts: int = 10,
    ):
        missing = reward.events - ATPTask.events
        if missing:
            raise ValueError(f"reward.name {reward.name!r} reads events {sorted(missing)}")
        if config.model.backend != "torch":
            raise ValueError(f"env.model.backend must be torch, got {config.model.backend!r}")
        B = config.replicas
        super().__init__(B)
        self.config, self.observation, self.reward_fn = config, observation, reward
        self.max_reset_attempts = max_reset_attempts
        domain = config.mesh.create(MPI.COMM_SELF)
        model = config.model
        self.simulator = sim = BatchedMonodomain(
            domain, **model.numerics(), **model.torch_settings()
        )
        report(sim.resolution, model.warn_resolution)
        ahead = model.induce_ahead
        self.induce_ahead = sim.device.type == "cuda" if ahead == "auto" else ahead
        V = sim.V
        # row 0: the integral of u; then the observation's rows, of the variable it reads
        integral, readings = form_rows(V, [1.0]), observation.rows(V)
        if observation.variable == "u":
            self.rows = {"u": sim.tensor(np.vstack([integral, readings]))}
        else:
            self.rows = {"u": sim.tensor(integral), observation.variable: sim.tensor(readings)}
        degree = config.region_quadrature_degree
        self.stimulus = CellAverage(domain, rectangle_above, 3, degree)
        shock = config.shock
        disk_current = CellAverage(domain, disk, 3, degree)
        self.shock = sim.tensor(
            self._cells(disk_current(shock.current, *shock.centre, shock.radius))
        )
        self.sampler = ResetSampler(config)
        self._s1_state: tuple[torch.Tensor, torch.Tensor] | None = None  # cross-field S1
        induction = config.reset if config.induction == "report" else config.cross_field
        settings = repr((config.mesh, config.model, induction, degree, "torch"))
        self.snapshots = SnapshotCache(
            config.snapshots.capacity, config.snapshots.directory, settings, MPI.COMM_SELF
        )
        self.u = torch.zeros(B, sim.num_dofs, device=sim.device, dtype=sim.dtype)
        self.w = torch.ones_like(self.u)
        self.decisions = np.zeros(B, dtype=np.int64)
        self.intervals = np.zeros(B, dtype=np.int64)
        self.simulated = {phase: (0.0, 0, 0) for phase in ("induction", "decisions", "waits")}
        self.rngs: list[np.random.Generator] = [None] * B  # seeded below (member_seed)
        self._ahead: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}  # draw -> (u, w)

        flag = Categorical(2, shape=(B, 1), dtype=torch.bool)
        self.observation_spec = Composite(
            observation=Unbounded(shape=(B, observation.size), dtype=torch.float32),
            step=Bounded(0, config.max_decisions, shape=(B, 1), dtype=torch.int64),
            diverged=flag.clone(),
            success=flag.clone(),
            shape=(B,),
        )
        self.action_spec = Categorical(ATPTask.n_actions, shape=(B,))
        self.reward_spec = Unbounded(shape=(B, 1), dtype=torch.float32)
        self.done_spec = Composite(
            done=flag.clone(), terminated=flag.clone(), truncated=flag.clone(), shape=(B,)
        )
        self._set_seed(seed)

    # seeds ---------------------------------------------------------------------------------
    def seed_each(self, seeds: Sequence[int | None], indices: Sequence[int] | None = None):
        indices = range(self.batch_size[0]) if indices is None else indices
        for i, seed in zip(indices, seeds, strict=True):
            self.rngs[i] = np.random.default_rng(seed)

    def rng_state(self) -> list[dict]:
        return [rng.bit_generator.state for rng in self.rngs]

    def set_rng_state(self, states: Sequence[dict]) -> None:
        if len(states) != len(self.rngs):
            raise ValueError(f"{len(states)} generator states for {len(self.rngs)} replicas")
        for rng, state in zip(self.rngs, states, strict=True):
            rng.bit_generator.state = state

    # the simulation ----------------------------------------------------------------------
    def _integrals(self, rows: torch.Tensor | None) -> np.ndarray:
        """(replicas, K) of the replicas ``rows`` (None: all): row 0 the integral of u, then
        the observation (of u or w)."""
        state, values = {"u": self.u, "w": self.w}, []
        for variable, matrix in self.rows.items():
            x = state[variable] if rows is None else state[variable][rows]
            values.append(per_replica(matrix, x))
        return torch.cat(values, dim=1).double().cpu().numpy()

    def _run(self, u, w, current, duration: float) -> torch.Tensor:
        return self.simulator.advance(u, w, current, self.simulator.steps(duration))

    def _induce(self, draws: list[tuple[float, ...]]):
        """(u, w, finite: numpy) after the reset's induction of each draw (see
        :meth:`~physicsrl.envs.atp.ATPTask.draw`), in one batch: the stimuli together, each wait
        with the replicas still waiting; the cross-field S1 state is simulated once."""
        sim = self.simulator
        if self.config.induction == "report":
            r = self.config.reset
            w = torch.stack([sim.nodal(half_plane_gate(c, r.w_slope)) for c, *_ in draws])
            u = torch.zeros_like(w)
            stimuli = [(r.current, c, h, b) for c, h, b, _ in draws]
            finite = torch.ones(len(draws), dtype=torch.bool, device=u.device)
            duration = r.stimulus_time
        else:
            f, far = self.config.cross_field, self.config.mesh.extent
            u, w = (x.repeat(len(draws), 1) for x in self._s1())
            finite = self._wait(u, w, [delay for delay, *_ in draws])
            # x < edge: the rectangle |x - c| < h with its left side beyond the domain
            stimuli = [(f.current, -far, edge + far, bottom) for _, edge, bottom, _ in draws]
            duration = f.stimulus_time
        current = sim.tensor(np.array([self._cells(self.stimulus(*s)) for s in stimuli]))
        finite &= self._run(u, w, current, duration)
        finite &= self._wait(u, w, [rest for *_, rest in draws])
        return u, w, finite.cpu().numpy()

    def _s1(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(u, w), each (1, n): the cross-field S1 state at ``s1_time``, from rest."""
        if self._s1_state is None:
            f, sim = self.config.cross_field, self.simulator
            u = torch.zeros(1, sim.num_dofs, device=sim.device, dtype=sim.dtype)
            w = torch.ones_like(u)
            strip = self.stimulus(f.current, 0.0, 2 * self.config.mesh.extent, f.s1_bottom)
            self._run(u, w, sim.tensor(self._cells(strip)[None]), f.stimulus_time)
            self._run(u, w, None, f.s1_time - f.stimulus_time)
            self._s1_state = (u, w)
        return self._s1_state

    def _cells(self, function) -> np.ndarray:
        """The cell values (c,) of a DG0 function (its owned dofs, copied)."""
        return function.x.array[: self.simulator.num_cells].copy()

    def _wait(self, u, w, durations: Sequence[float]) -> torch.Tensor:
        """Advance replica j of ``u``, ``w`` by ``durations[j]`` without current, in place, the
        replicas still waiting together; whether each is finite, (B,) bool."""
        steps = np.array([self.simulator.steps(d) for d in durations])
        finite = torch.ones(len(steps), dtype=torch.bool, device=u.device)
        done = 0
        for s in np.unique(steps):
            rows = torch.as_tensor(np.flatnonzero(steps >= s), device=u.device)
            waiting_u, waiting_w = u[rows], w[rows]
            finite[rows] &= self.simulator.advance(waiting_u, waiting_w, None, int(s) - done)
            u[rows], w[rows] = waiting_u, waiting_w
            done = int(s)
        return finite

    def _start(self, replicas: list[int]) -> None:
        """New episodes for ``replicas``: each draws from its generator (again if the state
        comes out non-finite, as :class:`~physicsrl.envs.env.PhysicsEnv` does); rows of u and w
        from the states induced ahead, the snapshot library, or one batched induction of the
        draws in neither (with ``induce_ahead``, and the other replicas' next draws)."""
        pending = {i: 0 for i in replicas}  # replica -> attempts so far
        while pending:
            keys = {i: self.sampler(self.rngs[i]) for i in pending}
            new = [i for i in pending if not self._stored(keys[i])]
            fresh = set(new)
            for i in [i for i in pending if i not in fresh]:
                self.u[i], self.w[i] = self._take(keys[i])
                del pending[i]
            if not new:
                continue
            # each distinct draw induced once (policies compared on the same seeds share draws);
            # the induced states are used as they are: the library may keep fewer than len(new)
            draws = list(dict.fromkeys(keys[i] for i in new))
            ahead = self._next_draws(pending, draws) if self.induce_ahead else []
            with self._phase("induction"):
                u, w, finite = self._induce(draws + ahead)
            row = {key: j for j, key in enumerate(draws + ahead)}
            for key, j in row.items():
                if bool(finite[j]):
                    self.snapshots.put(key, u[j].cpu().numpy(), w[j].cpu().numpy())
            self._ahead.update(
                {key: (u[row[key]], w[row[key]]) for key in ahead if bool(finite[row[key]])}
            )
            for i in new:
                j = row[keys[i]]
                if bool(finite[j]):
                    self.u[i], self.w[i] = u[j], w[j]
                    del pending[i]
                    continue
                pending[i] += 1
                if pending[i] >= self.max_reset_attempts:
                    raise ResetDiverged(self.max_reset_attempts, f" (replica {i})")
        self.decisions[replicas] = 0
        self.intervals[replicas] = 0

    def _stored(self, key: tuple) -> bool:
        return key in self._ahead or key in self.snapshots

    def _take(self, key: tuple) -> tuple[torch.Tensor, torch.Tensor]:
        """(u, w) of the draw ``key``: induced ahead (kept for replicas that share the draw,
        until no replica comes to it next), else from the library."""
        if key in self._ahead:
            return self._ahead[key]
        return tuple(self.simulator.tensor(x) for x in self.snapshots.get(key))

    def _next_draws(self, pending: dict[int, int], inducing: list[tuple]) -> list[tuple]:
        """The next draw of each replica not in ``pending`` that is neither stored nor among the
        draws ``inducing``, from a copy of its generator (its own is not advanced); the states
        induced ahead for draws that no replica comes to next are dropped."""
        upcoming = [
            self.sampler(copy.deepcopy(rng)) for i, rng in enumerate(self.rngs) if i not in pending
        ]
        self._ahead = {key: self._ahead[key] for key in upcoming if key in self._ahead}
        return [k for k in dict.fromkeys(upcoming) if k not in inducing and not self._stored(k)]

    def _advance(self, rows: torch.Tensor | None, shocks: np.ndarray | None) -> np.ndarray:
        """One decision interval for the replicas ``rows`` (None: all), with the shock on those
        where ``shocks`` is true (None: none); their finite mask."""
        u, w = (self.u, self.w) if rows is None else (self.u[rows], self.w[rows])
        config, sim = self.config, self.simulator
        steps = sim.steps(config.decision_interval)
        finite = torch.ones(len(u), dtype=torch.bool, device=u.device)
        if shocks is not None and shocks.any():
            on = sim.steps(config.shock.duration)
            current = torch.as_tensor(shocks).to(sim.device, sim.dtype)[:, None] * self.shock
            finite &= sim.advance(u, w, current, on)
            steps -= on
        finite &= sim.advance(u, w, None, steps)
        if rows is not None:
            self.u[rows], self.w[rows] = u, w
        return finite.cpu().numpy()

    def _rows(self, index: np.ndarray) -> torch.Tensor | None:
        """``index`` as rows of u and w (None for all replicas in order: no copies)."""
        if len(index) == len(self.u) and (index == np.arange(len(index))).all():
            return None
        return torch.as_tensor(index, device=self.u.device)

    @contextmanager
    def _phase(self, name: str) -> Iterator[None]:
        """Add the seconds, replica-steps and batch-steps of the block to :attr:`simulated`
        [name] (the block ends by reading results back to the host, so a GPU's work is done by
        then)."""
        sim = self.simulator
        before = (time.perf_counter(), sim.replica_steps, sim.batch_steps)
        yield
        after = (time.perf_counter(), sim.replica_steps, sim.batch_steps)
        self.simulated[name] = tuple(
            total + b - a for total, a, b in zip(self.simulated[name], before, after, strict=True)
        )

    # members -------------------------------------------------------------------------------
    def _values(self, index: np.ndarray, observations, diverged, success) -> dict[str, np.ndarray]:
        """Per-key arrays (leading dimension len(index)) of the replicas ``index``."""
        column = lambda flags: np.asarray(flags, dtype=bool).reshape(-1, 1)  # noqa: E731
        return {
            "observation": np.asarray(observations, dtype=np.float32),
            "step": self.decisions[index][:, None].copy(),
            "diverged": column(diverged),
            "success": column(success),
        }

    @staticmethod
    def _split(index: np.ndarray, values: dict[str, np.ndarray]) -> dict[int, dict]:
        return {int(i): {k: v[j] for k, v in values.items()} for j, i in enumerate(index)}

    def reset_some(self, indices: Sequence[int]) -> dict[int, dict]:
        index = np.asarray(indices, dtype=np.int64)
        self._start(index.tolist())
        rows = self._rows(index)
        false = np.zeros(len(index), dtype=bool)
        values = self._values(index, self._integrals(rows)[:, 1:], false, false)
        for key in ("done", "terminated", "truncated"):
            values[key] = np.zeros((len(index), 1), dtype=bool)
        return self._split(index, values)

    def step_some(self, actions: dict[int, int]) -> dict[int, dict]:
        """One decision of the replicas ``actions.keys()``; those that reach ``max_decisions``
        without success run up to ``extra_waits`` further intervals in a sub-batch."""
        config = self.config
        index = np.fromiter(actions, dtype=np.int64, count=len(actions))
        chosen = np.fromiter(actions.values(), dtype=np.int64, count=len(actions))
        shock, bad = chosen == SHOCK, chosen[(chosen != WAIT) & (chosen != SHOCK)]
        if bad.size:
            raise ValueError(f"action must be 0 (wait) or 1 (shock), got {bad[0]}")
        self.decisions[index] += 1
        self.intervals[index] += 1
        rows = self._rows(index)
        with self._phase("decisions"):
            finite = self._advance(rows, shock)
            values = self._integrals(rows)
        success = finite & (values[:, 0] < config.success_threshold)
        last = self.decisions[index] >= config.max_decisions
        waiting = np.flatnonzero(finite & ~success & last)
        with self._phase("waits"):
            for _ in range(config.extra_waits):
                if not len(waiting):
                    break
                waiting_rows = torch.as_tensor(index[waiting], device=self.u.device)
                finite[waiting] &= self._advance(waiting_rows, None)
                self.intervals[index[waiting]] += 1
                values[waiting] = self._integrals(waiting_rows)
                success[waiting] = finite[waiting] & (values[waiting, 0] < config.success_threshold)
                waiting = waiting[finite[waiting] & ~success[waiting]]
        diverged = ~finite
        failure = finite & ~success & last
        values[diverged] = 0.0
        rewards = [
            self.reward_fn(
                {
                    "shock": bool(shock[j]),
                    "success": bool(success[j]),
                    "failure": bool(failure[j]),
                    "steps": int(self.intervals[i]),
                }
            )
            for j, i in enumerate(index)
        ]
        terminated = (success | failure).reshape(-1, 1)
        result = self._values(index, values[:, 1:], diverged, success)
        result |= {
            "reward": np.asarray(rewards, dtype=np.float32).reshape(-1, 1),
            "done": terminated | diverged.reshape(-1, 1),
            "terminated": terminated,
            "truncated": diverged.reshape(-1, 1).copy(),
        }
        return self._split(index, result)
