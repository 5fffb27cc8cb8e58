"""``train(cfg)``: a DQN training run of a composed :class:`~physicsrl.config.TrainConfig`.

Every rank builds the environment (its simulator is coordinated); the leader trains the
:class:`~physicsrl.dojo.Dojo`, compares the greedy policy with the task's baselines on the
held-out seeds and writes ``summary.txt``/``summary.json`` in the run directory; followers
serve the simulation. SIGINT/SIGTERM checkpoint and stop cleanly.

``resume=true`` continues the newest run beside this command's run directory, ``resume=<run
dir>`` that run, from its newest readable checkpoint; the continuation is written into the
resumed run (checkpoints, events, evaluations, log, summary), and this command's own run
directory keeps only its config, its log and ``resumed.txt`` naming the run it continued. In a
sweep (``-m``), ``resume=true`` continues each job's own run directory (give the earlier
sweep's ``hydra.sweep.dir``), and ``resume=<run dir>`` is refused (every job would continue
that one run). A
checkpoint directory that cannot be written, or a resume without a readable checkpoint, is one
line (exit status 2) before any environment is built.
"""

from __future__ import annotations

import random
import signal

import numpy as np
from mpi4py import MPI

from physicsrl.config import TrainConfig, typed
from physicsrl.envs.factory import builds_env, make_env_for_rank
from physicsrl.envs.layout import environments
from physicsrl.launch import output_dir, refuse


def train(cfg) -> None:
    """Every rank: build the env; the leader trains and reports (:mod:`physicsrl.learner`),
    the other ranks serve. Only the ranks that hold a TorchRL env (world rank 0 and the
    other group leaders) import torch: a rank that serves only its group leader's simulator
    calls builds the task alone (:func:`~physicsrl.envs.factory.make_env_for_rank`)."""
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

    # where to continue from, and whether checkpoints can be written: the leader decides
    resume, error = None, None
    if leader:
        from physicsrl import learner  # torch and TorchRL: the learner's rank only

        try:
            resume = learner.resume_point(config, run_dir)
        except (OSError, ValueError) as problem:
            error = str(problem)
    resume, error = comm.bcast((resume, error), root=0)
    if error:
        refuse(error)
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
