"""``envs_groups.py P OUT``: the heat task (small) as N = ranks / P environments of P ranks.

On the learner: a batched rollout with automatic partial resets, the episodes of three seeds
spread over the groups (``spread_episodes``) and the specs check; then, on the learner alone
(``COMM_SELF``), the serial reference: environment i built alone and seeded with
``member_seed(seed, i)``, and each evaluation seed run alone. Writes everything to OUT (JSON)."""

import json
import sys

import torch
from mpi4py import MPI
from torchrl.envs.utils import check_env_specs

from physicsrl.coordinated import Coordinator, abort_on_error
from physicsrl.envs import load_config, make_env
from physicsrl.envs.gym import GymnasiumVectorView
from physicsrl.envs.layout import environments
from physicsrl.envs.members import member_seed, spread_episodes

SEED, STEPS, EVAL_SEEDS = 7, 14, [100, 101, 102]


def config():
    return load_config("heat", overrides=["env.mesh.cells=12", "env.max_steps=4"])


def policy(td):
    """Wait, wait, stop (by the decision index): deterministic, batched or not."""
    td["action"] = (td["step"].squeeze(-1) % 3 != 2).long()
    return td


def columns(rollout):
    return {
        "observation": rollout["next", "observation"].tolist(),
        "reward": rollout["next", "reward"].squeeze(-1).tolist(),
        "done": rollout["next", "done"].squeeze(-1).tolist(),
    }


def episode(rollout):
    return {
        "reward": rollout["next", "reward"].flatten().tolist(),
        "observation": rollout["next", "observation"].tolist(),
    }


with abort_on_error():
    ranks_per_env, out = int(sys.argv[1]), sys.argv[2]
    with environments(lambda c: make_env(config(), c), ranks_per_env, seed=SEED) as env:
        if env is not None:
            n = env.batch_size[0] if env.batch_size else 1
            with torch.no_grad():
                batched = columns(env.rollout(STEPS, policy, break_when_any_done=False))
            evaluated = (
                [episode(r) for r in spread_episodes(env, [(policy, s) for s in EVAL_SEEDS], 10)]
                if n > 1
                else []
            )
            vector_rewards = []
            vector = GymnasiumVectorView(env)
            _, info = vector.reset(seed=SEED)
            for _ in range(STEPS):
                _, reward, _, _, info = vector.step(info["step"] % 3 != 2)
                vector_rewards.append(reward.tolist())
            check_env_specs(env)
    if MPI.COMM_WORLD.rank == 0:
        coordinator = Coordinator(MPI.COMM_SELF)
        alone = make_env(config(), coordinator)
        with coordinator:
            serial = []
            for i in range(n):
                alone.set_seed(member_seed(SEED, i))
                serial.append(columns(alone.rollout(STEPS, policy, break_when_any_done=False)))
            serial_eval = []
            for seed in EVAL_SEEDS:
                alone.set_seed(seed)
                serial_eval.append(episode(alone.rollout(10, policy, break_when_any_done=True)))
        result = {
            "n": n,
            "batched": batched,
            "serial": serial,
            "evaluated": evaluated,
            "serial_eval": serial_eval,
            "vector_rewards": vector_rewards,
        }
        with open(out, "w") as f:
            json.dump(result, f)
