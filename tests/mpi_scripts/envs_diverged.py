"""The ATP env's divergence on every rank of the job: dt = 0.1 with the shock's current blows
up. Inside the step's parallel call every rank raises the same ``SimulationDiverged`` (a
``CollectiveError``): the leader's env ends the episode, the followers drop it and go on
serving. The leader prints ``RESULT <json>``: the flags and reward of that step, then of the
next episode's reset and first step."""

import json

from tensordict import TensorDict

from physicsrl.coordinated import Coordinator, abort_on_error
from physicsrl.envs import load_config, make_env
from tests.conftest import SMALL_ATP  # run_mpi puts the repository root on PYTHONPATH


def flags(td) -> dict:
    keys = ("diverged", "truncated", "terminated", "done")
    return {key: bool(td[key].item()) for key in keys if key in td.keys()}


coordinator = Coordinator()
env = make_env(load_config("ms", overrides=[*SMALL_ATP, "env.model.dt=0.1"], seed=0), coordinator)
with abort_on_error(), coordinator:
    if coordinator.is_leader():
        env.reset()
        shock = env.step(TensorDict(action=1, batch_size=[]))["next"]
        start = env.reset()
        wait = env.step(TensorDict(action=0, batch_size=[]))["next"]
        result = {
            "shock": {**flags(shock), "reward": shock["reward"].item()},
            "reset": {**flags(start), "finite": bool(start["observation"].isfinite().all())},
            "wait": flags(wait),
        }
        print("RESULT", json.dumps(result), flush=True)
