"""A bad action given to the Gymnasium view on the leader: a ValueError there, before any
rank steps, and the environment goes on (the test runs this serially and on 2 ranks)."""

import physicsrl.fem  # noqa: F401  (first: loads the MPI library that dolfinx links to)

# isort: split

from physicsrl.coordinated import Coordinator
from physicsrl.envs import load_config, make_env
from physicsrl.envs.gym import GymnasiumView

coordinator = Coordinator()
env = make_env(load_config("heat", overrides=["env.mesh.cells=8"]), coordinator)
view = GymnasiumView(env)
with coordinator:
    if coordinator.is_leader():
        view.reset(seed=3)
        for action in (2, -1, 1.7, 0.5, True):
            try:
                view.step(action)
                raise AssertionError(f"action {action!r} was taken")
            except ValueError as error:
                print("refused:", error)
        _, _, _, _, info = view.step(1)
        print("then step", info["step"])
