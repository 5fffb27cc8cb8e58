"""``physicsrl-train [key=value ...] [mpi.ranks=N]``: DQN training (the Dojo) under Hydra + MPI.

Composes ``conf/train.yaml``: the task groups ``env``, ``observation``, ``reward`` (``env=ms``
picks ``observation=catheter reward=atp`` unless given), the ``agent`` group (``agent=dqn``:
network and exploration) and sections named after the TorchRL objects they configure
(``collector``, ``buffer``, ``loss``, ``optim``, ``logger``, ``checkpoint``, ``eval``).

Every rank builds the environment (its simulator is coordinated); the leader trains, logs and
writes files in the run directory; followers serve the simulation. The config is checked on
every rank before anything is simulated: an unknown key, a wrong type or a bad value exits with
status 2 and one line naming the key. ``resume=true`` continues the newest run of this config,
``resume=<run dir>`` that run (in its directory). SIGINT/SIGTERM checkpoint and stop cleanly.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from physicsrl.launch import output_dir, relaunch, run_hydra

log = logging.getLogger("physicsrl.train")

# env option -> the observation and reward that go with it (unless given on the command line)
PAIRS = {"heat": ("quadrants", "heat_stop"), "ms": ("catheter", "atp")}


# the schema: unknown keys and wrong types are rejected while composing ---------------------
@dataclass
class Network:
    inputs: list[str] = field(default_factory=lambda: ["observation"])  # env keys, concatenated
    hidden: list[int] = field(default_factory=lambda: [64, 64])
    activation: str = "relu"  # relu | tanh | elu | gelu
    normalize: bool = True  # fit (x - mean) / std on the first collected data


@dataclass
class Exploration:
    eps_init: float = 1.0
    eps_end: float = 0.05
    annealing_frames: int = 800


@dataclass
class DQNAgent:
    name: str = "dqn"
    lr: float = 1e-3
    network: Network = field(default_factory=Network)
    exploration: Exploration = field(default_factory=Exploration)


@dataclass
class Mpi:
    ranks: int = 1


@dataclass
class CollectorSection:
    frames_per_batch: int = 20
    reset_at_each_iter: bool = True  # every batch starts a fresh episode seeded by iteration


@dataclass
class BufferSection:
    size: int = 10_000
    storage: str = "tensor"  # tensor (LazyTensorStorage) | memmap (LazyMemmapStorage)
    batch_size: int = 64


@dataclass
class TargetSection:
    kind: str = "soft"  # soft (SoftUpdate, tau) | hard (HardUpdate, period)
    tau: float = 0.05
    period: int = 100


@dataclass
class LossSection:
    gamma: float = 0.99
    loss_function: str = "smooth_l1"  # l1 | l2 | smooth_l1
    double_dqn: bool = True
    n_steps: int = 1  # n-step TD targets
    target: TargetSection = field(default_factory=TargetSection)


@dataclass
class OptimSection:
    lr: float = 1e-3  # train.yaml: ${agent.lr}
    weight_decay: float = 0.0
    updates_per_batch: int = 8
    learning_starts: int = 200
    grad_clip: float = 10.0


@dataclass
class LoggerSection:
    tensorboard: bool = True
    progress: bool = True


@dataclass
class CheckpointSection:
    every: int = 25
    keep: int = 3


@dataclass
class EvalSection:
    every: int = 10
    seeds: list[int] = field(default_factory=lambda: list(range(1_000_000_000, 1_000_000_010)))
    baselines: bool = True


@dataclass
class TrainConfig:
    mpi: Mpi = field(default_factory=Mpi)
    env: dict[str, Any] = field(default_factory=dict)
    observation: dict[str, Any] = field(default_factory=dict)
    reward: dict[str, Any] = field(default_factory=dict)
    agent: Any = None
    seed: int = 0
    iterations: int = 50
    threads: int = 1
    resume: Any = None  # null | true | a run directory
    collector: CollectorSection = field(default_factory=CollectorSection)
    buffer: BufferSection = field(default_factory=BufferSection)
    loss: LossSection = field(default_factory=LossSection)
    optim: OptimSection = field(default_factory=OptimSection)
    logger: LoggerSection = field(default_factory=LoggerSection)
    checkpoint: CheckpointSection = field(default_factory=CheckpointSection)
    eval: EvalSection = field(default_factory=EvalSection)


SCHEMAS = {
    c.__name__: c
    for c in (
        Network,
        Exploration,
        DQNAgent,
        Mpi,
        CollectorSection,
        BufferSection,
        TargetSection,
        LossSection,
        OptimSection,
        LoggerSection,
        CheckpointSection,
        EvalSection,
    )
}
AGENTS = {"dqn": DQNAgent}  # agent.name -> its schema (conf/agent/NAME.yaml)


def register_schemas() -> None:
    from hydra.core.config_store import ConfigStore

    store = ConfigStore.instance()
    store.store(name="train_schema", node=TrainConfig)
    store.store(group="agent", name="dqn_schema", node=DQNAgent)


CHOICES = {
    "buffer.storage": ("tensor", "memmap"),
    "loss.loss_function": ("l1", "l2", "smooth_l1"),
    "loss.target.kind": ("soft", "hard"),
    "agent.network.activation": ("relu", "tanh", "elu", "gelu"),
}
POSITIVE = [
    "iterations",
    "threads",
    "collector.frames_per_batch",
    "buffer.size",
    "buffer.batch_size",
    "optim.lr",
    "loss.target.period",
]
NON_NEGATIVE = [
    "optim.updates_per_batch",
    "optim.learning_starts",
    "optim.weight_decay",
    "checkpoint.every",
    "eval.every",
    "optim.grad_clip",
    "seed",
]


def check_keys(cfg, schema: type, prefix: str = "") -> None:
    """Keys added with ``+key=value`` that the schema does not know; ValueError naming them.
    (Hydra lets ``+`` add keys to a structured config.) The task groups are checked by
    :func:`check_task`."""
    import dataclasses

    from omegaconf import DictConfig

    fields = {f.name: f for f in dataclasses.fields(schema)}
    for key in cfg:
        name = f"{prefix}{key}"
        if key not in fields:
            raise ValueError(f"unknown key '{name}' (not in {schema.__name__})")
        kind = fields[key].type
        value = cfg[key]
        nested = SCHEMAS.get(kind) if isinstance(kind, str) else kind
        if key == "agent" and not prefix:
            nested = AGENTS.get(str(value.get("name"))) if isinstance(value, DictConfig) else None
        if dataclasses.is_dataclass(nested) and isinstance(value, DictConfig):
            check_keys(value, nested, f"{name}.")


def check_values(cfg) -> None:
    """Range checks the schema cannot express; ValueError naming the key."""
    from omegaconf import OmegaConf

    check_keys(cfg, TrainConfig)

    def get(key):
        return OmegaConf.select(cfg, key)

    for key, options in CHOICES.items():
        if get(key) not in options:
            raise ValueError(f"{key} must be one of {', '.join(options)}, got {get(key)!r}")
    for key in POSITIVE:
        if not get(key) > 0:
            raise ValueError(f"{key} must be > 0, got {get(key)!r}")
    for key in NON_NEGATIVE:
        if not get(key) >= 0:
            raise ValueError(f"{key} must be >= 0, got {get(key)!r}")
    if not 0 < get("loss.gamma") <= 1:
        raise ValueError(f"loss.gamma must be in (0, 1], got {get('loss.gamma')!r}")
    if not 0 < get("loss.target.tau") <= 1:
        raise ValueError(f"loss.target.tau must be in (0, 1], got {get('loss.target.tau')!r}")
    for key in ("agent.exploration.eps_init", "agent.exploration.eps_end"):
        if not 0 <= get(key) <= 1:
            raise ValueError(f"{key} must be in [0, 1], got {get(key)!r}")
    if not cfg.eval.seeds:
        raise ValueError("eval.seeds must list at least one seed")
    last_train_seed = cfg.seed * 1_000_000 + cfg.iterations - 1
    clash = [s for s in cfg.eval.seeds if cfg.seed * 1_000_000 <= s <= last_train_seed]
    if clash:
        raise ValueError(f"eval.seeds {clash[:3]} are also training seeds (seed * 1e6 + iteration)")
    if cfg.resume not in (None, True, False) and not isinstance(cfg.resume, str):
        raise ValueError(f"resume must be true, false or a run directory, got {cfg.resume!r}")
    if not cfg.env.get("factory"):
        check_task(cfg)


def check_task(cfg) -> None:
    """The task groups as :func:`physicsrl.envs.make_env` will read them (nothing is built)."""
    from physicsrl.envs import OBSERVATIONS, REWARDS, TASKS
    from physicsrl.envs.config import build, plain

    plain_cfg = plain(cfg)
    for group, registry in (("observation", OBSERVATIONS), ("reward", REWARDS)):
        kind, settings = registry.lookup(plain_cfg[group])
        build(kind, settings, group)
    kind, settings = TASKS.lookup(plain_cfg["env"])
    build(kind.Config, settings, "env")


# the command line -----------------------------------------------------------------------------
def with_pairs(overrides: list[str]) -> list[str]:
    """Add the observation and reward that go with ``env=NAME`` unless they are given. Without
    ``env=`` nothing is added: the defaults list or an experiment preset chooses them."""
    chosen = {o.split("=", 1)[0].lstrip("+~"): o.split("=", 1)[1] for o in overrides if "=" in o}
    pair = PAIRS.get(chosen.get("env"))
    extra = []
    if pair is not None:
        for group, option in zip(("observation", "reward"), pair, strict=True):
            if group not in chosen:
                extra.append(f"{group}={option}")
    return [*overrides, *extra]


def one_line(error: BaseException) -> str:
    """A one-line description of a config error, naming the key."""
    chain, seen = [], error
    while seen is not None:
        chain.append(seen)
        seen = seen.__cause__ or seen.__context__
    for item in chain:
        key = getattr(item, "full_key", None)
        if key:
            message = str(item).splitlines()[0]
            if "not in" in message or "Could not append" in message or "Key '" in message:
                return f"unknown key '{key}': {message}"
            return f"bad value for '{key}': {message}"
    message = " ".join(str(chain[-1]).split()).split(" Config search path")[0]
    message = message or type(chain[-1]).__name__
    first = " ".join(str(chain[0]).split())
    return first if first and first != message and len(chain) == 1 else message


def compose(config_name: str, overrides: list[str]):
    """The job config (no Hydra section), or ValueError with a one-line message."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    register_schemas()
    job_overrides = [o for o in overrides if not o.lstrip("+~").startswith(("hydra.", "hydra/"))]
    GlobalHydra.instance().clear()
    try:
        with initialize_config_module(config_module="physicsrl.conf", version_base=None):
            return hydra_compose(config_name=config_name, overrides=job_overrides)
    except Exception as error:  # noqa: BLE001 - Hydra and OmegaConf raise many kinds
        raise ValueError(one_line(error)) from error
    finally:
        GlobalHydra.instance().clear()


