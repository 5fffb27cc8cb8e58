"""physicsrl: reinforcement learning against distributed FEniCSx (DOLFINx) simulations, on TorchRL.

- :mod:`physicsrl.coordinated`: the RL runs on the leader rank, the simulator's ``@parallel``
  methods are replayed on every rank.
- :mod:`physicsrl.fem`: ``TimeProblem``, the heat equation, the monodomain Mitchell-Schaeffer
  model, each reporting how well its mesh resolves the solution.
- :mod:`physicsrl.envs`: the tasks as TorchRL environments (``load_config``, ``make_env``).
- :mod:`physicsrl.dojo`: DQN training (``Dojo``), set by :class:`physicsrl.config.TrainConfig`.
- The commands ``physicsrl-train``, ``physicsrl-eval`` and ``physicsrl-bench`` (Hydra, MPI).
"""

from importlib.metadata import version

__version__ = version("physicsrl")
