"""Run both tasks (small configs; the ATP task also observing w) with fixed seeds and a seeded
random policy on all ranks of the job, then again on the leader alone (``COMM_SELF``: the
serial reference, in the same job to save a launch). The leader prints ``RESULT <json>`` with
both runs' observations, actions, rewards and flags; the test compares them."""

import json

from mpi4py import MPI

from physicsrl.coordinated import Coordinator, abort_on_error
from physicsrl.envs import load_config, make_env
from physicsrl.envs.baselines import RandomActions
from tests.conftest import SMALL_ATP  # run_mpi puts the repository root on PYTHONPATH

HEAT = ["env.mesh.cells=16", "env.max_steps=4"]
ATP = [*SMALL_ATP, "observation.normalise=true"]


def episodes(env, seeds):
    result = []
    for seed in seeds:
        env.set_seed(seed)
        rollout = env.rollout(
            env.task.max_steps + 1, RandomActions(0.5, seed), break_when_any_done=True
        )
        result.append(
            {
                "observation": rollout["observation"].tolist(),
                "action": rollout["action"].tolist(),
                "reward": rollout["next", "reward"].flatten().tolist(),
                "done": rollout["next", "done"].flatten().tolist(),
                "final": rollout["next", "observation"][-1].tolist(),
            }
        )
    return result


def run(comm):
    coordinator = Coordinator(comm)
    heat = make_env(load_config("heat", overrides=HEAT), coordinator)
    atp = make_env(load_config("ms", overrides=ATP), coordinator)
    gate = make_env(load_config("ms", overrides=[*ATP, "observation.variable=w"]), coordinator)
    with coordinator:
        if coordinator.is_leader():
            return {
                "heat": episodes(heat, [0, 1, 2]),
                "atp": episodes(atp, [0, 1]),
                "atp_w": episodes(gate, [0]),
            }


with abort_on_error():
    parallel = run(MPI.COMM_WORLD)
    if MPI.COMM_WORLD.rank == 0:
        serial = run(MPI.COMM_SELF)
        print(
            "RESULT",
            json.dumps({"ranks": MPI.COMM_WORLD.size, "parallel": parallel, "serial": serial}),
        )
