"""The learner's side of ``physicsrl-train`` and ``physicsrl-eval`` (world rank 0; torch and
TorchRL): where a run continues from (:func:`resume_point`), the
:class:`~physicsrl.dojo.Dojo` of a config (:func:`make_dojo`), the training and its summary
(:func:`train_on_leader`), the task's baselines, and the evaluation of a stored run
(:func:`evaluate_on_leader`). The jobs of :mod:`physicsrl.jobs` run it on every rank's behalf.
"""

from __future__ import annotations

import json
import logging
import sys
import time
from pathlib import Path
from typing import NoReturn

from mpi4py import MPI
from torchrl.checkpoint import Checkpoint, CheckpointError

from physicsrl import builders, learning_curve
from physicsrl.checkpoint import Checkpoints, read
from physicsrl.cli.command import refuse_config
from physicsrl.config import (
    EvalConfig,
    TrainConfig,
    as_dict,
    check_sweep_resume,
    held_out_seeds,
    is_held_out,
    training_seeds_among,
)
from physicsrl.dojo import Dojo, NonFiniteTraining
from physicsrl.envs.env import PhysicsEnv
from physicsrl.envs.factory import parts
from physicsrl.envs.groups import GroupedEnv
from physicsrl.envs.members import Members
from physicsrl.envs.task import ResetDiverged, Task
from physicsrl.evaluation import compare
from physicsrl.fem import FieldRecorder
from physicsrl.fem.output import render_series
from physicsrl.launch import output_dir, refuse, sweeping
from physicsrl.run_directory import RESUMED, find_run
from physicsrl.tables import format_table, provenance, rounded, write_csv

log = logging.getLogger("physicsrl.train")


def resume_point(config: TrainConfig, run_dir: Path) -> Path | None:
    """The checkpoint to continue from (None: a new run) and whether checkpoints can be
    written (the leader's checks before any environment is built); OSError or ValueError in
    one line. In a sweep each job resumes its own run directory (ValueError for one run
    directory named for every job). A resume of another task or Q-network, of a stored policy,
    or with another number of environments (groups x replicas) is refused here too."""
    resume = None
    if config.resume not in (None, False):
        request = str(config.resume)
        if sweeping():
            check_sweep_resume(request)
            request = str(run_dir)
        resume_dir = find_run(request, run_dir.parent)
        resume = Checkpoints(resume_dir / "checkpoints", 1).newest_readable()
        if "replay_buffer" not in Checkpoint.manifest(resume)["components"]:
            raise ValueError(
                f"resume: {resume} holds a policy, not a training run's state (no replay "
                f"buffer, optimizer, ...): physicsrl-eval run={resume} evaluates it"
            )
        extra, settings = read(resume, ["extra"])["extra"], as_dict(config)
        check_same_task(extra.get("config", {}), settings)
        if not config.env.get("factory"):  # its env's batch is known once it is built
            *_, task_config = parts(settings)
            replicas = getattr(task_config, "replicas", 1)
            groups = MPI.COMM_WORLD.size // config.mpi.ranks_per_env
            check_environments(extra.get("environments", 1), groups * replicas)
    log_dir = run_dir if resume is None else resume.parent.parent
    Checkpoints(log_dir / "checkpoints", config.checkpoint.keep).check_writable()
    return resume


def task_of(env) -> Task | type[Task] | None:
    """The :class:`~physicsrl.envs.task.Task` behind ``env`` (group 0's for many environments,
    the task's class for replicas), if it has one: its hooks name the baselines, action counts
    and score lines."""
    # not getattr: EnvBase.__getattr__ searches further
    task = env.task if isinstance(env, Members) else vars(env).get("task")
    is_class = isinstance(task, type) and issubclass(task, Task)
    return task if is_class or isinstance(task, Task) else None


