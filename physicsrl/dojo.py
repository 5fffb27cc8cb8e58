"""The Dojo: DQN training of a Q-network against a (distributed) TorchRL environment.

Report section 5, on TorchRL: :class:`Dojo` collects transitions with an epsilon-greedy policy,
stores them in a replay buffer, trains the Q-network on sampled batches, evaluates the greedy
policy on held-out seeds, logs to TensorBoard and a text log, and checkpoints everything needed
to continue after a kill. Readable top to bottom: ``__init__`` wires the TorchRL objects,
:meth:`train` is the loop, the rest are its steps.

Run it on the leader inside ``with coordinator`` when the env drives a distributed simulator::

    coordinator = Coordinator()
    env = make_env(cfg, coordinator)           # every rank, same order
    with coordinator:
        if coordinator.is_leader():
            config = TrainConfig(iterations=200)  # every other setting: its default
            dojo = Dojo(make_q_network(env), env, config, log_dir="runs/heat")
            dojo.train()

Reproducibility: every collection batch starts from a reset of the env seeded with
:func:`physicsrl.config.train_seed` (``reset_at_each_iter``; otherwise episodes run across
batches, and the env is reseeded so after each evaluation, which ran held-out seeds), and
checkpoints hold the weights, target network, optimizer, replay buffer, counters and every
random generator state (torch, numpy, python, the env's), so a resumed run repeats an
uninterrupted one step for step when the env is deterministic given its seed.
"""

from __future__ import annotations

import logging
import math
import signal
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, NoReturn

import torch
from tensordict import TensorDictBase
from torchrl.checkpoint import Checkpoint, GlobalRNGState, StateDictCheckpointAdapter
from torchrl.collectors import Collector
from torchrl.data.postprocs import MultiStep
from torchrl.envs import EnvBase, RewardSum, TransformedEnv
from tqdm import tqdm

from physicsrl import builders
from physicsrl.checkpoint import Checkpoints, CheckpointsError, State
from physicsrl.checks import integer
from physicsrl.config import TrainConfig, as_dict, check_seeds, train_config, train_seed
from physicsrl.evaluation import run_episodes
from physicsrl.tables import mean_metrics, write_csv

__all__ = ["Dojo", "Counters", "NonFiniteTraining", "charge_actions", "n_step_transitions"]

log = logging.getLogger("physicsrl.dojo")


@dataclass
class Counters:
    iteration: int = 0  # collection batches done
    frames: int = 0  # env steps taken by the exploration policy
    episodes: int = 0  # training episodes finished
    updates: int = 0  # gradient steps
    time_s: dict = field(default_factory=dict)  # cumulative seconds per phase
    # the "simulation" of time_s by the env's phases, where it reports them: (seconds,
    # replica-steps, batch-steps) per phase (the torch replicas' ``simulated``)
    simulated: dict = field(default_factory=dict)


class NonFiniteTraining(ArithmeticError):
    """A loss or a weight became NaN or infinite: :meth:`Dojo.train` stops at once, keeping the
    checkpoints written before (the message names the iteration and what became non-finite)."""


def n_step_transitions(data: TensorDictBase, n_steps: int, gamma: float) -> TensorDictBase:
    r"""The n-step transitions of a batch of consecutive steps (shape (..., T): T steps of
    each environment of a batch).

    Step t becomes (s_t, a_t, R_t, s_{t+k}) with :math:`R_t = \sum_{i<k} \gamma^i r_{t+i}` and
    k = min(n, steps until the episode or the batch ends); ``steps_to_next_obs`` = k makes the
    TD target :math:`R_t + \gamma^k \max_a Q(s_{t+k}, a)`, and the done flags are those of
    step t+k-1, so no target bootstraps from a state after the end of an episode. TorchRL's
    ``MultiStep`` does the sums but keeps step t's own done flags.
    """
    out = MultiStep(gamma, n_steps)(data)
    steps = out["steps_to_next_obs"].reshape(data.shape)
    last = torch.arange(data.shape[-1]) + steps - 1  # (..., T)
    ended = data["next"]
    for key in ("done", "terminated", "truncated"):
        if key in ended.keys():  # not every env reports truncated
            flags = ended[key]  # (..., T, 1)
            index = last.reshape(*last.shape, *[1] * (flags.ndim - last.ndim)).expand_as(flags)
            out["next", key] = flags.gather(data.ndim - 1, index)
    return out


