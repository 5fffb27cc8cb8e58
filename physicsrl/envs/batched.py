r"""The ATP task with B replicas on one process: a TorchRL environment of ``batch_size=[B]``.

The task of :mod:`physicsrl.envs.atp` (same config, observation, reward, draws and events), its
time loop on torch (:class:`~physicsrl.fem.batched.BatchedMonodomain`, CPU or CUDA) for all
replicas at once, on this process's own copy of the mesh (``MPI.COMM_SELF``: under MPI every
rank owns its replicas, and the batches of the ranks together form the training batch).

- Reset honours TorchRL's ``"_reset"`` mask: only the replicas it selects start a new episode
  (their rows of u and w are written from the snapshot library, or induced, all new draws of
  the call in one batch); the others keep their state.
- Step: every replica takes its action for one decision interval (shocks as a (B, cells)
  current on the replicas that shock); replicas that reach ``max_decisions`` without success
  run up to ``extra_waits`` further intervals in a sub-batch. A replica whose state stops being
  finite ends its episode as truncated with ``diverged`` set, as in
  :class:`~physicsrl.envs.env.PhysicsEnv`.
- Determinism: replica i's draw for its k-th episode comes from the generator seeded by
  (seed, i, k), so it depends on nothing else (not B, not the other replicas' resets).

Keys are those of :class:`~physicsrl.envs.env.PhysicsEnv` with a leading batch dimension B.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict
from typing import Any

import numpy as np
import torch
from mpi4py import MPI
from tensordict import TensorDict
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from physicsrl.checks import build, choice, integer, plain
from physicsrl.envs.atp import SHOCK, ATPConfig, ATPTask, ResetSampler
from physicsrl.envs.observations import OBSERVATIONS, Observation
from physicsrl.envs.regions import CellAverage, disk, half_plane_gate, rectangle_above
from physicsrl.envs.rewards import REWARDS, Reward
from physicsrl.envs.snapshots import SnapshotCache
from physicsrl.fem.batched import BatchedMonodomain
from physicsrl.fem.integrals import form_rows
from physicsrl.fem.resolution import report

BACKENDS = ("petsc", "torch")
"""``env.model.backend``: the coordinated DOLFINx/PETSc simulator, or this module's."""


