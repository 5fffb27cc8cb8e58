"""Train Stable-Baselines3 DQN on the heat task through the Gymnasium adapter.

    python examples/sb3_heat.py --steps 20000           # one rank
    mpiexec -n 2 python examples/sb3_heat.py            # the simulation on two ranks

Prints the trained policy's mean return over every level beside the exact optimum and the two
trivial baselines. Short by default (a smoke run); ~20k steps learn the task.
"""

from __future__ import annotations

import argparse

import numpy as np

from physicsrl.coordinated import Coordinator, abort_on_error
from physicsrl.envs import exact_optimum, load_config, make_env
from physicsrl.envs.gym import GymnasiumView


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000, help="environment steps of training")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("overrides", nargs="*", help="config overrides, e.g. env.mesh.cells=20")
    args = parser.parse_args()

    coordinator = Coordinator()
    env = make_env(load_config("heat", overrides=args.overrides, seed=args.seed), coordinator)
    with abort_on_error(), coordinator:  # followers serve the simulation until the leader leaves
        if not coordinator.is_leader():
            return
        from stable_baselines3 import DQN
        from stable_baselines3.common.logger import Logger

        gym_env = GymnasiumView(env)
        model = DQN(
            "MlpPolicy",
            gym_env,
            learning_starts=200,
            exploration_fraction=0.3,
            target_update_interval=250,
            seed=args.seed,
            verbose=0,
        )
        model.set_logger(Logger(folder=None, output_formats=[]))  # else an empty dir in /tmp
        model.learn(total_timesteps=args.steps)

        optimum = exact_optimum(env)
        returns = []
        for level in optimum.levels:  # one greedy episode per level
            observation, total, done = gym_env.env.task.reset(int(level)), 0.0, False
            while not done:
                action, _ = model.predict(observation.astype(np.float32), deterministic=True)
                observation, reward, terminated, truncated, _ = gym_env.step(action)
                total, done = total + reward, terminated or truncated
            returns.append(total)
        print(f"DQN after {args.steps} steps: mean return {np.mean(returns):.3f}")
        print(
            f"exact optimum {optimum.mean:.3f}; stop at once {optimum.returns[:, 0].mean():.3f}; "
            f"never stop {optimum.returns[:, -1].mean():.3f}"
        )


if __name__ == "__main__":
    main()