def make_dojo(config: TrainConfig, env, coordinator=None, log_dir: Path | None = None) -> Dojo:
    """The Dojo of ``config`` for ``env`` (leader only)."""
    task, environments = task_of(env), n_environments(env)
    return Dojo(
        builders.make_q_network(env, config.agent.network),
        env,
        config,
        log_dir=log_dir,
        checkpoint_extra={"environments": environments},
        coordinator=coordinator,
        action_counts=task.action_counts if task else {},
        environments=environments,
        cores=MPI.COMM_WORLD.size,
    )


def baselines(env, config: TrainConfig, seeds) -> dict:
    """Display name -> policy: the task's baseline policies (none for envs without a task)."""
    task = task_of(env)
    return task.baselines(env, list(seeds), config.seed) if task else {}


def train_on_leader(config: TrainConfig, env, run_dir: Path, resume: Path | None) -> str | None:
    """Train (continuing from the checkpoint ``resume``, in its run directory), print the
    summary, write ``summary.json``; return the stop reason, if any."""
    task = task_of(env)
    coordinator = task.coordinator if isinstance(task, Task) else None  # its time is logged
    ranks, per_env = MPI.COMM_WORLD.size, config.mpi.ranks_per_env
    log_dir = run_dir if resume is None else resume.parent.parent
    groups, n = ranks // per_env, n_environments(env)
    plural = lambda count: "s" if count > 1 else ""  # noqa: E731
    layout = f"{groups} environment{plural(groups)} of {per_env} rank{plural(per_env)}"
    if n != groups:  # replicas: a group is a batch of them
        layout = f"{n} environments ({groups} group{plural(groups)} of {n // groups} replicas)"
    log.info(
        "%s (%d rank%s); run directory %s; training to iteration %d; %s",
        layout,
        ranks,
        plural(ranks),
        log_dir,
        config.iterations,
        provenance(),
    )
    if log_dir != run_dir:  # the resumed run keeps its own log; this command's says where
        handler = logging.FileHandler(log_dir / "train.log")
        handler.setFormatter(
            logging.Formatter("[%(asctime)s][%(name)s][%(levelname)s] - %(message)s")
        )
        logging.getLogger().addHandler(handler)
    dojo = make_dojo(config, env, coordinator, log_dir)
    if resume is not None:
        try:
            extra = dojo.load_checkpoint(resume)
        except CheckpointError as error:
            if "size mismatch" not in str(error):
                raise
            refuse_misfit(error, f"resume={config.resume}")  # the observation's size changed
        try:  # an env.factory's env, whose batch resume_point could not know
            check_environments(extra.get("environments", 1), n)
        except ValueError as error:
            refuse(str(error))
        warn_differences(extra.get("config", {}), dojo.checkpoint_extra["config"])
    if log_dir != run_dir:
        (run_dir / RESUMED).write_text(
            f"this command resumed {log_dir} from {resume.name}: its checkpoints, events, "
            f"evaluations and summary are written there\n"
        )
    started = time.perf_counter()
    try:
        summary = dojo.train(config.iterations)
    except (NonFiniteTraining, ResetDiverged) as error:
        print(f"error: {error}", file=sys.stderr, flush=True)
        raise SystemExit(1) from None
    summary["wall_s"] = time.perf_counter() - started  # this command's (total_s: the run's)
    summary["resumed_from"] = None if resume is None else str(resume)
    summary["ranks"], summary["environments"] = ranks, n  # for core-hours
    table, stopped = [], dojo.stopped
    if dojo.history:  # a stop request skips the baselines: it should end quickly
        counters = ("iteration", "frames", "wall_s")
        greedy = {k: v for k, v in dojo.history[-1].items() if k not in counters}
        table = [{"policy": "greedy DQN", **greedy}]
        if config.eval.baselines and not stopped:
            try:
                policies = baselines(env, config, config.eval.seeds)
                table += compare(env, policies, config.eval.seeds, dojo.action_counts)[1]
            except KeyboardInterrupt:  # Ctrl-C after training: the summary, without them
                stopped = summary["baselines"] = "received SIGINT"
    report = format_summary(summary, table, log_dir, task)
    print(report, flush=True)
    (log_dir / "summary.txt").write_text(report + "\n")
    (log_dir / "summary.json").write_text(
        json.dumps({"summary": summary, "table": table}, indent=2, default=str)
    )
    return stopped


