"""The commands' jobs, run on every rank after the command line is checked: ``train(cfg)``
(``physicsrl-train``) and ``evaluate(cfg)`` (``physicsrl-eval``).

Every rank builds the environment of its group (its simulator is coordinated); world rank 0,
the learner, does the job's torch side (:mod:`physicsrl.learner`) while the other ranks serve
the simulation. A rank that only serves its group leader's simulator calls builds the task
alone (:func:`~physicsrl.envs.factory.make_env_for_rank`) and imports no torch: only the
learner's side imports it.

``train``: the leader trains the :class:`~physicsrl.dojo.Dojo`, compares the greedy policy with
the task's baselines on the held-out seeds and writes ``summary.txt``/``summary.json`` in the
run directory. SIGINT/SIGTERM checkpoint and stop cleanly. ``resume=true`` continues the newest
run beside this command's run directory, ``resume=<run dir>`` that run, from its newest
readable checkpoint; the continuation is written into the resumed run (checkpoints, events,
evaluations, log, summary), and this command's own run directory keeps only its config, its log
and ``resumed.txt`` naming the run it continued. In a sweep (``-m``), ``resume=true`` continues
each job's own run directory (give the earlier sweep's ``hydra.sweep.dir``), and ``resume=<run
dir>`` is refused (every job would continue that one run). A checkpoint directory that cannot
be written, or a resume without a readable checkpoint, is one line (exit status 2) before any
environment is built.
"""

from __future__ import annotations

import random
import signal

import numpy as np
from mpi4py import MPI
from omegaconf import OmegaConf

from physicsrl.cli.command import refuse_config
from physicsrl.cli.eval import run_config
from physicsrl.cli.train import check_run
from physicsrl.config import EvalConfig, TrainConfig, typed
from physicsrl.envs.factory import builds_env, make_env_for_rank
from physicsrl.envs.layout import environments
from physicsrl.envs.task import Task
from physicsrl.fem import FieldRecorder
from physicsrl.launch import check_backend, output_dir
from physicsrl.run_directory import agree, checkpoint_path


def train(cfg) -> None:
    """Every rank: build the env; the leader trains and reports
    (:func:`~physicsrl.learner.train_on_leader`), the other ranks serve."""
    config: TrainConfig = typed(cfg)
    comm = MPI.COMM_WORLD
    leader = comm.rank == 0
    if builds_env(cfg, leader=comm.rank % config.mpi.ranks_per_env == 0):  # leads its group
        import torch  # this rank holds an env

        torch.set_num_threads(config.threads)
        torch.manual_seed(config.seed)
    np.random.seed(config.seed)
    random.seed(config.seed)
    run_dir = output_dir()

    if leader:
        from physicsrl import learner  # torch and TorchRL: the learner's rank only
    # where to continue from, and whether checkpoints can be written: the leader decides
    resume = agree(lambda: learner.resume_point(config, run_dir), (OSError, ValueError))
    if not leader:  # the leader checkpoints and releases the followers on a signal
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)

    stopped = None
    make_env = lambda coordinator: make_env_for_rank(cfg, coordinator)  # noqa: E731
    with environments(make_env, config.mpi.ranks_per_env, seed=config.seed) as env:
        if env is not None:  # world rank 0: the learner
            stopped = learner.train_on_leader(config, env, run_dir, resume)
    if leader and stopped:
        raise SystemExit(130 if "SIGINT" in stopped else 143 if "SIGTERM" in stopped else 1)


def evaluate(cfg) -> None:
    """Every rank: rebuild the run's env from its stored config, checked as ``physicsrl-train``
    checks its own; the leader evaluates (:func:`~physicsrl.learner.evaluate_on_leader`)."""
    comm = MPI.COMM_WORLD
    leader = comm.rank == 0
    path = checkpoint_path(str(cfg.run))
    state = None
    if leader:
        from physicsrl import learner  # torch and TorchRL: the learner's rank only
        from physicsrl.checkpoint import read

        state = read(path, ["q_network", "counters", "extra"])
    config = comm.bcast(state["extra"].get("config", {}) if leader else None, root=0)
    if not {"name", "factory"} & set(config.get("env", {})):
        refuse_config(
            f"run={cfg.run}: its config names no task (env.name) to rebuild the env from; a Dojo "
            "built in Python records one when its config holds the task's groups: "
            'Dojo(q_network, env, {**load_config("heat", seed=0), ...})'
        )
    try:  # as physicsrl-train checks its config, before anything is built
        train_cfg = run_config(config, list(cfg.overrides))
        model = OmegaConf.select(train_cfg, "env.model") or {}
        check_backend(model.get("backend"), cfg.mpi.ranks_per_env, model.get("device"))
        check_run(train_cfg)
    except ValueError as error:
        refuse_config(error)
    eval_cfg: EvalConfig = typed(cfg)
    recorders = []

    def make_env(coordinator):
        env = make_env_for_rank(train_cfg, coordinator)
        if eval_cfg.fields:
            recorders.append(field_recorder(env, coordinator, output_dir() / "fields.bp"))
        return env

    with environments(make_env, eval_cfg.mpi.ranks_per_env) as env:
        if env is not None:  # world rank 0; the seeds are spread over the job's environments
            recorder = recorders[0] if recorders else None
            learner.evaluate_on_leader(eval_cfg, typed(train_cfg), env, state, path, recorder)


def field_recorder(env, coordinator, path):
    """A :class:`~physicsrl.fem.FieldRecorder` of the simulator's u (and w, for a model with a
    gate variable) into ``path``, built on every rank of the environment that world rank 0
    plays (collective there); None on the other environments' ranks."""
    task = env if isinstance(env, Task) else vars(env).get("task")  # a follower's: the task
    simulator = getattr(task, "simulator", None)
    if simulator is None:
        refuse_config(
            "fields=true needs a physics task's env on the PETSc backend (env.factory's envs "
            "and env.model.backend=torch have no fields)"
        )
    if not coordinator.comm.bcast(MPI.COMM_WORLD.rank == 0, root=0):
        return None
    functions = [simulator.u_n(), *([simulator.w_n()] if hasattr(simulator, "w_n") else [])]
    return FieldRecorder(coordinator, path, functions)