def charge_actions(data: TensorDictBase, costs: torch.Tensor) -> TensorDictBase:
    """``data`` with ``costs[a]`` subtracted from the reward of each step that took action ``a``
    (one-hot or index actions; actions beyond ``costs`` cost nothing)."""
    action = data["action"]
    chosen = action.long().argmax(-1) if action.dtype == torch.bool else action.long()
    padded = torch.cat([costs, torch.zeros(max(0, int(chosen.max()) + 1 - len(costs)))])
    out = data.clone(recurse=False)
    out["next"] = data["next"].clone(recurse=False)
    reward = data["next", "reward"]
    out["next", "reward"] = reward - padded[chosen].reshape(reward.shape).to(reward.dtype)
    return out


class Dojo:
    """DQN training pipeline: collect, store, learn, evaluate, log, checkpoint.

    Every setting comes from ``config`` (:class:`~physicsrl.config.TrainConfig`, or a mapping of
    its keys on its defaults: :func:`~physicsrl.config.train_config`), and every TorchRL object
    but the Q-network is built from it by :mod:`physicsrl.builders`: double-DQN ``DQNLoss``, its
    target updater, Adam, the replay buffer and the annealed ``EGreedyModule``. The sections
    used: ``collector`` (frames per batch, reset at each batch), ``optim`` (updates per batch,
    ``learning_starts`` frames before the first, when the Q-network's ``Normalizer`` is fitted
    to the stored data, ``grad_clip``), ``loss`` (``n_steps``: :func:`n_step_transitions`;
    ``action_costs``: a training-only penalty per action, :func:`charge_actions`, never in the
    returns logged or evaluated), ``eval`` (every so many iterations, on one episode per
    held-out seed), ``checkpoint``, ``logger`` and ``seed`` (batch ``i`` resets the env with
    :func:`~physicsrl.config.train_seed`).

    Parameters
    ----------
    q_network:
        A greedy Q-value actor (``QValueActor``) reading the env keys in its ``in_keys``
        (:func:`~physicsrl.builders.make_q_network`).
    env:
        A TorchRL env with a discrete action spec. Stepped only from the calling rank.
    config:
        The training config (default: :class:`~physicsrl.config.TrainConfig`'s defaults).
    log_dir:
        Run directory: TensorBoard events (``tensorboard/``: training scalars by iteration,
        and each evaluation metric against iterations, environment steps, training wall-clock
        seconds and core-seconds), ``eval.csv``, checkpoints (``checkpoints/``) and a
        memory-mapped buffer (``buffer/``). ``None``: no files.
    checkpoint_extra:
        Saved with every checkpoint under ``"extra"``, after ``"config"``: ``config`` as plain
        dicts, from which ``physicsrl-eval`` rebuilds the env when it holds the task's groups
        (``{**load_config("heat", seed=0), "iterations": 200}``).
    coordinator:
        The env's :class:`~physicsrl.coordinated.Coordinator`: time spent sending calls to the
        followers is reported as coordination time.
    action_counts:
        ``{"shocks": 1}``: evaluation also reports how often action 1 was taken.
    environments, cores:
        The environments behind ``env`` (``collector.frames_per_env`` x N frames per batch)
        and the cores (MPI ranks) the job uses, for the core-seconds axis.
    """

    def __init__(
        self,
        q_network: torch.nn.Module,
        env: EnvBase,
        config: TrainConfig | Mapping | None = None,
        *,
        log_dir: str | Path | None = None,
        checkpoint_extra: Mapping | None = None,
        coordinator: Any = None,
        action_counts: Mapping[str, int] | None = None,
        environments: int = 1,
        cores: int = 1,
    ):
        self.config = config = train_config(config)
        self.env = env
        self.q_network = q_network
        self.loss = builders.make_loss(self.q_network, env, config.loss)
        self.target_updater = builders.make_target_updater(self.loss, config.loss.target)
        self.optimizer = builders.make_optimizer(
            self.loss, config.learning_rate, config.optim.weight_decay
        )
        self.log_dir = None if log_dir is None else Path(log_dir)
        scratch = None if self.log_dir is None else self.log_dir / "buffer"
        self.replay_buffer = builders.make_buffer(config.buffer, scratch)
        self.exploration = builders.make_exploration(self.q_network, env, config.agent.exploration)
        self.frames_per_batch = config.collector.frames(environments)
        self.action_costs = torch.tensor([float(c) for c in config.loss.action_costs])
        self.eval_seeds = [int(s) for s in config.eval.seeds]
        self.checkpoint_extra = {"config": as_dict(config), **(checkpoint_extra or {})}
        self.coordinator = coordinator
        self.action_counts = dict(action_counts or {})
        self.cores = cores
        self.counters = Counters()
        self.history: list[dict] = []  # one row per evaluation
        self.checkpoints = (
            None
            if self.log_dir is None
            else Checkpoints(self.log_dir / "checkpoints", config.checkpoint.keep)
        )
        self.writer = None
        self._cost_writers: dict = {}  # the evaluations' cost axes (_open_logs)
        self.stopped: str | None = None  # why train() stopped early (request_stop)
        self._saved_iteration = -1  # the iteration of the last checkpoint written or loaded
        self._checkpoint_failed = False
        self._pending_rng: dict | None = None
        self._collector: Collector | None = None

    # the loop -----------------------------------------------------------------------------
    def train(self, iterations: int | None = None, handle_signals: bool = True) -> dict:
        """Train until ``iterations`` (default: ``config.iterations``) iterations have run in
        total (restored ones included).

        Stops early, after a checkpoint, on SIGINT/SIGTERM (when called from the main thread
        with ``handle_signals``) or :meth:`request_stop`. Returns :meth:`summary`. A new run
        (no checkpoint loaded or written) refuses a ``log_dir`` that holds checkpoints.
        """
        config = self.config
        iterations = (
            config.iterations if iterations is None else integer("iterations", iterations, 1)
        )
        check_seeds(config.seed, iterations, self.eval_seeds)
        if self._saved_iteration < 0 and self.checkpoints and self.checkpoints.latest():
            raise FileExistsError(  # its checkpoints would mix with this run's
                f"log_dir={self.log_dir} holds another run's checkpoints: load_checkpoint(log_dir) "
                "continues it, a new run needs another directory"
            )
        if self.counters.iteration >= iterations:  # a resume of a finished run
            log.warning(
                "nothing to train: iteration %d of %d is done (raise iterations to train on)",
                self.counters.iteration,
                iterations,
            )
        self._open_logs()
        started, sent, phases = time.perf_counter(), self._broadcast_s(), self._phases()
        collector = self._collector = Collector(
            TransformedEnv(self.env, RewardSum()),  # each episode's return so far
            self.exploration,
            frames_per_batch=self.frames_per_batch,
            total_frames=-1,  # the loop counts iterations itself (and never closes the env)
            reset_at_each_iter=config.collector.reset_at_each_iter,
            pre_collect_hook=self._seed_next_batch,
            auto_register_policy_transforms=False,
        )
        self._account_simulation(started, sent, phases)  # the collector's first reset
        if self._pending_rng is not None:  # after the collector's own initial reset
            self._set_rng_state(self._pending_rng)
            self._pending_rng = None
        restore = self._install_signal_handlers() if handle_signals else None
        bar = tqdm(
            total=iterations,
            initial=self.counters.iteration,
            desc="train",
            unit="it",
            dynamic_ncols=True,
            mininterval=0.5,
            disable=not config.logger.progress,
        )
        batches = iter(collector)
        try:
            while self.counters.iteration < iterations and self.stopped is None:
                # 1. collect a batch with the exploration policy (the simulation runs here)
                started, sent, phases = time.perf_counter(), self._broadcast_s(), self._phases()
                data = next(batches).exclude("collector")
                collect_s = self._account_simulation(started, sent, phases)
                returns = self._record_batch(data)
                self.exploration[-1].step(data.numel())  # anneal epsilon
                if len(self.action_costs):
                    data = charge_actions(data, self.action_costs)
                if config.loss.n_steps > 1:
                    gamma = float(self.loss.value_estimator.gamma)
                    data = n_step_transitions(data, config.loss.n_steps, gamma)
                self.replay_buffer.extend(data.reshape(-1))

                # 2. learn from replayed transitions
                started = time.perf_counter()
                learning = self.counters.frames >= config.optim.learning_starts
                losses = self._learn() if learning else []
                self._add_time("learner", time.perf_counter() - started)
                self.counters.iteration += 1

                # 3. evaluate, log, checkpoint
                if self._due(config.eval.every):
                    self.evaluate()
                self._log_iteration(data.numel(), collect_s, losses, returns)
                if self._due(config.checkpoint.every):
                    self.save_checkpoint()
                bar.update(1)
                bar.set_postfix(self._postfix(returns), refresh=False)
        finally:
            if restore is not None:
                restore()
            bar.close()
        last = self.history[-1]["iteration"] if self.history else None
        final = self.stopped is None and last != self.counters.iteration
        if final:
            self.evaluate()  # the final greedy policy, kept in the last checkpoint too
        if final or self._saved_iteration != self.counters.iteration:
            self.save_checkpoint()
        if self.stopped is not None:
            log.warning("stopped at iteration %d: %s", self.counters.iteration, self.stopped)
        if (
            self.counters.frames
            and not self.counters.episodes
            and config.collector.reset_at_each_iter
        ):
            log.warning(
                "no training episode ended: each batch of %d frames restarts every environment's "
                "episode (collector.reset_at_each_iter); set collector.frames_per_env to at "
                "least an episode's length",
                self.frames_per_batch,
            )
        if self.writer is not None:
            for writer in (self.writer, *self._cost_writers.values()):
                writer.flush()
        return self.summary()

    # the steps ----------------------------------------------------------------------------
    def _due(self, every: int) -> bool:
        """Whether the iteration just done is a multiple of ``every`` (0: never)."""
        return every > 0 and self.counters.iteration % every == 0

    def _seed_next_batch(self) -> None:
        if self.config.collector.reset_at_each_iter:
            self.env.set_seed(train_seed(self.config.seed, self.counters.iteration))

    def _record_batch(self, data: TensorDictBase) -> list[float]:
        """Count frames and episodes; return the returns of the episodes finished here (the
        collector's ``RewardSum`` at their last steps, episodes begun in earlier batches
        included). The batch is (time,) for one environment and (environments, time) for
        many."""
        self.counters.frames += data.numel()
        ended = data["next", "done"].reshape(data.shape)
        returns = data["next", "episode_reward"].reshape(data.shape)[ended].tolist()
        self.counters.episodes += len(returns)
        return returns

    def _learn(self) -> list[float]:
        normalizer = builders.normalizer_of(self.q_network)
        if normalizer is not None and not normalizer.fitted:
            stored = self.replay_buffer[: len(self.replay_buffer)]
            inputs = builders.Inputs.concat(*(stored[key] for key in self.q_network.in_keys))
            normalizer.fit(inputs)  # shared by the online and target networks
            log.info(
                "observation normaliser: loc %s scale %s",
                normalizer.loc.tolist(),
                normalizer.scale.tolist(),
            )
        losses = []
        for _ in range(self.config.optim.updates_per_batch):
            batch = self.replay_buffer.sample(self.config.buffer.batch_size)
            loss = self.loss(batch)["loss"]
            self.optimizer.zero_grad()
            loss.backward()
            if self.config.optim.grad_clip:
                torch.nn.utils.clip_grad_norm_(self.loss.parameters(), self.config.optim.grad_clip)
            self.optimizer.step()
            self.target_updater.step()
            self.counters.updates += 1
            losses.append(float(loss.detach()))
            if not math.isfinite(losses[-1]):
                self._non_finite(f"the loss became {losses[-1]}")
        bad = [name for name, p in self.loss.named_parameters() if not p.isfinite().all()]
        if bad:
            self._non_finite(f"the weights {bad[0]} became non-finite")
        return losses

    def _non_finite(self, what: str) -> NoReturn:
        saved = self._saved_iteration
        kept = f"the checkpoint of iteration {saved} is kept" if saved >= 0 else "no checkpoint"
        raise NonFiniteTraining(
            f"iteration {self.counters.iteration + 1}, update {self.counters.updates}: {what}; "
            f"training stopped ({kept})"
        )

    def evaluate(self) -> dict:
        """Average metrics of the greedy Q-network over the held-out seeds (``eval.seeds``),
        recorded in the history and the logs."""
        started = time.perf_counter()
        rows = run_episodes(self.env, self.q_network, self.eval_seeds, self.action_counts)
        metrics = mean_metrics(rows)
        self._add_time("evaluation", time.perf_counter() - started)
        if self._collector is not None and not self.config.collector.reset_at_each_iter:
            # evaluation reseeded the env with held-out seeds and left the batch in flight
            self.env.set_seed(train_seed(self.config.seed, self.counters.iteration))
            self._collector.reset()
        row = {
            "iteration": self.counters.iteration,
            "frames": self.counters.frames,
            "wall_s": round(sum(self.counters.time_s.values()), 3),  # of training, resumes too
            **metrics,
        }
        self.history.append(row)
        self._log_evaluation(row)
        return metrics

    def request_stop(self, reason: str = "stop requested") -> None:
        """End :meth:`train` after the current iteration (with a checkpoint)."""
        self.stopped = reason

    def summary(self) -> dict:
        last = self.history[-1] if self.history else {}
        total = sum(self.counters.time_s.values())
        return {
            **{k: v for k, v in asdict(self.counters).items() if k != "time_s"},
            "time_s": dict(self.counters.time_s),
            "total_s": total,
            "env_steps_per_s": self.counters.frames
            / max(self.counters.time_s.get("simulation", 0.0), 1e-9),
            "eval": last,
            "stopped": self.stopped,
        }

    # checkpoints --------------------------------------------------------------------------
    def checkpoint(self, extra: dict) -> Checkpoint:
        """The Dojo's state as one TorchRL :class:`~torchrl.checkpoint.Checkpoint`: counters,
        evaluation history, Q-network (its normaliser included), loss (online and target
        networks), exploration (epsilon), optimizer, target updater, replay buffer (contents and
        cursor), the random generators (torch, numpy and python through ``GlobalRNGState``; the
        env's through its ``rng_state()``) and ``extra`` (JSON; filled in place on loading)."""
        state_dict = StateDictCheckpointAdapter()  # the buffer's own dump/load is not needed
        checkpoint = Checkpoint(
            format="archive",
            counters=State(lambda: asdict(self.counters), self._set_counters),
            history=self.history,  # JSON, restored in place
            q_network=self.q_network,
            loss=self.loss,
            exploration=self.exploration,
            optimizer=self.optimizer,
            target_updater=self.target_updater,
            rng=State(self._rng_state, self._defer_rng_state),
            extra=extra,
        )
        return checkpoint.register("replay_buffer", self.replay_buffer, adapter=state_dict)

    def _set_counters(self, state: dict) -> None:
        self.counters = Counters(**state)
        self._saved_iteration = self.counters.iteration

    def _rng_state(self) -> dict:
        state = {"global": GlobalRNGState().state_dict()}
        if hasattr(self.env, "rng_state"):  # an env with its own episode generator
            state["env"] = self.env.rng_state()
        return state

    def _defer_rng_state(self, state: dict) -> None:
        self._pending_rng = state  # applied when train() has built its collector

    def _set_rng_state(self, state: dict) -> None:
        GlobalRNGState().load_state_dict(state["global"])
        if "env" in state:
            self.env.set_rng_state(state["env"])

    def save_checkpoint(self) -> Path | None:
        """Checkpoint now (the newest ``checkpoint.keep`` are kept). A directory that cannot be
        written stops training (:meth:`request_stop` naming it) with the older checkpoints
        kept."""
        if self.checkpoints is None or self._checkpoint_failed:
            return None
        started = time.perf_counter()
        checkpoint = self.checkpoint(dict(self.checkpoint_extra))
        try:
            path = self.checkpoints.save(checkpoint, self.counters.iteration)
        except CheckpointsError as error:
            self._checkpoint_failed = True
            self.request_stop(str(error))
            return None
        self._saved_iteration = self.counters.iteration
        self._add_time("checkpoint", time.perf_counter() - started)
        log.info("checkpoint %s (%s)", path, self._position())
        return path

    def load_checkpoint(self, path: str | Path) -> dict:
        """Restore the checkpoint ``path``, or a run directory's newest readable one (as
        ``resume=<run dir>`` does; :class:`~physicsrl.checkpoint.CheckpointsError` if it has
        none); return its ``extra``."""
        if Path(path).is_dir():
            path = Checkpoints(Path(path) / "checkpoints", 1).newest_readable()
        extra: dict = {}
        self.checkpoint(extra).load(path, map_location="cpu")
        self.history[:] = [self._in_order(row) for row in self.history]
        self._apply_settings()
        log.info("resumed from %s at %s", path, self._position())
        return extra

    def _apply_settings(self) -> None:
        """Give the settings that the loaded state holds this config's values (a resume with
        other settings runs with them): Adam's learning rate and weight decay, the loss's
        discount, the exploration's epsilons (its current epsilon goes on from the state); the
        replay buffer's stored batch size is not used: :meth:`_learn` samples the config's."""
        config = self.config
        for group in self.optimizer.param_groups:
            group["lr"], group["weight_decay"] = config.learning_rate, config.optim.weight_decay
        self.loss.value_estimator.gamma.fill_(config.loss.gamma)
        greedy = self.exploration[-1]
        greedy.eps_init.fill_(config.agent.exploration.eps_init)
        greedy.eps_end.fill_(config.agent.exploration.eps_end)

    def _in_order(self, row: dict) -> dict:
        """An evaluation row restored from JSON (its keys sorted) in :meth:`evaluate`'s order:
        the counters, return and length, the env's flags (sorted), the action counts."""
        first, last = ("iteration", "frames", "wall_s", "return", "length"), (*self.action_counts,)
        middle = sorted(key for key in row if key not in first + last)
        return {key: row[key] for key in (*first, *middle, *last) if key in row}

    def _position(self) -> str:
        return (
            f"iteration {self.counters.iteration}, {self.counters.frames} frames, "
            f"buffer {len(self.replay_buffer)}"
        )

    # logging ------------------------------------------------------------------------------
    def _open_logs(self) -> None:
        if self.log_dir is None or self.writer is not None:
            return
        self.log_dir.mkdir(parents=True, exist_ok=True)
        if not self.config.logger.tensorboard:
            return
        from torch.utils.tensorboard import SummaryWriter

        # purge_step drops the events that a killed run wrote after its last checkpoint. It
        # applies to every tag of a directory, so each step axis has its own: the iterations
        # here, each cost axis of the evaluations in a subdirectory.
        directory = self.log_dir / "tensorboard"
        self.writer = SummaryWriter(str(directory), purge_step=self.counters.iteration + 1)
        wall_s = sum(self.counters.time_s.values())
        self._cost_writers = {
            axis: SummaryWriter(str(directory / axis), purge_step=step + 1)
            for axis, step in self._cost_steps(self.counters.frames, wall_s).items()
        }

    def _cost_steps(self, frames: int, wall_s: float) -> dict[str, int]:
        """The steps of the evaluations' cost axes: env steps, wall and core seconds."""
        return {
            "eval_by_env_steps": frames,
            "eval_by_wall_s": round(wall_s),
            "eval_by_core_s": round(wall_s * self.cores),
        }

    def _log_iteration(self, frames, collect_s, losses, returns) -> None:
        if self.writer is None:
            return
        step, scalar = self.counters.iteration, self.writer.add_scalar
        if losses:
            scalar("train/loss", sum(losses) / len(losses), step)
        if returns:
            scalar("train/return", sum(returns) / len(returns), step)
        scalar("train/epsilon", float(self.exploration[-1].eps), step)
        scalar("train/frames", self.counters.frames, step)
        scalar("perf/env_steps_per_s", frames / max(collect_s, 1e-9), step)
        for phase, seconds in self.counters.time_s.items():
            scalar(f"time/{phase}_s", seconds, step)
        for phase, (seconds, *_) in self.counters.simulated.items():
            scalar(f"time/simulation_{phase}_s", seconds, step)

    def _log_evaluation(self, row: dict) -> None:
        counters = ("iteration", "frames", "wall_s")
        text = " ".join(f"{k} {v:.4g}" for k, v in row.items() if k not in counters)
        log.info("eval at iteration %d (%d frames): %s", row["iteration"], row["frames"], text)
        if self.writer is not None:
            costs = self._cost_steps(row["frames"], row["wall_s"])
            for key, value in row.items():
                if key not in counters:
                    name = "success_rate" if key == "success" else key
                    self.writer.add_scalar(f"eval/{name}", value, row["iteration"])
                    for axis, step in costs.items():
                        self._cost_writers[axis].add_scalar(f"{axis}/{name}", value, step)
        if self.log_dir is not None:
            write_csv(self.log_dir / "eval.csv", self.history)

    def _postfix(self, returns: list[float]) -> dict:
        postfix = {"eps": f"{float(self.exploration[-1].eps):.2f}", "frames": self.counters.frames}
        if returns:
            postfix["ret"] = f"{sum(returns) / len(returns):.3g}"
        if self.history:
            postfix["eval"] = f"{self.history[-1]['return']:.3g}"
        return postfix

    def _account_simulation(self, started: float, sent: float, phases: dict) -> float:
        """Add the seconds since ``started`` to the simulation time, less the leader's seconds
        sending calls since it had sent ``sent`` (coordination time), and the env's phases
        since ``phases`` to :attr:`Counters.simulated`; return the seconds."""
        seconds = time.perf_counter() - started
        coordination_s = self._broadcast_s() - sent
        self._add_time("coordination", coordination_s)
        self._add_time("simulation", seconds - coordination_s)
        for phase, after in self._phases().items():
            total = self.counters.simulated.get(phase, (0.0, 0, 0))
            before = phases.get(phase, (0.0, 0, 0))
            self.counters.simulated[phase] = tuple(
                t + a - b for t, a, b in zip(total, after, before, strict=True)
            )
        return seconds

    def _add_time(self, phase: str, seconds: float) -> None:
        self.counters.time_s[phase] = self.counters.time_s.get(phase, 0.0) + seconds

    def _phases(self) -> dict[str, tuple[float, int, int]]:
        """The env's (seconds, replica-steps, batch-steps) of each of its phases so far ({}: it
        does not say)."""
        return dict(vars(self.env).get("simulated", {}))  # not getattr: EnvBase searches on

    def _broadcast_s(self) -> float:
        """The leader's seconds sending parallel calls to the followers so far (0: none)."""
        return float(getattr(self.coordinator, "broadcast_s", 0.0))

    def _install_signal_handlers(self) -> Callable[[], None] | None:
        """SIGINT/SIGTERM: finish the iteration, checkpoint, return (twice: interrupt now)."""
        if threading.current_thread() is not threading.main_thread():
            return None
        previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}

        def handler(signum, frame):
            if self.stopped is not None and signum == signal.SIGINT:
                raise KeyboardInterrupt
            self.request_stop(f"received {signal.Signals(signum).name}")

        for s in previous:
            signal.signal(s, handler)

        def restore():
            for s, h in previous.items():
                signal.signal(s, h)

        return restore