class BatchedATPEnv(EnvBase):
    """B replicas of the ATP task (see the module docstring).

    Parameters
    ----------
    config, observation, reward:
        As for :class:`~physicsrl.envs.atp.ATPTask` and :class:`~physicsrl.envs.env.PhysicsEnv`.
    replicas:
        B.
    seed:
        Seed of every replica's draws (None: from the OS, drawn once).
    device:
        Where the simulation runs (``"cpu"`` or ``"cuda"``); the tensordicts are on the CPU.
    max_reset_attempts:
        Draws tried per replica and reset before giving up when states come out non-finite.
    """

    def __init__(
        self,
        config: ATPConfig,
        observation: Observation,
        reward: Reward,
        replicas: int,
        seed: int | None = None,
        device: str = "cpu",
        max_reset_attempts: int = 10,
    ):
        missing = reward.events - ATPTask.events
        if missing:
            raise ValueError(f"reward.name {reward.name!r} reads events {sorted(missing)}")
        B = integer("env.replicas", replicas, 1)
        if config.induction != "report" or len(set(config.reset.rest_time)) > 1:
            raise ValueError(
                f"env.induction={config.induction!r}, env.reset.rest_time="
                f"{list(config.reset.rest_time)}: the torch backend induces the report's "
                "arrhythmia with a fixed rest only (induction: report, one rest_time)"
            )
        super().__init__(device="cpu", batch_size=[B])
        self.config, self.observation, self.reward_fn = config, observation, reward
        self.max_reset_attempts = max_reset_attempts
        domain = config.mesh.create(MPI.COMM_SELF)
        model = asdict(config.model)
        warn = model.pop("warn_resolution")
        self.simulator = sim = BatchedMonodomain(domain, **model, device=device)
        report(sim.resolution, warn)
        V = sim.V
        rows = np.vstack([form_rows(V, [1.0]), observation.rows(V)])  # row 0: integral of u
        self.rows = sim.tensor(rows)
        degree = config.region_quadrature_degree
        self.stimulus = CellAverage(domain, rectangle_above, 3, degree)
        shock = config.shock
        self.shock = sim.tensor(
            CellAverage(domain, disk, 3, degree)(shock.current, *shock.centre, shock.radius)
            .x.array[: sim.num_cells]
            .copy()
        )
        self.sampler = ResetSampler(config)
        settings = repr((config.mesh, config.model, config.reset, degree, "torch"))
        self.snapshots = SnapshotCache(
            config.snapshots.capacity, config.snapshots.directory, settings, MPI.COMM_SELF
        )
        self.u = torch.zeros(B, sim.num_dofs, device=sim.device, dtype=sim.dtype)
        self.w = torch.ones_like(self.u)
        self.decisions = np.zeros(B, dtype=np.int64)
        self.intervals = np.zeros(B, dtype=np.int64)
        self.episodes = np.zeros(B, dtype=np.int64)  # episodes started per replica

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

    def _set_seed(self, seed: int | None) -> None:
        self.seed = int(np.random.SeedSequence(seed).entropy) if seed is None else int(seed)
        self.episodes[:] = 0

    def draw(self, replica: int, episode: int, attempt: int = 0) -> tuple[float, float, float]:
        """The reset draw (c, h, b) of ``replica``'s ``episode``-th episode (its
        ``attempt``-th try if earlier ones diverged)."""
        rng = np.random.default_rng([self.seed, replica, episode, attempt])
        return self.sampler(rng)

    # the simulation ----------------------------------------------------------------------
    def _integrals(self, u: torch.Tensor) -> np.ndarray:
        """(len(u), K): row 0 the integral of u, then the observation."""
        return (u @ self.rows.T).double().cpu().numpy()

    def _run(self, u, w, current, duration: float) -> torch.Tensor:
        return self.simulator.advance(u, w, current, self.simulator.steps(duration))

    def _induce(self, draws: list[tuple[float, ...]]):
        """(u, w, finite) after the reset's induction of each draw, in one batch."""
        r, sim = self.config.reset, self.simulator
        w = torch.stack([sim.nodal(half_plane_gate(c, r.w_slope)) for c, *_ in draws])
        u = torch.zeros_like(w)
        current = sim.tensor(
            np.array(
                [self.stimulus(r.current, *d[:3]).x.array[: sim.num_cells].copy() for d in draws]
            )
        )
        finite = self._run(u, w, current, r.stimulus_time)
        finite &= self._run(u, w, None, r.rest_time[0])
        return u, w, finite

    def _start(self, replicas: list[int]) -> None:
        """New episodes for ``replicas``: their rows of u and w from the snapshot library or
        from one batched induction of the draws not in it."""
        pending = {i: 0 for i in replicas}  # replica -> attempt
        while pending:
            keys = {i: self.draw(i, int(self.episodes[i]), a) for i, a in pending.items()}
            new = [i for i in pending if keys[i] not in self.snapshots]
            if new:
                u, w, finite = self._induce([keys[i] for i in new])
                for j, i in enumerate(new):
                    if bool(finite[j]):
                        self.snapshots.put(keys[i], u[j].cpu().numpy(), w[j].cpu().numpy())
            for i in list(pending):
                if keys[i] in self.snapshots:
                    u, w = self.snapshots.get(keys[i])
                    self.u[i], self.w[i] = self.simulator.tensor(u), self.simulator.tensor(w)
                    del pending[i]
                else:
                    pending[i] += 1
                    if pending[i] >= self.max_reset_attempts:
                        raise RuntimeError(
                            f"{self.max_reset_attempts} reset draws in a row gave non-finite "
                            f"states (replica {i})"
                        )
        for i in replicas:
            self.episodes[i] += 1
        self.decisions[replicas] = 0
        self.intervals[replicas] = 0

    def _advance(self, index: torch.Tensor | None, shocks: torch.Tensor | None):
        """One decision interval for the replicas ``index`` (None: all), with the shock on the
        rows of ``shocks`` (bool, or None: no shock); their finite mask."""
        u, w = (self.u, self.w) if index is None else (self.u[index], self.w[index])
        config, sim = self.config, self.simulator
        steps = sim.steps(config.decision_interval)
        finite = torch.ones(len(u), dtype=torch.bool, device=u.device)
        if shocks is not None and bool(shocks.any()):
            on = sim.steps(config.shock.duration)
            current = shocks.to(sim.device, sim.dtype)[:, None] * self.shock
            finite &= sim.advance(u, w, current, on)
            steps -= on
        finite &= sim.advance(u, w, None, steps)
        if index is not None:
            self.u[index], self.w[index] = u, w
        return finite.cpu().numpy()

    # TorchRL -----------------------------------------------------------------------------
    def _reset(self, tensordict=None, **kwargs) -> TensorDict:
        B = self.batch_size[0]
        mask = np.ones(B, dtype=bool)
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict["_reset"].reshape(B).cpu().numpy()
        self._start([int(i) for i in np.flatnonzero(mask)])
        false = torch.zeros(B, 1, dtype=torch.bool)
        return TensorDict(
            {
                **self._observation(self._integrals(self.u)[:, 1:], false, false),
                "done": false.clone(),
                "terminated": false.clone(),
                "truncated": false.clone(),
            },
            batch_size=[B],
        )

    def _observation(self, values, diverged, success) -> dict:
        return {
            "observation": torch.as_tensor(values, dtype=torch.float32),
            "step": torch.as_tensor(self.decisions, dtype=torch.int64)[:, None].clone(),
            "diverged": torch.as_tensor(diverged).reshape(-1, 1).clone(),
            "success": torch.as_tensor(success).reshape(-1, 1).clone(),
        }

    def _step(self, tensordict: TensorDict) -> TensorDict:
        config = self.config
        action = tensordict["action"].reshape(-1).cpu()
        shock = (action == SHOCK).numpy()
        self.decisions += 1
        self.intervals += 1
        finite = self._advance(None, torch.as_tensor(shock))
        values = self._integrals(self.u)
        success = finite & (values[:, 0] < config.success_threshold)
        waiting = np.flatnonzero(finite & ~success & (self.decisions >= config.max_decisions))
        for _ in range(config.extra_waits):
            if not len(waiting):
                break
            index = torch.as_tensor(waiting, device=self.u.device)
            finite[waiting] &= self._advance(index, None)
            self.intervals[waiting] += 1
            values[waiting] = self._integrals(self.u[index])
            success[waiting] = finite[waiting] & (values[waiting, 0] < config.success_threshold)
            waiting = waiting[finite[waiting] & ~success[waiting]]
        diverged = ~finite
        failure = finite & ~success & (self.decisions >= config.max_decisions)
        values[diverged] = 0.0
        rewards = [
            self.reward_fn(
                {
                    "shock": bool(shock[i]),
                    "success": bool(success[i]),
                    "failure": bool(failure[i]),
                    "steps": int(self.intervals[i]),
                }
            )
            for i in range(len(shock))
        ]
        terminated = torch.as_tensor(success | failure)[:, None]
        truncated = torch.as_tensor(diverged)[:, None]
        return TensorDict(
            {
                **self._observation(values[:, 1:], diverged, success),
                "reward": torch.tensor(rewards, dtype=torch.float32)[:, None],
                "done": terminated | truncated,
                "terminated": terminated,
                "truncated": truncated,
            },
            batch_size=self.batch_size,
        )