def rank_from_launcher() -> int:
    for variable in ("PMI_RANK", "OMPI_COMM_WORLD_RANK", "PMIX_RANK", "SLURM_PROCID"):
        if variable in os.environ:
            return int(os.environ[variable])
    return 0


def validate_or_exit(config_name: str, overrides: list[str], check=check_values) -> None:
    """Compose and check the config on this rank; on error the leader prints one line and
    every rank exits with status 2 (all ranks see the same config, so no rank waits)."""
    try:
        cfg = compose(config_name, overrides)
        check(cfg)
    except Exception as error:  # noqa: BLE001
        message = error.args[0] if isinstance(error, ValueError) and error.args else str(error)
        if rank_from_launcher() == 0:
            print(f"error: bad config: {' '.join(str(message).split())}", file=sys.stderr)
        raise SystemExit(2) from None


def main() -> None:
    overrides = with_pairs(sys.argv[1:])
    relaunch(overrides)
    register_schemas()
    if not [o for o in overrides if o.startswith("-")]:
        validate_or_exit("train", overrides)
    run_hydra("train", train, overrides)


# the run ------------------------------------------------------------------------------------
def train(cfg) -> None:
    """Every rank: build the env; the leader trains and reports, followers serve."""
    import random

    import numpy as np
    import torch
    from mpi4py import MPI

    from physicsrl import builders
    from physicsrl.checkpoint import find_run
    from physicsrl.coordinated import Coordinator

    comm = MPI.COMM_WORLD
    leader = comm.rank == 0
    torch.set_num_threads(int(cfg.threads))
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    random.seed(cfg.seed)
    run_dir = output_dir()

    # where to continue from: decided by the leader, known to all
    resume_dir, error = None, None
    if leader and cfg.resume not in (None, False):
        try:
            resume_dir = find_run(
                str(cfg.resume),
                run_dir.parent,  # a fresh run dir has no checkpoint yet
            )
        except FileNotFoundError as problem:
            error = str(problem)
    resume_dir, error = comm.bcast((resume_dir, error), root=0)
    if error:
        if leader:
            print(f"error: {error}", file=sys.stderr)
        raise SystemExit(2)
    if not leader:  # the leader checkpoints and releases the followers on a signal
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)

    coordinator = Coordinator(comm)
    env = builders.make_env(cfg, coordinator)  # collective: every rank, same order
    stopped = None
    with coordinator:
        if leader:
            stopped = train_on_leader(cfg, env, coordinator, run_dir, resume_dir)
    if leader and stopped:
        raise SystemExit(130 if "SIGINT" in stopped else 143 if "SIGTERM" in stopped else 1)


