"""Baseline policies for evaluation, usable wherever the agent's policy is (TorchRL style:
``policy(tensordict)`` writes ``"action"`` and returns the tensordict).

They read only the unbatched keys of :class:`~physicsrl.envs.env.PhysicsEnv`: ``step`` (the
decisions taken so far) and ``observation``; none keeps state between calls.

Heat: :class:`Constant` (0 = stop at once, 1 = never stop), :class:`HeatOptimal` (the exact
optimum of :func:`~physicsrl.envs.heat.exact_optimum`). ATP: :class:`Constant` (0 = never
shock, 1 = always shock), :class:`RandomActions`, :class:`EveryKth`, :class:`Schedule` (shock
at given decisions) and :func:`best_single_shock` (the best one-shock schedule over evaluation
seeds); :func:`atp_baselines` names the ATP set, :func:`open_loop_schedules` the bar's
schedules and :func:`two_shock_schedules` the pairs of shocks.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING

import numpy as np
import torch
from tensordict import TensorDictBase

if TYPE_CHECKING:
    from physicsrl.envs.heat import HeatOptimum


class Policy:
    """Base class: ``action(tensordict) -> int``; calling writes it as ``"action"``."""

    def action(self, tensordict: TensorDictBase) -> int:
        raise NotImplementedError

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        return tensordict.set("action", torch.tensor(self.action(tensordict), dtype=torch.int64))


class Constant(Policy):
    """Always ``value`` (heat: 0 stop at once, 1 never stop; ATP: 0 never shock, 1 always)."""

    def __init__(self, value: int):
        self.value = int(value)

    def action(self, tensordict):
        return self.value


class RandomActions(Policy):
    """Action 1 with probability ``p`` at each decision, from its own seeded generator."""

    def __init__(self, p: float = 0.5, seed: int = 0):
        self.p, self.rng = p, np.random.default_rng(seed)

    def action(self, tensordict):
        return int(self.rng.random() < self.p)


class EveryKth(Policy):
    """Action 1 at decisions ``offset``, ``offset + k``, ... (decisions counted from 0)."""

    def __init__(self, k: int, offset: int = 0):
        if k < 1:
            raise ValueError(f"k must be an integer >= 1, got {k!r}")
        self.k, self.offset = k, offset

    def action(self, tensordict):
        step = int(tensordict["step"])
        return int(step >= self.offset and (step - self.offset) % self.k == 0)


class Schedule(Policy):
    """Action 1 at the decisions in ``steps`` (counted from 0), 0 otherwise."""

    def __init__(self, steps: Iterable[int]):
        self.steps = frozenset(int(s) for s in steps)

    def action(self, tensordict):
        return int(int(tensordict["step"]) in self.steps)


class HeatOptimal(Policy):
    """The exact optimum of the heat task: identify the level by the nearest recorded
    observation at this step, then advance until that level's best stopping time."""

    def __init__(self, optimum: HeatOptimum):
        self.optimum = optimum

    def action(self, tensordict):
        step = int(tensordict["step"])
        seen = self.optimum.observations[:, step]  # (levels, size)
        distance = np.abs(seen - tensordict["observation"].double().numpy()).sum(axis=1)
        level = int(distance.argmin())
        return int(step < self.optimum.best_stop[level])


def decisions(env) -> int:
    """The decisions of one of ``env``'s episodes: the upper bound of its ``step`` key."""
    return int(env.observation_spec["step"].space.high.max())


def best_single_shock(env, seeds: Iterable[int]) -> tuple[Schedule, dict[int | None, float]]:
    """Try a single shock at every decision (and none) over ``seeds``; return the schedule with
    the best mean return and every schedule's mean (key None: no shock). All the schedules run
    in one :func:`~physicsrl.evaluation.compare`: the members of a batch (replicas, groups)
    share their episodes; snapshot resets make the repeated resets of each seed cheap."""
    from physicsrl.evaluation import compare  # it imports this package

    candidates = {None: Constant(0)} | {step: Schedule([step]) for step in range(decisions(env))}
    _, rows = compare(env, {str(step): policy for step, policy in candidates.items()}, seeds)
    means = {step: row["return"] for step, row in zip(candidates, rows, strict=True)}
    best = max(means, key=means.get)
    return Schedule([] if best is None else [best]), means


def open_loop_schedules(
    max_decisions: int, periods: Iterable[int] = range(2, 7)
) -> dict[str, Policy]:
    """Display name -> policy: every open-loop ATP schedule of the bar (a policy that reads no
    observation): never and always shock, one shock at each decision 0 .. ``max_decisions`` - 1,
    and a shock every k-th decision from each offset 0 .. k - 1 for k in ``periods``."""
    schedules: dict[str, Policy] = {"never shock": Constant(0), "always shock": Constant(1)}
    schedules |= {f"single shock at {d}": Schedule([d]) for d in range(max_decisions)}
    for k in periods:
        schedules |= {f"every {k} from {offset}": EveryKth(k, offset) for offset in range(k)}
    return schedules


def two_shock_schedules(max_decisions: int, gaps: Iterable[int]) -> dict[str, Policy]:
    """Display name -> policy: two shocks, at decisions i < j < ``max_decisions`` with
    j - i in ``gaps``."""
    return {
        f"shocks at {i} and {i + gap}": Schedule([i, i + gap])
        for i in range(max_decisions)
        for gap in sorted(set(gaps))
        if 0 < gap and i + gap < max_decisions
    }


def atp_baselines(
    env, seeds: Iterable[int], seed: int = 0, single_shock: int | None = None
) -> dict[str, Policy]:
    """Display name -> policy: never shock, always shock, random (p = 0.5, seeded with
    ``seed``), every 4th decision, and the best single shock over ``seeds``
    (:func:`best_single_shock`; ``single_shock`` fixes its decision instead)."""
    if single_shock is None:
        best, _ = best_single_shock(env, seeds)
    else:
        best = Schedule([single_shock])
    at = f"decision {min(best.steps)}" if best.steps else "none"
    return {
        "never shock": Constant(0),
        "always shock": Constant(1),
        "random (p=0.5)": RandomActions(0.5, seed=seed),
        "every 4th": EveryKth(4),
        f"best single shock ({at})": best,
    }