def make_batched_env(cfg: Mapping | Any) -> BatchedATPEnv:
    """The batched environment of a ``make_env`` config (:mod:`physicsrl.envs.factory`) whose
    ``env`` is the ATP task with ``env.model.backend=torch``, ``env.model.device`` (cpu or
    cuda; default cpu) and ``env.replicas`` (B, default 1)."""
    cfg = plain(cfg)
    env = dict(cfg["env"])
    model = dict(env.get("model", {}))
    backend = choice("env.model.backend", model.pop("backend", "torch"), BACKENDS)
    if backend != "torch":
        raise ValueError(f"env.model.backend must be torch for the batched env, got {backend!r}")
    device = choice("env.model.device", model.pop("device", "cpu"), ("cpu", "cuda"))
    replicas = env.pop("replicas", 1)
    env["model"] = model
    if env.pop("name", "atp") != "atp":
        raise ValueError("env.name must be atp for env.model.backend=torch")
    observation_class, settings = OBSERVATIONS.lookup(cfg["observation"])
    reward_class, reward_settings = REWARDS.lookup(cfg["reward"])
    return BatchedATPEnv(
        build(ATPConfig, env, "env"),
        build(observation_class, settings, "observation"),
        build(reward_class, reward_settings, "reward"),
        replicas,
        seed=cfg.get("seed"),
        device=device,
    )