def task_name(env) -> str | None:
    """``heat`` or ``atp`` for the envs of :mod:`physicsrl.envs`, else None."""
    task = vars(env).get("task")  # not getattr: EnvBase.__getattr__ searches further
    return getattr(task, "name", None)


def make_dojo(cfg, env, coordinator=None, log_dir: Path | None = None):
    """The Dojo of ``cfg`` for ``env`` (leader only)."""
    from physicsrl import builders
    from physicsrl.dojo import Dojo

    q_network = builders.make_q_network(env, cfg.agent.network)
    loss = builders.make_loss(q_network, env, cfg.loss)
    counts = {"heat": {"advances": 1}, "atp": {"shocks": 1}}.get(task_name(env), {})
    return Dojo(
        q_network,
        env,
        optimizer=builders.make_optimizer(loss, cfg.optim),
        loss=loss,
        target_updater=builders.make_target_updater(loss, cfg.loss.target),
        replay_buffer=builders.make_buffer(
            cfg.buffer, None if log_dir is None else log_dir / "buffer"
        ),
        exploration=builders.make_exploration(q_network, env, cfg.agent.exploration),
        frames_per_batch=cfg.collector.frames_per_batch,
        reset_at_each_iter=cfg.collector.reset_at_each_iter,
        updates_per_batch=cfg.optim.updates_per_batch,
        learning_starts=cfg.optim.learning_starts,
        grad_clip=cfg.optim.grad_clip or None,
        n_steps=cfg.loss.get("n_steps", 1),  # checkpoints of earlier versions lack it
        seed=cfg.seed,
        eval_every=cfg.eval.every,
        eval_seeds=list(cfg.eval.seeds),
        log_dir=log_dir,
        checkpoint_every=cfg.checkpoint.every,
        keep_checkpoints=cfg.checkpoint.keep,
        coordinator=coordinator,
        progress=cfg.logger.progress,
        action_counts=counts,
    )


