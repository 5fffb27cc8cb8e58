"""Factories for the training runner: env, Q-network, exploration, loss, target updater, buffer.

Each factory takes the typed config section (:mod:`physicsrl.config`) named after the TorchRL
object it builds and returns that object; :class:`physicsrl.dojo.Dojo` builds its objects with
them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
from torch import nn
from torchrl.data import LazyMemmapStorage, LazyTensorStorage, ReplayBuffer
from torchrl.data.replay_buffers import RandomSampler
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, exploration_type
from torchrl.modules import MLP, EGreedyModule, QValueActor
from torchrl.objectives import DQNLoss, HardUpdate, SoftUpdate

from physicsrl.config import (
    BufferConfig,
    Exploration,
    LossConfig,
    Network,
    Storage,
    TargetConfig,
    TargetKind,
)
from physicsrl.imports import load_object

__all__ = [
    "Normalizer",
    "make_env",
    "make_q_network",
    "q_values",
    "make_exploration",
    "OneRandomAction",
    "make_loss",
    "make_target_updater",
    "make_optimizer",
    "make_buffer",
]

ACTIVATIONS = {"relu": nn.ReLU, "tanh": nn.Tanh, "elu": nn.ELU, "gelu": nn.GELU}  # Activation


# env ------------------------------------------------------------------------------------------
def make_env(cfg: Any, coordinator) -> EnvBase:
    """The task of ``cfg`` (groups ``env``, ``observation``, ``reward`` and ``seed``).

    Collective: call it on every rank in the same order (the simulator registers with
    ``coordinator``). ``env.factory: "module:function"`` (or ``"file.py:function"``) picks any
    factory with the signature of :func:`physicsrl.envs.make_env`; the default is that one.
    """
    factory = cfg["env"].get("factory")
    if factory:
        return load_object(str(factory))(cfg, coordinator)
    from physicsrl import envs

    return envs.make_env(cfg, coordinator)


# model ----------------------------------------------------------------------------------------
class Normalizer(nn.Module):
    """``(x - loc) / scale``, fitted once from data.

    ``loc`` and ``scale`` are plain tensors, not buffers: the online and the target network of
    ``DQNLoss`` (which copies parameters and buffers) share them, so the target network never
    sees differently scaled inputs. They travel in ``state_dict`` as the module's extra state.
    """

    def __init__(self, size: int):
        super().__init__()
        self.loc = torch.zeros(size)
        self.scale = torch.ones(size)
        self.fitted = False

    @torch.no_grad()
    def fit(self, observations: torch.Tensor, min_scale: float = 1e-3) -> None:
        x = observations.reshape(-1, self.loc.numel()).float()
        self.loc = x.mean(0)
        self.scale = (
            x.std(0, unbiased=False).clamp_min(min_scale)
            if len(x) > 1
            else torch.ones_like(self.loc)
        )
        self.fitted = True

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.loc) / self.scale

    def get_extra_state(self) -> dict:
        return {"loc": self.loc.clone(), "scale": self.scale.clone(), "fitted": self.fitted}

    def set_extra_state(self, state: dict) -> None:
        self.loc, self.scale = state["loc"].clone(), state["scale"].clone()
        self.fitted = state["fitted"]

    def extra_repr(self) -> str:
        return f"size={self.loc.numel()}, fitted={self.fitted}"


class Inputs(nn.Sequential):
    """``nn.Sequential`` fed with several tensors (one per input key, each (..., n_k)),
    concatenated along the last dimension as float32."""

    @staticmethod
    def concat(*inputs: torch.Tensor) -> torch.Tensor:
        return torch.cat([x.float() for x in inputs], -1)

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        return super().forward(self.concat(*inputs))


def make_q_network(env: EnvBase, network: Network | None = None):
    """A greedy ``QValueActor``: inputs -> [Normalizer] -> MLP -> argmax over the actions.

    ``network``: ``inputs`` (the env keys the network reads, concatenated in this order;
    default ``[observation]``; e.g. ``[observation, step]`` adds the decision index),
    ``hidden`` (list of layer widths), ``activation`` (relu, tanh, elu, gelu), ``normalize``
    (put a :class:`Normalizer` first; the Dojo fits it once from the first collected data);
    default: :class:`~physicsrl.config.Network`'s defaults.
    """
    network = network or Network()
    inputs = [str(key) for key in network.inputs]
    unknown = [key for key in inputs if key not in env.observation_spec.keys()]
    if unknown:
        raise ValueError(
            f"agent.network.inputs {inputs}: each must be one of the env's observation keys "
            f"{sorted(env.observation_spec.keys())}"
        )
    spec = env.action_spec_unbatched  # one environment's (batched envs: N of them)
    n_obs = sum(int(env.observation_spec[key].shape[-1]) for key in inputs)
    return QValueActor(q_values(n_obs, int(spec.space.n), network), in_keys=inputs, spec=spec)


def q_values(n_inputs: int, n_actions: int, network: Network) -> Inputs:
    """The Q-network's module: ``network.inputs``' tensors (..., n_k), concatenated (n_inputs
    numbers), -> [Normalizer] -> MLP -> Q-values (..., n_actions)."""
    layers: list[nn.Module] = [Normalizer(n_inputs)] if network.normalize else []
    activation = ACTIVATIONS[network.activation.value]
    hidden = list(network.hidden)
    layers.append(MLP(n_inputs, n_actions, num_cells=hidden, activation_class=activation))
    return Inputs(*layers)


def normalizer_of(q_network: nn.Module) -> Normalizer | None:
    """The :class:`Normalizer` inside ``q_network``, if any."""
    return next((m for m in q_network.modules() if isinstance(m, Normalizer)), None)


class OneRandomAction(TensorDictModuleBase):
    """One exploratory decision per episode: when an episode starts (``step`` = 0), draw a
    decision index uniformly from 0..``within``-1; at that decision, replace the action by one
    of the other ``n_actions`` actions, drawn uniformly.

    Epsilon-greedy deviates at every step independently, so an episode that deviates once, at
    one chosen time, and then follows the policy is rare while epsilon is high and rarer still
    when it is low; tasks where one well-timed action decides the episode (a shock) need just
    those episodes. With ``probes`` = p > 0, an episode is a probe with probability p: it
    takes action 0 at every decision but the drawn one, whatever the policy says, so that what
    one action at one decision leads to is seen on the task's own draws, at every decision.
    Reads ``step`` (the decision index, shape (*batch, 1)) and ``action``
    (an index, shape (*batch,), or one-hot, (*batch, n_actions)); acts under
    ``ExplorationType.RANDOM`` (the collector's) or when none is set, as ``EGreedyModule`` does,
    with torch's global generator (checkpointed).
    """

    def __init__(self, within: int, n_actions: int, probes: float = 0.0):
        super().__init__()
        self.in_keys, self.out_keys = ["step", "action"], ["action"]
        self.within, self.n_actions, self.probes = int(within), int(n_actions), float(probes)
        self.chosen: torch.Tensor | None = None  # (*batch,): each episode's decision
        self.probing: torch.Tensor | None = None  # (*batch,): whether each episode is a probe

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        if exploration_type() not in (ExplorationType.RANDOM, None):
            return td
        step = td["step"].reshape(td.batch_size)
        if self.chosen is None or self.chosen.shape != step.shape:
            self.chosen = torch.full(step.shape, -1)
            self.probing = torch.zeros(step.shape, dtype=torch.bool)
        starts = step == 0
        self.chosen[starts] = torch.randint(self.within, (int(starts.sum()),))
        if self.probes:  # no draw otherwise: the random stream of runs without probes stays
            self.probing[starts] = torch.rand(int(starts.sum())) < self.probes
        action = td["action"]
        one_hot = action.shape != step.shape
        index = action.long().argmax(-1) if one_hot else action
        index = torch.where(self.probing, 0, index)
        other = (index + torch.randint(1, self.n_actions, index.shape)) % self.n_actions
        index = torch.where(step == self.chosen, other, index)
        chosen = torch.nn.functional.one_hot(index, self.n_actions) if one_hot else index
        td["action"] = chosen.to(action.dtype)
        return td


def make_exploration(q_network: TensorDictModule, env: EnvBase, exploration: Exploration):
    """``TensorDictSequential(q_network, [OneRandomAction,] EGreedyModule)``: epsilon-greedy,
    annealed linearly from ``eps_init`` to ``eps_end`` over ``annealing_frames`` (call
    ``[-1].step(n)``), after one other action per episode (and probe episodes) if
    ``random_action_within`` > 0."""
    greedy = EGreedyModule(
        spec=env.action_spec_unbatched,
        eps_init=exploration.eps_init,
        eps_end=exploration.eps_end,
        annealing_num_steps=exploration.annealing_frames,
    )
    if not exploration.random_action_within:
        return TensorDictSequential(q_network, greedy)
    if "step" not in env.observation_spec.keys():
        raise ValueError(
            "agent.exploration.random_action_within needs the env's decision index 'step' "
            f"(its keys: {', '.join(map(str, env.observation_spec.keys()))})"
        )
    n_actions = env.action_spec_unbatched.space.n
    once = OneRandomAction(exploration.random_action_within, n_actions, exploration.probe_episodes)
    return TensorDictSequential(q_network, once, greedy)


def make_loss(q_network: TensorDictModule, env: EnvBase, loss: LossConfig) -> DQNLoss:
    """``DQNLoss`` with a target network and a TD(0) value estimator of discount ``gamma``."""
    module = DQNLoss(
        value_network=q_network,
        loss_function=loss.loss_function.value,
        delay_value=True,  # a target network (double DQN needs it too)
        double_dqn=loss.double_dqn,
        action_space=env.action_spec_unbatched,
    )
    module.make_value_estimator(gamma=loss.gamma)
    return module


def make_target_updater(loss_module: DQNLoss, target: TargetConfig):
    """``SoftUpdate(tau=...)`` (Polyak averaging every update) or ``HardUpdate`` (copy every
    ``period`` updates), from ``target.kind``."""
    if target.kind is TargetKind.soft:
        return SoftUpdate(loss_module, tau=target.tau)
    return HardUpdate(loss_module, value_network_update_interval=target.period)


def make_optimizer(loss_module: nn.Module, lr: float, weight_decay: float) -> torch.optim.Optimizer:
    """Adam over the trainable parameters of the loss (the target network is not trainable)."""
    return torch.optim.Adam(
        [p for p in loss_module.parameters() if p.requires_grad], lr=lr, weight_decay=weight_decay
    )


def make_buffer(buffer: BufferConfig, scratch_dir: str | Path | None = None) -> ReplayBuffer:
    """Uniform replay of ``size`` transitions in ``LazyTensorStorage`` (RAM) or, with
    ``storage: memmap``, ``LazyMemmapStorage`` (memory-mapped files under ``scratch_dir``)."""
    if buffer.storage is Storage.tensor:
        storage = LazyTensorStorage(buffer.size)
    else:
        scratch = None if scratch_dir is None else str(scratch_dir)
        storage = LazyMemmapStorage(buffer.size, scratch_dir=scratch)
    return ReplayBuffer(storage=storage, sampler=RandomSampler(), batch_size=buffer.batch_size)
