"""``envs_groups_fault.py MODE P``: faults in a job of N = ranks / P heat environments.

MODE ``remote``: the last environment gets an invalid action (its task raises on its group);
``learner``: the learner raises after one step; ``exit``: the learner calls sys.exit(3)."""

import sys

import torch

from physicsrl.coordinated import abort_on_error
from physicsrl.envs import load_config, make_env
from physicsrl.envs.layout import environments

mode, ranks_per_env = sys.argv[1], int(sys.argv[2])
cfg = load_config("heat", overrides=["env.mesh.cells=8"])
with abort_on_error():
    with environments(lambda c: make_env(cfg, c), ranks_per_env, seed=0) as env:
        if env is not None:
            td = env.reset()
            td["action"] = torch.ones(env.batch_size, dtype=torch.int64)
            if mode == "remote":
                td["action"][-1] = 5
            env.step(td)
            if mode == "learner":
                raise RuntimeError("the learner failed")
            if mode == "exit":
                sys.exit(3)