def train_on_leader(cfg, env, coordinator, run_dir: Path, resume_dir: Path | None) -> str | None:
    """Train, print the summary, write ``summary.json``; return the stop reason, if any."""
    import time

    from omegaconf import OmegaConf

    from physicsrl.checkpoint import CheckpointManager

    log_dir = resume_dir or run_dir
    if log_dir != run_dir:  # a resumed run keeps writing its own log too
        handler = logging.FileHandler(log_dir / "train.log")
        handler.setFormatter(
            logging.Formatter("[%(asctime)s][%(name)s][%(levelname)s] - %(message)s")
        )
        logging.getLogger().addHandler(handler)
    dojo = make_dojo(cfg, env, coordinator, log_dir)
    if not cfg.logger.tensorboard:
        dojo._open_logs = lambda: None  # noqa: SLF001 - no TensorBoard files
    config = OmegaConf.to_container(cfg, resolve=True)
    dojo.checkpoint_extra = {"config": config}
    if resume_dir is not None:
        state = dojo.load_checkpoint(CheckpointManager(resume_dir / "checkpoints").latest())
        warn_differences(state.get("extra", {}).get("config", {}), config)
    log.info(
        "run directory %s; %d ranks; training to iteration %d",
        log_dir,
        coordinator.size,
        cfg.iterations,
    )
    started = time.perf_counter()
    summary = dojo.train(cfg.iterations)
    summary["wall_s"] = time.perf_counter() - started
    table = []
    if dojo.history:  # a stop request skips the baselines: it should end quickly
        table = compare_with_baselines(dojo, env, cfg, cfg.eval.baselines and not dojo.stopped)
    report = format_summary(summary, table, log_dir)
    print(report, flush=True)
    (log_dir / "summary.txt").write_text(report + "\n")
    (log_dir / "summary.json").write_text(
        json.dumps({"summary": summary, "table": table}, indent=2, default=str)
    )
    return dojo.stopped


