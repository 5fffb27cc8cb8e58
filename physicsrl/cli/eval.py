"""``physicsrl-eval run=<run dir or checkpoint> [key=value ...] [mpi.ranks=N]``: evaluate a
trained greedy policy beside the baselines on held-out seeds.

Rebuilds the env and the Q-network from the config stored in the checkpoint (every rank builds
its part of the env, as in training; the leader evaluates), prints a table (return, success,
shocks, episode length; one episode per seed), writes ``eval.csv`` (per seed) and
``eval_summary.csv`` (means) and, for the physics tasks, ``episode.gif``: the field after the
reset and after each decision, catheter electrodes, shocks marked (by default of the first seed
whose greedy episode succeeds); with ``fields=true`` the fields of that episode as a VTX series
for ParaView (``fields.bp``) and a PNG of u drawn from the series read back (``fields.png``).
Files go to this command's run directory.
"""

from __future__ import annotations

from pathlib import Path

from physicsrl.cli import command
from physicsrl.launch import output_dir


def check(cfg, job) -> None:
    import importlib.util

    from physicsrl.launch import check_layout
    from physicsrl.run_directory import checkpoint_path

    check_layout(cfg.mpi.ranks_per_env, job.ranks)
    checkpoint_path(str(cfg.run))  # a checkpoint file, or a run directory with one
    if cfg.fields and importlib.util.find_spec("adios2") is None:
        raise ValueError("fields=true reads the series back with adios2: pip install adios2")
    run_config({}, list(cfg.overrides))  # the keys and types; the task groups come with the run
    for override in cfg.overrides:
        if override.lstrip("+~").startswith("agent.network"):
            raise ValueError(f"overrides: {override}: the stored weights fit the run's network")


def run_config(stored: dict, overrides: list[str]):
    """The training config of the evaluated run: ``stored`` (its checkpoint's) changed by
    ``overrides``, typed; ValueError naming the key."""
    from omegaconf import OmegaConf

    from physicsrl.cli.command import one_line
    from physicsrl.config import TrainConfig, parse_overrides, typed

    changes = parse_overrides(overrides)
    try:
        merged = OmegaConf.merge(OmegaConf.structured(TrainConfig), stored, changes)
        typed(merged)
    except Exception as error:  # noqa: BLE001 - OmegaConf's errors name the key
        raise ValueError(f"overrides: {one_line(error)}") from error
    return merged


def main() -> None:
    command.main("eval", "physicsrl.cli.eval:evaluate", check)


def evaluate(cfg) -> None:
    """Every rank: rebuild the run's env from its stored config; the leader evaluates. As in
    training, a rank that only serves its group leader's simulator builds the task alone
    (:func:`~physicsrl.envs.factory.make_env_for_rank`) and imports no torch."""
    from mpi4py import MPI
    from omegaconf import OmegaConf

    from physicsrl.cli.command import refuse_config
    from physicsrl.cli.train import check_run
    from physicsrl.config import typed
    from physicsrl.envs.factory import make_env_for_rank
    from physicsrl.envs.layout import environments
    from physicsrl.launch import check_backend
    from physicsrl.run_directory import checkpoint_path

    comm = MPI.COMM_WORLD
    leader = comm.rank == 0
    path = checkpoint_path(str(cfg.run))
    state = None
    if leader:
        from physicsrl.checkpoint import read  # TorchRL

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
    eval_cfg = typed(cfg)
    recorders = []

    def make_env(coordinator):
        env = make_env_for_rank(train_cfg, coordinator)
        if eval_cfg.fields:
            recorders.append(field_recorder(env, coordinator, output_dir() / "fields.bp"))
        return env

    with environments(make_env, eval_cfg.mpi.ranks_per_env) as env:
        if env is not None:  # the seeds are spread over the job's environments
            recorder = recorders[0] if recorders else None
            evaluate_on_leader(eval_cfg, typed(train_cfg), env, state, path, recorder)


def field_recorder(env, coordinator, path: Path):
    """A :class:`~physicsrl.fem.FieldRecorder` of the simulator's u (and w, for a model with a
    gate variable) into ``path``, built on every rank of the environment that world rank 0
    plays (collective there); None on the other environments' ranks."""
    from mpi4py import MPI

    from physicsrl.cli.command import refuse_config
    from physicsrl.envs.task import Task
    from physicsrl.fem import FieldRecorder

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


def evaluate_on_leader(cfg, train_cfg, env, state: dict, path: Path, recorder=None) -> None:
    from physicsrl import learning_curve
    from physicsrl.cli.command import refuse_config
    from physicsrl.config import held_out_seeds, is_held_out, training_seeds_among
    from physicsrl.envs.env import PhysicsEnv
    from physicsrl.envs.groups import GroupedEnv
    from physicsrl.envs.task import ResetDiverged
    from physicsrl.evaluation import compare
    from physicsrl.fem.output import render_series
    from physicsrl.learner import baselines, make_dojo
    from physicsrl.render import episode_gif, record_fields
    from physicsrl.tables import format_table, rounded, write_csv

    dojo = make_dojo(train_cfg, env)
    try:
        dojo.q_network.load_state_dict(state["q_network"])
    except RuntimeError as error:  # overrides that change the observation's size
        shapes = " ".join(str(error).split()).split("size mismatch for ")[-1]
        refuse_config(f"overrides: the stored weights do not fit this env's network ({shapes})")
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


if __name__ == "__main__":
    main()
