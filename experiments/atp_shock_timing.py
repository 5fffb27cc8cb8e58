"""Does the catheter tell when one shock works? A supervised reference for the timing variant.

    python experiments/atp_shock_timing.py label --draws 96     # ~2 core-hours
    python experiments/atp_shock_timing.py fit                  # a few minutes
    python experiments/atp_shock_timing.py features             # seconds
    python experiments/atp_shock_timing.py observe --tag b observation.splines=10  # 96 episodes
    python experiments/atp_shock_timing.py second               # ~200 episodes
    python experiments/atp_shock_timing.py second --first 0     # ~1,000 episodes
    python experiments/atp_shock_timing.py worked --first 0     # seconds, after second

The timing variant (``+experiment=atp_timing``) on the bar's simulator (torch, float32,
compiled). ``label``: for draws outside the held-out seeds (seeds 2000000000, 2000000001, ...),
the never-shock episode, whose observation at decision k is what any policy sees there before
its first shock, and one episode per decision k with a single shock at k: whether it ends the
arrhythmia. 25 episodes per draw (24 decisions), in chunks of 4 draws
(``<out>/atp_shock_timing_labels/chunk-NNN.pt``, the commands in its ``labels.txt``;
``label`` again continues).

``fit``: the label y(draw, k) = the single shock at k succeeds, the features x(draw, k) = the
catheter's 20 readings and k, standardised. A k-nearest-neighbour estimate p(x) of P(y = 1 | x)
and a policy that shocks once, at the first decision where p > theta (never otherwise). The
neighbours and theta are chosen by leave-one-draw-out success on the labelled draws only; the
policy then runs in the env on the held-out seeds of the results table, beside the bar (the
best open-loop schedule, single shock at 0: ``atp_timing_open_loop.csv``). Writes
``<out>/atp_shock_timing.csv`` (per seed), ``atp_shock_timing.txt`` (command, commit, choice
and means) and prints the learning curve: the held-out success with the first 8, 16, ...
labelled draws.

``features``: the same leave-one-draw-out choice for other inputs of the estimate
(:data:`FEATURE_SETS`: the readings alone, and with the previous decision's readings) and other
estimates of P(y = 1 | x) than the neighbours' (:class:`Logistic`: a linear one and a small
network), on the labels alone; ``atp_shock_timing_features.txt``.

``observe``: the same choice with the readings of another observation (more electrodes), from
the never-shock episodes of the labelled draws run again with it.

``second``: the draws where the shock-once policy (the reference's inputs, chosen on the labels
as ``fit`` chooses, each draw's p from the other draws) shocks and fails, or with ``--first D``
those where a shock at decision D fails, and on each of them a second shock at each later
decision: whether it ends the arrhythmia. With hindsight, an upper bound on a policy that shocks
again after that failed shock; and, chosen as ``fit`` chooses, a rule that times the second shock
from the readings after the first shock, run on the held-out seeds
(``atp_shock_timing_second[_atD].txt``, ``.csv``, and the second shocks' labels in ``.pt``).

``worked --first D``: do the readings after a shock at D tell the draws where it worked from
those where it failed? From ``second --first D``'s readings (``atp_shock_timing_worked_atD.txt``).
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
from contextlib import contextmanager
from functools import partial
from pathlib import Path

import numpy as np
import torch
from torch.nn import Tanh
from torchrl.modules import MLP

from physicsrl import builders
from physicsrl.cli.train import train_config
from physicsrl.config import held_out_seeds
from physicsrl.coordinated import abort_on_error
from physicsrl.envs.baselines import Constant, Policy, Schedule
from physicsrl.envs.layout import environments
from physicsrl.envs.members import spread_episodes
from physicsrl.evaluation import MAX_STEPS, run_jobs
from physicsrl.tables import mean_metrics, provenance, write_csv

FIRST_DRAW = 2_000_000_000  # labelled draws: outside the held-out seeds and training's
PER_CHUNK = 4
LABELS = "atp_shock_timing_labels"  # the chunks' folder under --out
NEIGHBOURS = (5, 15, 30)
THRESHOLDS = np.round(np.linspace(0.1, 0.9, 17), 2)


def make_env(replicas: int, overrides: list[str]):
    """The timing variant on the bar's simulator (``overrides`` last), and its env factory."""
    simulator = ["env.model.backend=torch", "env.model.compile=true", "env.model.dtype=float32"]
    settings = ["+experiment=atp_timing", *simulator, f"env.replicas={replicas}", *overrides]
    cfg = train_config(settings)
    return cfg, lambda coordinator: builders.make_env(cfg, coordinator)