def warn_differences(old: dict, new: dict, prefix: str = "") -> None:
    """Log the settings of a resumed run that differ from its checkpoint's."""
    ignored = {"resume", "iterations", "mpi", "logger"}
    for key in sorted(set(old) | set(new)):
        name = f"{prefix}{key}"
        if not prefix and key in ignored:
            continue
        a, b = old.get(key), new.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            warn_differences(a, b, f"{name}.")
        elif a != b:
            log.warning("resumed with %s = %r (the checkpoint's run had %r)", name, b, a)


def baselines(env, cfg) -> dict:
    """Name -> policy: the task's baseline policies (heat: stop at once, never stop, exact
    optimum; ATP: never/always shock, random, every 4th, best single shock)."""
    name = task_name(env)
    if name not in ("heat", "atp"):
        return {}
    from physicsrl.envs import baselines as b

    seeds = list(cfg.eval.seeds)
    if name == "heat":
        from physicsrl.envs import exact_optimum

        return {
            "stop at once": b.Constant(0),
            "never stop": b.Constant(1),
            "exact optimum": b.HeatOptimal(exact_optimum(env)),
        }
    best, _ = b.best_single_shock(env, seeds)
    return {
        "never shock": b.Constant(0),
        "always shock": b.Constant(1),
        "random (p=0.5)": b.RandomActions(0.5, seed=cfg.seed),
        "every 4th": b.EveryKth(4),
        f"best single shock {sorted(best.steps)}": best,
    }


def compare_with_baselines(dojo, env, cfg, with_baselines: bool = True) -> list[dict]:
    """Rows of mean metrics on the held-out seeds: the greedy policy, then the baselines."""
    rows = [
        {
            "policy": "greedy DQN",
            **{k: v for k, v in dojo.history[-1].items() if k not in ("iteration", "frames")},
        }
    ]
    for name, policy in (baselines(env, cfg) if with_baselines else {}).items():
        rows.append({"policy": name, **dojo.evaluate(policy, record=False)})
    return rows


def scores(table: list[dict]) -> list[str]:
    """The greedy return as a share of the optimum (heat): raw, and of the gap between the best
    trivial policy and the optimum."""
    by_name = {row["policy"]: row["return"] for row in table}
    if "exact optimum" not in by_name:
        return []
    greedy, optimum = by_name["greedy DQN"], by_name["exact optimum"]
    trivial = max(by_name["stop at once"], by_name["never stop"])
    lines = []
    if optimum > 0:
        lines.append(f"greedy / optimum: {100 * greedy / optimum:.1f}% of the optimal return")
    if optimum > trivial:
        share = 100 * (greedy - trivial) / (optimum - trivial)
        lines.append(
            f"(greedy - best trivial) / (optimum - best trivial): {share:.1f}% of the gap closed"
        )
    return lines


def format_summary(summary: dict, table: list[dict], log_dir: Path) -> str:
    from physicsrl.cli.bench import format_table

    times = ", ".join(f"{k} {v:.1f}s" for k, v in summary["time_s"].items())
    lines = [
        f"trained {summary['iteration']} iterations, {summary['frames']} env steps, "
        f"{summary['episodes']} episodes, {summary['updates']} updates in {summary['wall_s']:.1f}s "
        f"({summary['env_steps_per_s']:.1f} env steps/s while simulating)",
        f"time: {times}",
    ]
    if summary.get("stopped"):
        lines.append(f"stopped early: {summary['stopped']} (resume with resume={log_dir})")
    if table:
        lines.append("held-out seeds, mean per episode:")
        rounded = [
            {k: (f"{v:.3f}" if isinstance(v, float) else v) for k, v in row.items()}
            for row in table
        ]
        lines.append(format_table(rounded))
        lines.extend(scores(table))
    lines.append(f"run directory: {log_dir}")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