def n_environments(env) -> int:
    """N: the environments behind ``env`` (a batch's members, else 1)."""
    return env.batch_size[0] if isinstance(env, Members) else 1


def check_environments(before: int, n: int) -> None:
    """ValueError unless a job of ``n`` environments may resume a run of ``before``: the exact
    resume needs each environment's generator state."""
    if before != n:
        raise ValueError(
            f"the checkpoint's run had {before} environment(s), this job has {n} "
            "(mpi.ranks / mpi.ranks_per_env, times env.replicas): resume with the same number"
        )


TASK_KEYS = (
    *("env.name", "env.module", "env.factory", "observation.name", "reward.name"),
    *("agent.network.inputs", "agent.network.hidden", "agent.network.normalize"),
)
"""What a resumed run may not change: its buffer is the task's, its weights the network's."""


def check_same_task(old: dict, new: dict) -> None:
    """ValueError naming the first of :data:`TASK_KEYS` in which the config ``new`` of a resume
    differs from its checkpoint's ``old`` (other settings may change: a warning each)."""
    for key in TASK_KEYS:
        *sections, name = key.split(".")
        before, after = old, new
        for section in sections:
            before, after = before.get(section, {}), after.get(section, {})
        if before.get(name) != after.get(name):
            raise ValueError(
                f"resume: {key}={after.get(name)} where the checkpoint's run has "
                f"{before.get(name)}: a resume goes on with the run's task and Q-network (give "
                "its +experiment, or its env, observation, reward and agent.network)"
            )


def refuse_misfit(error: Exception, setting: str) -> NoReturn:
    """One line (status 2) for stored weights that do not fit this env's network (the size
    mismatches that ``error`` lists), which ``setting`` changed."""
    shapes = " ".join(str(error).split()).split("size mismatch for ")[-1]
    refuse_config(f"{setting}: the stored weights do not fit this env's network ({shapes})")


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


def format_summary(summary: dict, table: list[dict], log_dir: Path, task: Task | None) -> str:
    times = ", ".join(f"{k} {v:.1f}s" for k, v in summary["time_s"].items())
    took = f"{summary['total_s']:.1f}s"  # the run's, resumes included, as the times below
    if summary["resumed_from"]:
        took += f" ({summary['wall_s']:.1f}s of them since resuming)"
    lines = [
        f"trained {summary['iteration']} iterations, {summary['frames']} env steps, "
        f"{summary['episodes']} episodes, {summary['updates']} updates in {took} "
        f"({summary['env_steps_per_s']:.1f} env steps/s while simulating)",
        f"time: {times}",
    ]
    if summary.get("simulated"):
        phases = ", ".join(
            f"{phase} {seconds:.1f}s ({steps / max(seconds, 1e-9):,.0f} replica-steps/s, "
            f"mean batch {steps / max(batch_steps, 1):.1f})"
            for phase, (seconds, steps, batch_steps) in summary["simulated"].items()
        )
        lines.append(f"simulation by phase: {phases}")
    if summary.get("stopped"):
        lines.append(f"stopped early: {summary['stopped']} (resume with resume={log_dir})")
    if table:
        evaluated = summary["eval"]["iteration"]
        lines.append(
            f"held-out seeds, mean per episode (the greedy policy of iteration {evaluated}):"
        )
        lines.append(format_table(rounded(table)))
        if summary.get("baselines"):
            lines.append(f"baselines not run: {summary['baselines']} after training had ended")
        if task is not None:
            lines.extend(task.scores({row["policy"]: row["return"] for row in table}))
    lines.append(f"run directory: {log_dir}")
    return "\n".join(lines)