@contextmanager
def leader_env(replicas: int, overrides: list[str]):
    """(the decisions of an episode, the env of :func:`make_env`) on the leader, which runs
    every episode and writes every file; (the decisions, None) on the other ranks, once their
    environment has served the leader's episodes. An error on any rank ends every rank."""
    cfg, factory = make_env(replicas, overrides)
    with abort_on_error(), environments(factory, 1) as env:
        yield cfg.env.max_decisions, env


def label(draws: int, replicas: int, out: Path, overrides: list[str]) -> None:
    """The observations and single-shock outcomes of ``draws`` draws, chunk by chunk."""
    with leader_env(replicas, overrides) as (decisions, env):
        if env is None:
            return
        (out / LABELS).mkdir(parents=True, exist_ok=True)
        with (out / LABELS / "labels.txt").open("a") as record:  # every call that adds chunks
            record.write(f"{shlex.join(['python', *sys.argv])}  # {provenance()}\n")
        for chunk in range(-(-draws // PER_CHUNK)):
            path = out / LABELS / f"chunk-{chunk:03d}.pt"
            if path.exists():
                continue
            seeds = [FIRST_DRAW + PER_CHUNK * chunk + i for i in range(PER_CHUNK)]
            jobs = [(Constant(0), s) for s in seeds]
            jobs += [(Schedule([k]), s) for s in seeds for k in range(decisions)]
            with torch.no_grad():
                rollouts = spread_episodes(env, jobs, MAX_STEPS)
            success = torch.tensor([float(r["next", "success"][-1]) for r in rollouts])
            torch.save(
                {
                    "seeds": seeds,
                    "observations": readings_after(
                        rollouts[:PER_CHUNK], [-1] * PER_CHUNK, decisions
                    ),
                    "never": success[:PER_CHUNK],
                    "single": success[PER_CHUNK:].reshape(PER_CHUNK, decisions),
                },
                path,
            )
            print(
                f"draws {seeds[0]}-{seeds[-1]}: {int(success[PER_CHUNK:].sum())} of "
                f"{PER_CHUNK * decisions} single shocks end the arrhythmia",
                flush=True,
            )


def readings_after(rollouts: list, shots: list[int], decisions: int) -> torch.Tensor:
    """(episodes, decisions, readings): each episode's observations after its shot's decision
    (-1: from decision 0); NaN up to it and after the episode's end (it ended by itself, so
    those decisions are not seen)."""
    size = rollouts[0]["observation"].shape[-1]
    readings = torch.full((len(rollouts), decisions, size), float("nan"))
    for i, (at, rollout) in enumerate(zip(shots, rollouts, strict=True)):
        seen = min(decisions, rollout.shape[0])
        readings[i, at + 1 : seen] = rollout["observation"][at + 1 : seen]
    return readings


def load_labels(out: Path) -> tuple[list[int], np.ndarray, np.ndarray, np.ndarray]:
    """The stored labels under ``out``: (seeds, x (draws, decisions, features), y (draws,
    decisions), never (draws,))."""
    chunks = [torch.load(path) for path in sorted((out / LABELS).glob("chunk-*.pt"))]
    seeds = [seed for chunk in chunks for seed in chunk["seeds"]]
    x = features(np.concatenate([c["observations"].double().numpy() for c in chunks]))
    y = np.concatenate([c["single"].numpy() for c in chunks]).astype(float)
    never = np.concatenate([c["never"].numpy() for c in chunks]).astype(float)
    return seeds, x, y, never


def features(observations: np.ndarray) -> np.ndarray:
    """(draws, decisions, readings + 1): the readings and the decision index."""
    draws, decisions, _ = observations.shape
    step = np.broadcast_to(np.arange(decisions, dtype=float)[None, :, None], (draws, decisions, 1))
    return np.concatenate([observations, step], -1)


def previous(readings: np.ndarray) -> np.ndarray:
    """(draws, decisions, readings): each decision's previous decision's readings (decision 0:
    its own; a policy sees them before its first shock too)."""
    return np.concatenate([readings[:, :1], readings[:, :-1]], 1)


FEATURE_SETS = {
    "readings": lambda readings, step: readings,
    "readings, decision (the reference's)": lambda readings, step: np.concatenate(
        [readings, step], -1
    ),
    "readings, previous decision's readings, decision": lambda readings, step: np.concatenate(
        [readings, previous(readings), step], -1
    ),
    "readings, their change since the previous decision, decision": lambda readings, step: (
        np.concatenate([readings, readings - previous(readings), step], -1)
    ),
}
"""Inputs of the k-NN estimate compared by ``features``: does the catheter's recent past (a
policy with stacked frames) tell the window better than its present?"""


def compare_features(out: Path) -> None:
    """The leave-one-draw-out success of the shock-once policy for each of
    :data:`FEATURE_SETS`, with the neighbours' estimate and each of :data:`ESTIMATES`, on the
    labelled draws alone (no episodes run), into ``<out>/atp_shock_timing_features.txt``."""
    torch.set_num_threads(1)  # fits of ~2,000 points: more threads only wait on each other
    _, x, y, never = load_labels(out)
    readings, step = x[..., :-1], x[..., -1:]
    lines = [f"{shlex.join(['python', *sys.argv])}", provenance()]
    lines.append(f"{len(x)} labelled draws; hindsight best single shock: {y.max(1).mean():.1%}")
    lines.append(recurrence(y))
    for name, inputs in FEATURE_SETS.items():
        x = inputs(readings, step)
        k, theta, success = choose(x, y, never)
        lines.append(f"{name}: {success:.1%} (neighbours {k}, theta {theta})")
        print(lines[-1], flush=True)
        for label, estimate in ESTIMATES.items():
            _, theta, success = choose(x, y, never, {label: estimate})
            lines.append(f"{name}, {label}: {success:.1%} (theta {theta})")
            print(lines[-1], flush=True)
    (out / "atp_shock_timing_features.txt").write_text("\n".join(lines) + "\n")


def observe(out: Path, tag: str, replicas: int, overrides: list[str]) -> None:
    """Would another observation tell the window better? The never-shock episodes of the
    labelled draws, observed as ``overrides`` say (e.g. a basket of 10 splines of 8 electrodes:
    ``observation.splines=10 'observation.distances=[...]'``; the dynamics are those of the
    labels), :func:`kept` in ``<out>/atp_shock_timing_observe_<tag>.pt`` with the overrides
    (other overrides under the same tag are refused); then the reference's
    leave-one-draw-out choice (the neighbours on the readings and the decision) with those
    readings and the stored single-shock labels, beside the labels' own readings and both
    together, on the first 24, 48, 72 and all labelled draws (does the choice improve with more
    draws?), and the draws that the rule on all draws ends with one input and not the other
    (:func:`paired`), into ``atp_shock_timing_observe_<tag>.txt``."""
    seeds, x, y, never = load_labels(out)
    with leader_env(replicas, overrides) as (decisions, env):
        if env is None:
            return

        def run() -> dict:
            with torch.no_grad():
                rollouts = spread_episodes(env, [(Constant(0), s) for s in seeds], MAX_STEPS)
            ended = torch.tensor([float(r["next", "success"][-1]) for r in rollouts])
            return {
                "readings": readings_after(rollouts, [-1] * len(seeds), decisions),
                "never": ended,
                "overrides": overrides,
            }

        path = out / f"atp_shock_timing_observe_{tag}.pt"
        stored = kept(path, seeds, run)
        if stored["overrides"] != overrides:
            raise ValueError(
                f"{path} holds the readings of {stored['overrides']}, not {overrides}: "
                "another --tag"
            )
    readings = stored["readings"].double().numpy()
    sizes = [n for n in (24, 48, 72) if n < len(seeds)] + [len(seeds)]
    lines = [shlex.join(["python", *sys.argv]), provenance()]
    lines.append(
        f"{len(seeds)} labelled draws; never-shock outcome as the labels' on "
        f"{int((stored['never'].numpy() == never).sum())}; hindsight best single shock: "
        + ", ".join(f"first {n} draws {y[:n].max(1).mean():.1%}" for n in sizes)
    )
    both = features(np.concatenate([x[..., :-1], readings], -1))
    ended = {}  # name -> whether each draw ends, its rule chosen on all draws (each left out)
    for name, inputs in (
        ("the labels' readings", x),
        (f"{tag}'s", features(readings)),
        (f"the labels' and {tag}'s", both),
    ):
        chosen = [(n, *choose(inputs[:n], y[:n], never[:n])) for n in sizes]
        lines.append(
            f"{name} ({inputs.shape[-1] - 1} readings), decision: "
            + "; ".join(
                f"first {n} draws {s:.1%} (neighbours {k}, theta {t})" for n, k, t, s in chosen
            )
        )
        k, theta = chosen[-1][1:3]
        p = leave_one_draw_out(inputs, y, partial(Neighbours, k=k))
        ended[name] = outcomes(p, y, never, theta) > 0
    lines.append(
        paired(ended[f"{tag}'s"], ended["the labels' readings"], f"{tag}'s", "the labels'")
    )
    print("\n".join(lines[2:]), flush=True)
    (out / f"atp_shock_timing_observe_{tag}.txt").write_text("\n".join(lines) + "\n")


def paired(a: np.ndarray, b: np.ndarray, name_a: str, name_b: str) -> str:
    """The draws that rule a ends and rule b fails, and the reverse, with the two-sided sign
    test's p of that split (a, b: (draws,) booleans)."""
    only_a, only_b = int((a & ~b).sum()), int((b & ~a).sum())
    n, low = only_a + only_b, min(only_a, only_b)
    p = min(1.0, 2 * sum(math.comb(n, i) for i in range(low + 1)) / 2**n)
    return (
        f"paired, on all draws: {name_a} rule alone ends {only_a}, {name_b} alone {only_b} "
        f"(two-sided sign test p = {p:.3f})"
    )


def recurrence(y: np.ndarray, lags: int = 15) -> str:
    """Do a draw's windows recur (with the spiral's rotation?) For each lag L, the fraction of
    single shocks at k + L that work where the one at k works, beside that of all shocks at
    k + L (y: (draws, decisions); L up to the decisions less one)."""
    lags = min(lags, y.shape[1] - 1)
    given = [
        (y[:, :-lag] * y[:, lag:]).sum() / max(y[:, :-lag].sum(), 1) for lag in range(1, lags + 1)
    ]
    overall = [y[:, lag:].mean() for lag in range(1, lags + 1)]
    percent = lambda values: " ".join(f"{v:.0%}" for v in values)  # noqa: E731
    return (
        f"a single shock at k + L works, L = 1..{lags}: where the one at k works "
        f"{percent(given)}; of all {percent(overall)}"
    )


def standardiser(x: np.ndarray):
    """z(points) = (points - mean) / deviation, of the labelled points ``x`` (rows)."""
    mean, scale = x.mean(0), x.std(0) + 1e-9
    return lambda points: (np.atleast_2d(points) - mean) / scale


class Neighbours:
    """p(x) = the fraction of successes among the ``k`` labelled points nearest to x
    (Euclidean, after :func:`standardiser`)."""

    def __init__(self, x: np.ndarray, y: np.ndarray, k: int):
        self.z = standardiser(x)
        self.x, self.y, self.k = self.z(x), y, k

    def __call__(self, x: np.ndarray) -> np.ndarray:
        z = self.z(x)
        distances = ((z[:, None] - self.x[None]) ** 2).sum(-1)
        return self.y[np.argsort(distances, 1)[:, : self.k]].mean(1)


class Logistic:
    """p(x) = sigmoid(f(x)), f linear (``hidden`` = 0) or TorchRL's ``MLP`` of two tanh layers
    of ``hidden`` units, fitted to the labels by the mean binary cross-entropy (full batch,
    Adam, weight decay 1e-4, 300 steps; inputs after :func:`standardiser`; initial weights
    from seed 0, the caller's torch generator left as it was)."""

    def __init__(self, x: np.ndarray, y: np.ndarray, hidden: int, steps: int = 300):
        self.z = standardiser(x)
        cells = [hidden, hidden] if hidden else []
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(0)
            f = MLP(in_features=x.shape[1], out_features=1, num_cells=cells, activation_class=Tanh)
        self.f = f.double()
        optimizer = torch.optim.Adam(self.f.parameters(), lr=1e-2, weight_decay=1e-4)
        inputs, labels = self._standardised(x), torch.from_numpy(y)
        for _ in range(steps):
            optimizer.zero_grad()
            logits = self.f(inputs)[:, 0]
            torch.nn.functional.binary_cross_entropy_with_logits(logits, labels).backward()
            optimizer.step()

    def _standardised(self, x: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(self.z(x))

    def __call__(self, x: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return torch.sigmoid(self.f(self._standardised(x))[:, 0]).numpy()


ESTIMATES = {
    "logistic": partial(Logistic, hidden=0),
    "network 32 x 32": partial(Logistic, hidden=32),
}
"""Estimates of P(y = 1 | x) compared by ``features`` beside the neighbours'."""


def first_over(p: np.ndarray, theta: float) -> int:
    """The first decision with p > theta (NaN: not reached), -1 for none."""
    over = np.flatnonzero(np.nan_to_num(p, nan=-1.0) > theta)
    return int(over[0]) if len(over) else -1


def first_shocks(p: np.ndarray, theta: float) -> list[int]:
    """Each draw's decision of the policy's one shock (:func:`first_over` of its row of p)."""
    return [first_over(row, theta) for row in p]


def leave_one_draw_out(x: np.ndarray, y: np.ndarray, estimate) -> np.ndarray:
    """(draws, decisions): p of each labelled draw's points from the other draws' labels
    (x: (draws, decisions, features), NaN where not seen; y: (draws, decisions); ``estimate``:
    (x, y) of the labelled points -> p, e.g. ``partial(Neighbours, k=15)``)."""
    seen = ~np.isnan(x[..., 0])
    p = np.full(y.shape, np.nan)
    for d in range(len(x)):
        others = np.arange(len(x)) != d
        p[d, seen[d]] = estimate(x[others][seen[others]], y[others][seen[others]])(x[d][seen[d]])
    return p


def outcomes(p: np.ndarray, y: np.ndarray, never: np.ndarray, theta: float) -> np.ndarray:
    """(draws,): whether the policy that shocks once, at the first decision with p > theta,
    ends each draw (``never``: the draw's outcome without a shock)."""
    shots = first_shocks(p, theta)
    return np.array([y[d, s] if s >= 0 else never[d] for d, s in enumerate(shots)])


def choose(x: np.ndarray, y: np.ndarray, never: np.ndarray, estimates: dict | None = None):
    """(the estimate's key, theta, success) maximising the leave-one-draw-out success of the
    policy on the labelled draws, among ``estimates`` (key -> ``estimate`` of
    :func:`leave_one_draw_out`; by default the neighbours' for each k of :data:`NEIGHBOURS`,
    keyed by k)."""
    estimates = estimates or {k: partial(Neighbours, k=k) for k in NEIGHBOURS}
    best = (None, 0.0, -1.0)
    for key, estimate in estimates.items():
        p = leave_one_draw_out(x, y, estimate)
        for theta in THRESHOLDS:
            success = float(outcomes(p, y, never, theta).mean())
            if success > best[2]:
                best = (key, float(theta), success)
    return best


class ShockOnce(Policy):
    """One shock at the first decision where ``p(observation, decision) > theta``; one object
    per episode (it remembers that it shocked)."""

    def __init__(self, p: Neighbours, theta: float):
        self.p, self.theta, self.shocked = p, theta, False

    def action(self, tensordict):
        if self.shocked:
            return 0
        x = np.append(tensordict["observation"].double().numpy(), float(tensordict["step"]))
        self.shocked = bool(self.p(x)[0] > self.theta)
        return int(self.shocked)


def fit(out: Path, seeds: int, replicas: int, overrides: list[str]) -> None:
    _, x, y, never = load_labels(out)
    seen = ~np.isnan(x[..., 0])
    held_out = held_out_seeds(seeds)
    lines = []
    with leader_env(replicas, overrides) as (_, env):
        if env is None:
            return
        sizes = [n for n in (8, 16, 32, 64) if n < len(x)] + [len(x)]
        for n in sizes:  # the learning curve: the first n labelled draws
            k, theta, cv = choose(x[:n], y[:n], never[:n])
            p = Neighbours(x[:n][seen[:n]], y[:n][seen[:n]], k)
            rows = run_jobs(env, [(ShockOnce(p, theta), s) for s in held_out], {"shocks": 1})
            means = mean_metrics(rows)
            lines.append(
                f"{n} labelled draws ({int(y[:n][seen[:n]].sum())} successes of "
                f"{int(seen[:n].sum())} single shocks): neighbours {k}, theta {theta} "
                f"(leave-one-draw-out success {cv:.0%}); held-out: return {means['return']:.2f}, "
                f"success {means['success']:.0%}, shocks {means['shocks']:.2f}"
            )
            print(lines[-1], flush=True)
    write_csv(out / "atp_shock_timing.csv", [{"policy": "shock once (k-NN)", **r} for r in rows])
    call = shlex.join(["python", *sys.argv])
    text = f"{call}\n{provenance()}\n" + "\n".join(lines) + "\n"
    (out / "atp_shock_timing.txt").write_text(text)


class ShockAgain(Policy):
    """The ``first`` policy until it shocks, then :class:`ShockOnce`'s second shock at the first
    later decision where ``p(observation, decision) > theta``; one object per episode."""

    def __init__(self, first: Policy, p, theta: float):
        self.first, self.again, self.shocked = first, ShockOnce(p, theta), False

    def action(self, tensordict):
        if self.shocked:
            return self.again.action(tensordict)
        self.shocked = bool(self.first.action(tensordict))
        return int(self.shocked)


def kept(path: Path, seeds: list[int], run) -> dict:
    """``run()`` (a dict of tensors) once, kept in ``path`` beside ``seeds``; read from there
    after (ValueError if it holds other draws)."""
    if not path.exists():
        torch.save({"seeds": seeds, **run()}, path)
    stored = torch.load(path)
    if stored["seeds"] != seeds:
        raise ValueError(f"{path} holds other draws: move it away to rerun")
    return stored


def second_shocks(env, path: Path, first: dict[int, int], decisions: int):
    """(readings (draws, decisions, readings), outcomes (draws, decisions)) of a second shock at
    each decision after each draw's first (``first``: seed -> the decision of its failed first
    shock): the readings there, before the second shock, and whether it ends the arrhythmia
    (NaN and 0 up to the first). Run once and :func:`kept` in ``path``."""

    def run() -> dict:
        jobs = [(Schedule([at, k]), s) for s, at in first.items() for k in range(at + 1, decisions)]
        with torch.no_grad():
            rollouts = iter(spread_episodes(env, jobs, MAX_STEPS))
        size = env.observation_spec["observation"].shape[-1]
        readings = torch.full((len(first), decisions, size), float("nan"))
        y2 = torch.zeros(len(first), decisions)
        for i, at in enumerate(first.values()):
            for k in range(at + 1, decisions):
                rollout = next(rollouts)
                readings[i, k] = rollout["observation"][k]
                y2[i, k] = float(rollout["next", "success"][-1])
        return {"readings": readings, "second": y2}

    stored = kept(path, list(first), run)
    return stored["readings"].double().numpy(), stored["second"].double().numpy()


def first_shock_readings(env, path: Path, first: dict[int, int], decisions: int) -> np.ndarray:
    """(draws, decisions, readings): the readings after each draw's one shock (``first``: seed ->
    its decision), one episode each, NaN up to the shock and after the episode's end. Run once
    and :func:`kept` in ``path``."""

    def run() -> dict:
        jobs = [(Schedule([at]), seed) for seed, at in first.items()]
        with torch.no_grad():
            rollouts = spread_episodes(env, jobs, MAX_STEPS)
        return {"readings": readings_after(rollouts, list(first.values()), decisions)}

    return kept(path, list(first), run)["readings"].double().numpy()


def second(
    replicas: int, out: Path, overrides: list[str], first_at: int | None = None, held_out: int = 20
) -> None:
    """The outcomes of a second shock at each decision after failed first shocks: the shock-once
    policy's (``first_at`` None), or a shock at decision ``first_at`` on every draw. With
    hindsight (the second shock at its best decision) an upper bound on a policy that shocks
    again after a failed shock. Then the same leave-one-draw-out choice as ``fit``'s, among every
    draw with a first shock, of a rule timing a second shock from the readings after the first
    (a shock that works mostly ends the arrhythmia only after the last decision, so a policy
    meets those draws too: there a second shock counts as undoing the first, a pessimistic
    label), and that policy (:class:`ShockAgain`, fitted on every labelled draw) on
    ``held_out`` held-out seeds. Into ``<out>/atp_shock_timing_second[_at<first_at>]``: ``.pt``
    (the second shocks' readings and outcomes; an existing one is read, not rerun), ``.txt`` and
    ``.csv`` (per held-out seed); the readings after the first shocks that work in
    ``atp_shock_timing_worked[_at<first_at>].pt``."""
    seeds, x, y, never = load_labels(out)
    seen = ~np.isnan(x[..., 0])
    if first_at is None:
        k, theta, _ = choose(x, y, never)
        p = leave_one_draw_out(x, y, partial(Neighbours, k=k))
        first, ends = first_shocks(p, theta), int(outcomes(p, y, never, theta).sum())
        policy = f"shock once (neighbours {k}, theta {theta})"
        first_policy = partial(ShockOnce, Neighbours(x[seen], y[seen], k), theta)
    else:
        first, ends = [first_at] * len(x), int(y[:, first_at].sum())
        policy = f"a shock at decision {first_at}"
        first_policy = partial(Schedule, [first_at])
    failed = [d for d, shot in enumerate(first) if shot >= 0 and not y[d, shot]]
    works = [d for d, shot in enumerate(first) if shot >= 0 and y[d, shot]]
    suffix = "" if first_at is None else f"_at{first_at}"
    path = out / f"atp_shock_timing_second{suffix}"
    with leader_env(replicas, overrides) as (decisions, env):
        if env is None:
            return
        failed_first = {seeds[d]: first[d] for d in failed}
        readings, y2 = second_shocks(env, path.with_suffix(".pt"), failed_first, decisions)
        first_works = {seeds[d]: first[d] for d in works}
        after_works = first_shock_readings(
            env, out / f"atp_shock_timing_worked{suffix}.pt", first_works, decisions
        )
        lines = [shlex.join(["python", *sys.argv]), provenance()]
        lines.append(
            f"{policy}: ends {ends} of {len(x)} labelled draws; its shock fails on "
            f"{len(failed)}, it never shocks on {first.count(-1)}"
        )
        for i, d in enumerate(failed):
            again = [int(k) for k in np.flatnonzero(y2[i])]
            lines.append(f"draw {seeds[d]}: shock at {first[d]} fails; a second ends it at {again}")
        rescued = int(y2.max(1, initial=0).sum())
        lines.append(
            f"a second shock ends {rescued} of the {len(failed)} (at its best decision, with "
            f"hindsight): shocking again ends at most {ends + rescued} of {len(x)} "
            f"({(ends + rescued) / len(x):.1%})"
        )
        if len(failed) > 1:
            # every shocked draw: a second shock where the first worked counts as undoing it
            x2 = features(np.concatenate([readings, after_works]))
            y2 = np.concatenate([y2, np.zeros(after_works.shape[:2])])
            kept = np.r_[np.zeros(len(failed)), np.ones(len(works))]  # without a second shock
            unshocked = int(sum(never[d] for d, shot in enumerate(first) if shot < 0))
            k2, theta2, _ = choose(x2, y2, kept)
            p2 = leave_one_draw_out(x2, y2, partial(Neighbours, k=k2))
            timed = int(outcomes(p2, y2, kept, theta2).sum())
            lines.append(
                f"timed from the readings after the first shock (neighbours {k2}, theta {theta2}; "
                f"each of the {len(x2)} shocked draws' from the others; a second shock where the "
                f"first worked counted as undoing it): ends {timed} of them; with the "
                f"{unshocked} unshocked draws that end by themselves, {timed + unshocked} of "
                f"{len(x)} ({(timed + unshocked) / len(x):.1%})"
            )
            seen2 = ~np.isnan(x2[..., 0])
            again = Neighbours(x2[seen2], y2[seen2], k2)
            jobs = [
                (ShockAgain(first_policy(), again, theta2), s) for s in held_out_seeds(held_out)
            ]
            rows = run_jobs(env, jobs, {"shocks": 1})
            means = mean_metrics(rows)
            lines.append(
                f"that policy, fitted on every labelled draw, on {held_out} held-out seeds: "
                f"return {means['return']:.2f}, success {means['success']:.0%}, "
                f"shocks {means['shocks']:.2f}"
            )
            write_csv(
                path.with_suffix(".csv"), [{"policy": "shock again (k-NN)", **r} for r in rows]
            )
    print("\n".join(lines[2:]), flush=True)
    path.with_suffix(".txt").write_text("\n".join(lines) + "\n")


def worked(out: Path, first_at: int) -> None:
    """Do the catheter's readings after a shock at decision ``first_at`` tell whether it worked?
    The readings after it where it works against those where it fails (both stored by ``second
    --first``, which runs first); at each later decision, the :class:`Neighbours` estimate (k of
    :data:`NEIGHBOURS`, the best) of each draw from the other draws still running there, and
    how many episodes have visibly ended; into ``atp_shock_timing_worked_at<first_at>.txt``."""
    _, x, y, _ = load_labels(out)
    works = int(y[:, first_at].sum())
    stored = {
        name: torch.load(out / f"atp_shock_timing_{name}_at{first_at}.pt")
        for name in ("worked", "second")
    }
    after_works = stored["worked"]["readings"].double().numpy()
    after_fails = stored["second"]["readings"].double().numpy()
    decisions = x.shape[1]
    lines = [shlex.join(["python", *sys.argv]), provenance()]
    lines.append(
        f"a shock at decision {first_at} works on {works} of {len(x)} labelled draws; at "
        "each later decision, the draws still running and how often the readings there tell a "
        "working shock from a failed one (each draw's vote from the other draws)"
    )
    readings = np.concatenate([after_works, after_fails])
    label = np.r_[np.ones(len(after_works)), np.zeros(len(after_fails))]
    for k in range(first_at + 1, decisions):
        x_k = readings[:, k : k + 1]  # (draws, 1, readings): one decision
        running = ~np.isnan(x_k[:, 0, 0])
        labels = label[running]
        told = {}
        for n in NEIGHBOURS:
            p = leave_one_draw_out(x_k, label[:, None], partial(Neighbours, k=n))
            told[n] = ((p[running, 0] > 0.5) == labels).mean()
        n = max(told, key=told.get)
        lines.append(
            f"decision {k}: {int(labels.sum())} working and {int((1 - labels).sum())} failed "
            f"still running ({works - int(labels.sum())} ended); told apart on "
            f"{told[n]:.0%} (neighbours {n}; the larger group alone: "
            f"{max(labels.mean(), 1 - labels.mean()):.0%})"
        )
    print("\n".join(lines[2:]), flush=True)
    (out / f"atp_shock_timing_worked_at{first_at}.txt").write_text("\n".join(lines) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "stage", choices=("label", "fit", "features", "observe", "second", "worked")
    )
    parser.add_argument("--draws", type=int, default=96)
    parser.add_argument("--seeds", type=int, default=20, help="held-out seeds (fit, second)")
    parser.add_argument("--replicas", type=int, default=100)
    parser.add_argument(
        "--first", type=int, help="second: the first shock at this decision on every draw"
    )
    parser.add_argument("--tag", default="other", help="observe: the observation's name")
    parser.add_argument("--out", type=Path, default=Path("experiments/results"))
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. env.mesh.cells=20")
    args = parser.parse_intermixed_args()
    if args.stage == "label":
        label(args.draws, args.replicas, args.out, args.overrides)
    elif args.stage == "features":
        compare_features(args.out)
    elif args.stage == "observe":
        observe(args.out, args.tag, args.replicas, args.overrides)
    elif args.stage == "second":
        second(args.replicas, args.out, args.overrides, args.first, args.seeds)
    elif args.stage == "worked":
        worked(args.out, args.first)
    else:
        fit(args.out, args.seeds, args.replicas, args.overrides)


if __name__ == "__main__":
    main()
