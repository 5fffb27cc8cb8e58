"""``physicsrl-train [key=value ...] [mpi.ranks=N]``: DQN training (the Dojo) under Hydra + MPI.

Composes ``conf/train.yaml`` into the typed :class:`~physicsrl.config.TrainConfig`: the task
groups ``env``, ``observation``, ``reward`` (``env=NAME`` picks the observation and reward of
its YAML's defaults list unless given), the ``agent`` group (network and exploration) and
sections named after the TorchRL objects they configure (``collector``, ``buffer``, ``loss``,
``optim``, ``logger``, ``checkpoint``, ``eval``). The config is checked on every rank before
anything is simulated: an unknown key, a wrong type or a bad value exits with status 2 and one
line naming the key.
Then every rank runs :func:`physicsrl.jobs.train`.
"""

from __future__ import annotations

from omegaconf import OmegaConf

from physicsrl.checks import plain
from physicsrl.cli import command
from physicsrl.config import check_memory, typed
from physicsrl.launch import check_backend, check_layout


def check_task(cfg, job) -> None:
    """The layout of environments over the ranks of the job (a :class:`~physicsrl.launch.Job`)
    and the backend's (a group's replicas run on one rank, a CUDA device is there, if the job
    runs here), then :func:`check_run`."""
    check_layout(cfg.mpi.ranks_per_env, job.ranks)
    model = OmegaConf.select(cfg, "env.model") or {}
    device = model.get("device") if job.here else None
    check_backend(model.get("backend"), cfg.mpi.ranks_per_env, device)
    check_run(cfg)


def check_run(cfg) -> None:
    """The task groups as :func:`physicsrl.envs.make_env` will read them, the reward's events
    among the task's, the observation inside the task's domain, the network's inputs among the
    env's keys, and the memory of the network, the replay buffer and the simulator on a square
    mesh, per rank (:func:`~physicsrl.config.check_memory`); nothing is built.
    An env from ``env.factory`` checks its own settings (its keys and sizes are not known
    before it is built: each network input counts as one number)."""
    config = typed(cfg)
    if cfg.env.get("factory"):
        check_memory(config, {}, n_actions=2)
        return
    from physicsrl.envs.factory import parts, simulator_needs  # MPI: after the re-launch
    from physicsrl.envs.task import SquareMesh

    observation, reward, task, task_config = parts(plain(cfg))
    if reward.events - task.events:
        raise ValueError(
            f"reward={reward.name} does not fit the {task.name} task: it reads the events "
            f"{sorted(reward.events - task.events)}, which the task does not report"
        )
    mesh = getattr(task_config, "mesh", None)
    if isinstance(mesh, SquareMesh) and observation.outside(mesh.extent):
        far = max(max(abs(x), abs(y)) for x, y in observation.outside(mesh.extent))
        raise ValueError(
            f"observation={observation.name} does not fit the {task.name} task: it reads at "
            f"points up to {far:g} from the origin, outside the domain "
            f"[-{mesh.extent:g}, {mesh.extent:g}]^2 (env.mesh.extent)"
        )
    inputs = env_inputs(task, observation)
    unknown = [key for key in config.agent.network.inputs if key not in inputs]
    if unknown:
        raise ValueError(
            f"agent.network.inputs: {unknown[0]!r} is not an observation key of the "
            f"{task.name} task (its keys: {', '.join(inputs)})"
        )
    ranks = config.mpi.ranks_per_env
    simulator = simulator_needs(task_config, ranks, f"mpi.ranks_per_env={ranks}")
    check_memory(config, inputs, task.n_actions, simulator)


def env_inputs(task, observation) -> dict[str, tuple[int, int]]:
    """The observation keys of :class:`~physicsrl.envs.env.PhysicsEnv` for ``task``, each
    (numbers per step, bytes each), as its ``observation_spec`` will hold them."""
    flags = {name: (1, 1) for name in ("diverged", *task.flags)}  # bool
    return {"observation": (observation.size, 4), "step": (1, 8), **flags}


def train_config(overrides: list[str]):
    """The config that ``physicsrl-train <overrides>`` runs, checked as it checks it (one line
    and status 2 on every rank otherwise): for scripts that build its env."""
    command.validate_or_exit("train", overrides, check_task)
    return command.compose("train", overrides)


def main() -> None:
    command.main("train", "physicsrl.jobs:train", check_task)


if __name__ == "__main__":
    main()