def evaluate_on_leader(
    cfg: EvalConfig,
    train_cfg: TrainConfig,
    env,
    state: dict,
    path: Path,
    recorder: FieldRecorder | None = None,
) -> None:
    """Evaluate the greedy policy of the checkpoint ``path`` (its ``state``: ``q_network``,
    ``counters``, ``extra``) beside the task's baselines on ``cfg``'s seeds; print the table and
    write ``eval.csv``, ``eval_summary.csv``, the learning curve, the episode GIF and, with a
    ``recorder``, the episode's fields into the command's run directory."""
    from physicsrl.render import episode_gif, record_fields  # matplotlib, imageio: 0.4 s

    dojo = make_dojo(train_cfg, env)
    try:
        dojo.q_network.load_state_dict(state["q_network"])
    except RuntimeError as error:  # overrides that change the observation's size
        refuse_misfit(error, "overrides")
    seeds = cfg.seeds if cfg.seeds is not None else train_cfg.eval.seeds
    seeds = held_out_seeds(seeds) if isinstance(seeds, int) else [int(s) for s in seeds]
    policies = {"greedy DQN": dojo.q_network}
    try:  # the first reset (a baseline's search runs episodes too) finds the overrides' numerics
        if cfg.baselines:
            policies.update(baselines(env, train_cfg, seeds))
        per_seed, means = compare(env, policies, seeds, dojo.action_counts)
    except ResetDiverged as error:
        refuse_config(f"overrides: {error}")
    directory = output_dir()
    write_csv(directory / "eval.csv", per_seed)
    write_csv(directory / "eval_summary.csv", means)
    iterations = state["counters"]["iteration"]
    trained = training_seeds_among(train_cfg.seed, iterations, seeds)
    if trained:
        print(f"warning: seeds {trained[:3]} seeded this run's training batches (seed * 1e6 + i)")
    kind = "held-out seeds" if all(map(is_held_out, seeds)) and not trained else "seeds"
    print(
        f"checkpoint {path} (iteration {iterations}, {state['counters']['frames']} env steps); "
        f"{len(seeds)} {kind}, mean per episode:"
    )
    print(format_table(rounded(means)))
    print(f"results: {directory / 'eval_summary.csv'} (per seed: eval.csv)")
    if cfg.curve:
        run_dir = path.parent.parent
        environments = state["extra"].get("environments", 1)
        ranks = learning_curve.job_ranks(run_dir) or environments * train_cfg.mpi.ranks_per_env
        # the bars only where they were measured as the curve was: its seeds, its settings
        alike = seeds == list(state["extra"]["config"]["eval"]["seeds"]) and not cfg.overrides
        bars = means if alike else ()
        png = directory / "learning_curve.png"  # to the evaluated checkpoint's iteration
        curve = learning_curve.plot(run_dir, png, bars, ranks, until=iterations)
        if curve is not None:
            unlike = "" if alike else " (no baselines: these seeds or settings are not the run's)"
            print(f"learning curve: {curve}{unlike}")
    succeeded = [r["seed"] for r in per_seed if r["policy"] == "greedy DQN" and r.get("success")]
    seed = int(cfg.gif_seed if cfg.gif_seed is not None else (succeeded or seeds)[0])
    single = env.local_env if isinstance(env, GroupedEnv) else env
    if recorder is not None:
        series = record_fields(single, dojo.q_network, seed, recorder)
        render_series(series, "u", len(series.times) - 1, directory / "fields.png")
        print(
            f"fields of seed {seed} ({', '.join(series.values)} at {len(series.times)} times): "
            f"{recorder.path} (ParaView), last u: {directory / 'fields.png'}"
        )
    if cfg.gif and not isinstance(single, PhysicsEnv):
        print("no episode GIF: it needs a physics task's env on the PETSc backend")
    elif cfg.gif:
        gif = episode_gif(single, dojo.q_network, seed, directory / "episode.gif", fps=cfg.fps)
        print(
            f"episode of seed {seed}: actions {gif['actions']}, return {sum(gif['rewards']):.3f}: "
            f"{directory / 'episode.gif'}"
        )
