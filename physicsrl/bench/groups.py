"""``physicsrl-bench groups``: experience from N simulator groups of P ranks (issue 12).

Runs on the job's W ranks with ``mpi.ranks_per_env=P`` (N = W / P environments, see
:mod:`physicsrl.envs.groups`) and measures, on the learner:

- ``atp``: the ATP task (default: the report's 60 x 60 grid) as one batched env: the reset of
  all N environments (inducing the arrhythmia; snapshots off), then ``decisions`` batched steps
  with a fixed policy (shock at every ``shock_every``-th decision; success test off, so every
  layout simulates the same time). ``transitions_per_s`` = N x decisions / the steps' time.
- ``no-op``: W environments of one rank each (whatever P) whose step does nothing (the ATP
  env's keys and shapes, zeros). ``step_ms`` is the wall time per batched step; ``own_ms`` is that
  minus the time the learner waits for the group leaders' replies (``timeit("groups/wait")``):
  the batched env's own cost on the learner (sending the actions, receiving and unpickling the
  replies, the TensorDict work), the figure to fit against N. With more ranks than cores the
  wait is the OS scheduling the group leaders, which a real job with a core per rank does not
  have; the own cost is measured the same either way.
"""

from __future__ import annotations

import time

import torch
from mpi4py import MPI
from tensordict import TensorDict
from torchrl import timeit
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from physicsrl.envs import load_config, make_env
from physicsrl.envs.layout import environments

FIXED_LENGTH = ["env.success_threshold=-1e30", "env.extra_waits=0", "env.snapshots.capacity=0"]


class NoOpEnv(EnvBase):
    """An environment with the ATP env's keys and shapes (an observation of ``size`` floats,
    the decision index, flags) whose reset and step return zeros."""

    def __init__(self, size: int = 20):
        super().__init__(device="cpu", batch_size=[])
        flag = Categorical(2, shape=(1,), dtype=torch.bool)
        self.observation_spec = Composite(
            observation=Unbounded(shape=(size,)),
            step=Unbounded(shape=(1,), dtype=torch.int64),
            diverged=flag.clone(),
            success=flag.clone(),
        )
        self.action_spec = Categorical(2)
        self.reward_spec = Unbounded(shape=(1,))
        self.done_spec = Composite(
            done=flag.clone(), terminated=flag.clone(), truncated=flag.clone()
        )
        self._first = self.observation_spec.zero().update(self.done_spec.zero())
        self._next = self._first.clone().set("reward", self.reward_spec.zero())

    def _reset(self, tensordict=None, **kwargs) -> TensorDict:
        return self._first.clone()

    def _step(self, tensordict) -> TensorDict:
        return self._next.clone()

    def _set_seed(self, seed) -> None:
        pass


def _timed_steps(env: EnvBase, steps: int, shock_every: int) -> tuple[float, float]:
    """Seconds of one reset of all members, and of ``steps`` batched steps (``timeit`` holds,
    after it, the steps' waits only)."""
    started = time.perf_counter()
    td = env.reset()
    reset_s = time.perf_counter() - started
    timeit.erase()
    started = time.perf_counter()
    for decision in range(steps):
        td["action"] = torch.full(env.batch_size, int(decision % shock_every == 0))
        td = env.step(td)["next"]
    return reset_s, time.perf_counter() - started


def run(cfg) -> list[dict]:
    world = MPI.COMM_WORLD
    P = int(cfg.mpi.ranks_per_env)
    rows = []
    if cfg.atp:
        rows.append(_atp_row(cfg, world, P))
    with environments(lambda c: NoOpEnv(), 1) as env:
        if env is not None:
            _timed_steps(env, 10, cfg.shock_every)  # warm-up
            _, steps_s = _timed_steps(env, cfg.noop_steps, cfg.shock_every)
            wait_s = timeit.todict(percall=False).get("groups/wait", 0.0)
            rows.append(
                {
                    "what": "no-op",
                    "ranks": world.size,
                    "ranks_per_env": 1,
                    "envs": world.size,
                    "step_ms": round(1e3 * steps_s / cfg.noop_steps, 4),
                    "own_ms": round(1e3 * (steps_s - wait_s) / cfg.noop_steps, 4),
                }
            )
    return rows


def _atp_row(cfg, world: MPI.Comm, P: int) -> dict | None:
    """The ATP row (on the learner; None elsewhere)."""
    overrides = [*cfg.overrides, *FIXED_LENGTH, f"max_memory_gb={cfg.max_memory_gb}"]
    config = load_config("ms", overrides=overrides, seed=cfg.seed)
    with environments(lambda c: make_env(config, c), P, seed=cfg.seed) as env:
        if env is None:
            return None
        n = world.size // P
        reset_s, steps_s = _timed_steps(env, cfg.decisions, cfg.shock_every)
        return {
            "what": "atp",
            "ranks": world.size,
            "ranks_per_env": P,
            "envs": n,
            "reset_s": round(reset_s, 3),
            "step_ms": round(1e3 * steps_s / cfg.decisions, 3),
            "transitions_per_s": round(n * cfg.decisions / steps_s, 3),
        }
