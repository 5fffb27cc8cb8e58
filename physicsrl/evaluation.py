"""Evaluation of policies on held-out seeds: one episode runner, one table of means
(:func:`physicsrl.tables.mean_metrics`).

Used by the Dojo's periodic evaluation, the training summary, ``physicsrl-eval`` and
``experiments/atp_baselines.py``. A policy is anything TorchRL's ``env.rollout`` accepts (the
greedy Q-network, a baseline of :mod:`physicsrl.envs.baselines`); an episode is run in
deterministic exploration mode from the env seeded with its seed. Leader only, inside
``with coordinator:`` when the env drives a distributed simulator.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from physicsrl.envs.members import Members, spread_episodes
from physicsrl.tables import mean_metrics

STANDARD_KEYS = {"observation", "reward", "done", "terminated", "truncated", "step"}
MAX_STEPS = 10_000  # a safety bound on episodes of envs that never end


def episode_metrics(rollout: TensorDictBase, action_counts: Mapping[str, int] = ()) -> dict:
    """Return, length, the env's scalar flags at the end (success, diverged, ...) and, for
    each ``name: action`` of ``action_counts``, how often that action was taken (shocks)."""
    nxt = rollout["next"]
    metrics = {"return": float(nxt["reward"].sum()), "length": int(rollout.shape[-1])}
    last = nxt[-1]
    for key in sorted(last.keys()):
        if key in STANDARD_KEYS or not isinstance(key, str):
            continue
        value = last.get(key)
        if isinstance(value, torch.Tensor) and value.numel() == 1:
            metrics[key] = float(value)
    action = rollout["action"]
    chosen = action.argmax(-1) if action.dtype == torch.bool else action  # one-hot or index
    for name, value in dict(action_counts).items():
        metrics[name] = int((chosen.reshape(-1) == value).sum())
    return metrics


def episode(
    env: EnvBase, policy: Callable, seed: int, callback: Callable | None = None
) -> TensorDictBase:
    """The rollout (shape (steps,)) of one episode of ``policy`` from ``env`` seeded with
    ``seed``; ``callback(env, tensordict)`` runs after the reset and after every step."""
    env.set_seed(int(seed))
    start = env.reset()
    if callback is not None:
        callback(env, start)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        return env.rollout(
            MAX_STEPS,
            policy,
            callback=callback,
            auto_reset=False,
            tensordict=start,
            break_when_any_done=True,
        )


def run_episode(
    env: EnvBase, policy: Callable, seed: int, action_counts: Mapping[str, int] = ()
) -> dict:
    """The metrics of one :func:`episode`: ``{"seed", **episode_metrics}``."""
    return {"seed": int(seed), **episode_metrics(episode(env, policy, seed), action_counts)}


def run_episodes(
    env: EnvBase, policy: Callable, seeds: Iterable[int], action_counts: Mapping[str, int] = ()
) -> list[dict]:
    """:func:`run_episode` for each seed (:func:`run_jobs` of ``policy`` on each)."""
    return run_jobs(env, [(policy, int(s)) for s in seeds], action_counts)


def run_jobs(
    env: EnvBase, jobs: Iterable[tuple[Callable, int]], action_counts: Mapping[str, int] = ()
) -> list[dict]:
    """:func:`run_episode` for each ``(policy, seed)`` of ``jobs``; the members of a batch
    (:class:`~physicsrl.envs.members.Members`: groups, replicas) share the jobs (K episodes on
    N members take about K / N episode times) and give the same rows in float64 (in float32 an
    episode's rounding can depend on which others share its steps)."""
    jobs = [(policy, int(seed)) for policy, seed in jobs]
    if not isinstance(env, Members):
        return [run_episode(env, policy, seed, action_counts) for policy, seed in jobs]
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        rollouts = spread_episodes(env, jobs, MAX_STEPS)
    return [
        {"seed": seed, **episode_metrics(rollout, action_counts)}
        for (_, seed), rollout in zip(jobs, rollouts, strict=True)
    ]


def compare(
    env: EnvBase,
    policies: Mapping[str, Callable],
    seeds: Iterable[int],
    action_counts: Mapping[str, int] = (),
) -> tuple[list[dict], list[dict]]:
    """One episode of each policy per seed, all in one :func:`run_jobs` (the policies share
    a batch's members): the rows per seed and the mean row per policy (both with a ``policy``
    column holding the display name)."""
    seeds = [int(s) for s in seeds]
    names = [name for name in policies for _ in seeds]
    rows = run_jobs(env, [(policies[name], s) for name in policies for s in seeds], action_counts)
    per_seed = [{"policy": name, **row} for name, row in zip(names, rows, strict=True)]
    means = [
        {"policy": name, **mean_metrics(r for r in per_seed if r["policy"] == name)}
        for name in policies
    ]
    return per_seed, means
