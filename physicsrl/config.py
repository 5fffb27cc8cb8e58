"""The typed config of ``physicsrl-train`` and ``physicsrl-eval``: every default, once.

Structured dataclasses that Hydra/OmegaConf compose from ``conf/train.yaml`` (the YAML only
sets values): an unknown key or a wrong type fails while composing, an Enum field accepts only
its members, and each ``__post_init__`` checks ranges when :func:`typed` instantiates the
config, with a ValueError naming the full key (``optim.lr must be a finite number > 0``). The
sections are named after the TorchRL objects they configure; the factories of
:mod:`physicsrl.builders` and :class:`physicsrl.dojo.Dojo` take them.

The task groups (``env``, ``observation``, ``reward``) are plain mappings here: their typed
configs live beside each task in :mod:`physicsrl.envs` (``HeatConfig``, ``ATPConfig``, ...).

Seeds: training batch ``i`` of a run with seed ``s`` resets the env with :func:`train_seed`
``(s, i) = s * 1e6 + i``; evaluation uses the held-out seeds 1e9, 1e9 + 1, ...
(:func:`held_out_seeds`), never met in training while ``s < 1000``. A YAML names the first
``n`` of them as ``${held_out:n}``. Member i of a batch seeded with ``s`` is seeded with
``s + i * SEED_STRIDE`` (:func:`~physicsrl.envs.members.member_seed`); :func:`is_held_out` tells
the two kinds apart in any member.
"""

from __future__ import annotations

import collections
import dataclasses
import enum
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from physicsrl.checks import choice, integer, number, plain, positive

HELD_OUT_START = 1_000_000_000
SEEDS_PER_RUN = 1_000_000
SEED_STRIDE = 1 << 40  # between the seeds of a batch's members
# float32 parameters, held 5 times: the online and target networks, the gradient, Adam's moments
BYTES_PER_PARAMETER = 4 * 5
# a simulator's peak memory per cell of its mesh (DOLFINx/PETSc), rounded up from the
# Mitchell-Schaeffer model's on one rank (benchmarks/ms_memory.py)
MESH_BYTES_PER_CELL = 1000
# the torch backend's memory per replica and dof: u, w and the step's temporaries (float64)
STATE_BYTES_PER_DOF = 6 * 8


def train_seed(seed: int, iteration: int) -> int:
    """The env seed of training batch ``iteration`` of a run with ``seed``."""
    return seed * SEEDS_PER_RUN + iteration


def training_seeds_among(seed: int, iterations: int, seeds: list[int]) -> list[int]:
    """Those of ``seeds`` that seed a training batch 0..iterations-1 of a run with ``seed``."""
    first, last = train_seed(seed, 0), train_seed(seed, max(iterations - 1, 0))
    return [s for s in seeds if first <= s <= last]


def check_seeds(seed: int, iterations: int, eval_seeds: list[int]) -> None:
    """ValueError if one of ``eval_seeds`` is also the seed of a training batch 0..iterations-1
    of a run with ``seed``."""
    clash = training_seeds_among(seed, iterations, eval_seeds)
    if clash:
        raise ValueError(
            f"eval.seeds {clash[:3]} are also training seeds (seed * 1e6 + i for iteration i; "
            "a seed below 1000 never meets the held-out ones)"
        )


MAX_SEEDS = SEEDS_PER_RUN
"""The most seeds (episodes per policy) one evaluation takes."""


def held_out_seeds(n: int) -> list[int]:
    """The first ``n`` held-out evaluation seeds (1 <= n <= :data:`MAX_SEEDS`)."""
    integer("the number of held-out seeds", n, 1)
    if n > MAX_SEEDS:
        raise ValueError(f"{n} held-out seeds (an episode each): at most {MAX_SEEDS}")
    return list(range(HELD_OUT_START, HELD_OUT_START + n))


def check_seed_list(name: str, seeds: list) -> None:
    """ValueError naming ``name`` unless ``seeds`` are integers >= 0, each once."""
    for i, seed in enumerate(seeds):
        integer(f"{name}[{i}]", seed, 0)
    repeated = [seed for seed, count in collections.Counter(map(int, seeds)).items() if count > 1]
    if repeated:
        raise ValueError(f"{name} lists {repeated[0]} more than once (one episode per seed)")


def check_sweep_resume(resume) -> None:
    """ValueError unless ``resume`` suits every job of a sweep: unset, or true (each job its
    own run), not one run directory named for all."""
    if resume not in (None, False, True) and str(resume).lower() not in ("true", "false", "null"):
        raise ValueError(
            f"resume={resume}: in a sweep every job would continue that one run; resume=true "
            "continues each job's own run (with the earlier sweep's hydra.sweep.dir)"
        )


def is_held_out(seed: int | None) -> bool:
    """Whether an env seeded with ``seed`` runs held-out episodes: a held-out seed, a member's
    seed derived from one, or None (unseeded). Tasks that draw training episodes from a fixed
    pool draw these outside it (``reset.pool`` of :mod:`physicsrl.envs.atp`)."""
    return seed is None or seed % SEED_STRIDE >= HELD_OUT_START


class Activation(enum.Enum):
    relu = "relu"
    tanh = "tanh"
    elu = "elu"
    gelu = "gelu"


class Storage(enum.Enum):
    tensor = "tensor"  # LazyTensorStorage (RAM)
    memmap = "memmap"  # LazyMemmapStorage (files in the run directory)


class LossFunction(enum.Enum):
    l1 = "l1"
    l2 = "l2"
    smooth_l1 = "smooth_l1"


class TargetKind(enum.Enum):
    soft = "soft"  # SoftUpdate: Polyak averaging with tau after every update
    hard = "hard"  # HardUpdate: copy every `period` updates


def member(name: str, kind: type[enum.Enum], value) -> enum.Enum:
    """``value`` (a member of the Enum ``kind`` or a member's value, as a Python caller may
    write it) as the member, else ValueError naming ``name`` (:func:`~physicsrl.checks.choice`)."""
    return kind(choice(name, getattr(value, "value", value), [m.value for m in kind]))


def fraction(name: str, value, open_low: bool = False) -> float:
    """``value`` in [0, 1] ((0, 1] if ``open_low``), else ValueError naming ``name``."""
    return number(name, value, low=0.0, high=1.0, open_low=open_low)


@dataclass
class Network:
    """The Q-network: ``inputs`` (env keys, concatenated) -> [Normalizer] -> MLP."""

    inputs: list[str] = field(default_factory=lambda: ["observation"])
    hidden: list[int] = field(default_factory=lambda: [64, 64])  # []: a linear model
    activation: Activation = Activation.relu
    normalize: bool = True  # fit (x - mean) / std on the first collected data

    def __post_init__(self):
        self.activation = member("agent.network.activation", Activation, self.activation)
        if not self.inputs:
            raise ValueError("agent.network.inputs must name at least one env key")
        for i, width in enumerate(self.hidden):
            integer(f"agent.network.hidden[{i}]", width, 1)


@dataclass
class Exploration:
    """``EGreedyModule``: epsilon annealed linearly per collected frame; with
    ``random_action_within`` = K > 0, also one other action per episode, at a decision drawn
    from 0..K-1, and that fraction ``probe_episodes`` of the episodes probes: action 0 at every
    other decision (:class:`~physicsrl.builders.OneRandomAction`)."""

    eps_init: float = 1.0
    eps_end: float = 0.05
    annealing_frames: int = 800
    random_action_within: int = 0
    probe_episodes: float = 0.0

    def __post_init__(self):
        fraction("agent.exploration.eps_init", self.eps_init)
        fraction("agent.exploration.eps_end", self.eps_end)
        integer("agent.exploration.annealing_frames", self.annealing_frames, 1)
        integer("agent.exploration.random_action_within", self.random_action_within, 0)
        fraction("agent.exploration.probe_episodes", self.probe_episodes)
        if self.probe_episodes and not self.random_action_within:
            raise ValueError(
                "agent.exploration.probe_episodes needs random_action_within > 0 (the "
                f"decisions a probe acts at), got probe_episodes={self.probe_episodes!r}"
            )


@dataclass
class DQNAgent:
    name: str = "dqn"
    lr: float = 1e-3
    network: Network = field(default_factory=Network)
    exploration: Exploration = field(default_factory=Exploration)

    def __post_init__(self):
        positive("agent.lr", self.lr)


@dataclass
class Mpi:
    ranks: int = 1  # on the command line: re-launch under mpiexec -n ranks
    ranks_per_env: int = 1  # P: the job's W ranks run W / P environments of P ranks each

    def __post_init__(self):
        integer("mpi.ranks_per_env", self.ranks_per_env, 1)


@dataclass
class CollectorConfig:
    frames_per_batch: int = 20  # transitions per batch, over all environments
    frames_per_env: int = 0  # > 0: frames_per_batch = frames_per_env x the environments
    reset_at_each_iter: bool = True  # every batch starts a fresh episode seeded by iteration

    def __post_init__(self):
        integer("collector.frames_per_batch", self.frames_per_batch, 1)
        integer("collector.frames_per_env", self.frames_per_env, 0)

    def frames(self, environments: int) -> int:
        """Transitions per batch for a job of ``environments`` environments: TorchRL's
        collector rounds ``frames_per_batch`` up to a whole number of steps of them all."""
        if self.frames_per_env:
            return self.frames_per_env * environments
        return -(-self.frames_per_batch // environments) * environments


@dataclass
class BufferConfig:
    size: int = 10_000
    storage: Storage = Storage.tensor
    batch_size: int = 64

    def __post_init__(self):
        self.storage = member("buffer.storage", Storage, self.storage)
        integer("buffer.size", self.size, 1)
        integer("buffer.batch_size", self.batch_size, 1)


@dataclass
class TargetConfig:
    kind: TargetKind = TargetKind.soft
    tau: float = 0.05
    period: int = 100

    def __post_init__(self):
        self.kind = member("loss.target.kind", TargetKind, self.kind)
        fraction("loss.target.tau", self.tau, open_low=True)
        integer("loss.target.period", self.period, 1)


@dataclass
class LossConfig:
    gamma: float = 0.99
    loss_function: LossFunction = LossFunction.smooth_l1
    double_dqn: bool = True
    n_steps: int = 1  # n-step TD targets
    # extra cost of each action (by index) in the rewards learnt from, never in evaluations
    # ([0, 40]: action 1 costs 40 more in training); []: none
    action_costs: list[float] = field(default_factory=list)
    target: TargetConfig = field(default_factory=TargetConfig)

    def __post_init__(self):
        self.loss_function = member("loss.loss_function", LossFunction, self.loss_function)
        fraction("loss.gamma", self.gamma, open_low=True)
        integer("loss.n_steps", self.n_steps, 1)
        for i, cost in enumerate(self.action_costs):
            number(f"loss.action_costs[{i}]", cost)


@dataclass
class OptimConfig:
    lr: float | None = None  # None: the agent's (agent.lr)
    weight_decay: float = 0.0
    updates_per_batch: int = 8
    learning_starts: int = 200  # frames collected before the first update
    grad_clip: float = 10.0  # max gradient norm (0: off)

    def __post_init__(self):
        if self.lr is not None:
            positive("optim.lr", self.lr)
        number("optim.weight_decay", self.weight_decay, low=0.0)
        integer("optim.updates_per_batch", self.updates_per_batch, 0)
        integer("optim.learning_starts", self.learning_starts, 0)
        number("optim.grad_clip", self.grad_clip, low=0.0)


@dataclass
class LoggerConfig:
    tensorboard: bool = True
    progress: bool = True


@dataclass
class CheckpointConfig:
    every: int = 25  # iterations (0: only at the end and on a stop request)
    keep: int = 3

    def __post_init__(self):
        integer("checkpoint.every", self.every, 0)
        integer("checkpoint.keep", self.keep, 1)


@dataclass
class Evaluation:
    every: int = 10  # iterations (0: only at the end)
    seeds: list[int] = field(default_factory=lambda: held_out_seeds(10))
    baselines: bool = True  # the summary compares with the task's baseline policies

    def __post_init__(self):
        integer("eval.every", self.every, 0)
        if not self.seeds:
            raise ValueError("eval.seeds must list at least one seed")
        check_seed_list("eval.seeds", list(self.seeds))


@dataclass
class TrainConfig:
    mpi: Mpi = field(default_factory=Mpi)
    env: dict[str, Any] = field(default_factory=dict)
    observation: dict[str, Any] = field(default_factory=dict)
    reward: dict[str, Any] = field(default_factory=dict)
    agent: DQNAgent = field(default_factory=DQNAgent)
    seed: int = 0
    iterations: int = 50
    threads: int = 1
    resume: Any = None  # null | true | a run directory
    collector: CollectorConfig = field(default_factory=CollectorConfig)
    buffer: BufferConfig = field(default_factory=BufferConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)
    eval: Evaluation = field(default_factory=Evaluation)
    # the cap on the estimated bytes of the Q-network, the replay buffer and the simulator,
    # per process (check_memory)
    max_memory_gb: float = 16.0

    def __post_init__(self):
        positive("max_memory_gb", self.max_memory_gb)
        integer("seed", self.seed, 0)
        integer("iterations", self.iterations, 1)
        integer("threads", self.threads, 1)
        if self.resume not in (None, True, False) and not isinstance(self.resume, str):
            raise ValueError(f"resume must be true, false or a run directory, got {self.resume!r}")
        check_seeds(self.seed, self.iterations, self.eval.seeds)

    @property
    def learning_rate(self) -> float:
        """``optim.lr``, or the agent's ``agent.lr`` when that is null."""
        return self.agent.lr if self.optim.lr is None else self.optim.lr


@dataclass
class EvalConfig:
    mpi: Mpi = field(default_factory=Mpi)
    run: str = "???"  # a run directory (its latest checkpoint) or a checkpoint file
    seeds: Any = None  # null: the run's eval.seeds; a list of seeds; or N: the first N held out
    baselines: bool = True
    gif: bool = True
    gif_seed: Any = None  # null: the first seed the greedy policy succeeds on (else the first)
    fps: float = 1.5
    fields: bool = False  # u (and w) of the GIF's episode as a VTX series (ParaView) and a PNG
    curve: bool = True  # learning_curve.png from the run's eval.csv (physicsrl.learning_curve)
    overrides: list[str] = field(default_factory=list)  # changes to the run's config

    def __post_init__(self):
        positive("fps", self.fps)
        seeds = plain(self.seeds)
        if isinstance(seeds, list) and seeds:
            check_seed_list("seeds", seeds)
        elif seeds is not None:
            try:
                integer("seeds", seeds, 1)
            except ValueError:
                raise ValueError(
                    f"seeds must be N >= 1, a non-empty list of seeds >= 0, or null; got {seeds!r}"
                ) from None
            if seeds > MAX_SEEDS:
                raise ValueError(
                    f"seeds={seeds}: N runs N episodes per policy, at most {MAX_SEEDS} (a seed "
                    f"itself goes in a list: seeds=[{seeds}])"
                )
        if self.gif_seed is not None:
            integer("gif_seed", self.gif_seed, 0)


def network_parameters(n_inputs: int, hidden: list[int], n_actions: int) -> int:
    """The weights and biases of the MLP ``n_inputs -> hidden... -> n_actions``."""
    widths = [n_inputs, *hidden, n_actions]
    return sum((a + 1) * b for a, b in zip(widths, widths[1:], strict=False))


def transition_bytes(input_bytes: int, n_actions: int) -> int:
    """Bytes of one stored transition: the env's observation keys (``input_bytes``) now and
    next, the action (int64), the Q-values and the chosen one (float32), the reward (float32)
    and the done, terminated and truncated flags now and next (bool)."""
    return 2 * input_bytes + 8 + 4 * (n_actions + 1) + 4 + 2 * 3


def check_memory(
    config: TrainConfig,
    inputs: dict[str, tuple[int, int]],
    n_actions: int,
    others: dict[str, tuple[float, str]] | None = None,
) -> None:
    """ValueError naming ``agent.network.hidden`` or ``buffer.size`` if the Q-network
    (:data:`BYTES_PER_PARAMETER` per parameter) or the replay buffer (``buffer.size`` x
    :func:`transition_bytes`) would need more than ``max_memory_gb`` (10^9 bytes; a memory-mapped
    buffer: disk), or naming a setting of ``others`` (setting -> (bytes, how)) over it.
    ``inputs``: the env's observation keys, each (numbers per step, bytes each); a network
    input missing from it counts as one number."""
    network = config.agent.network
    n_inputs = sum(inputs.get(key, (1, 4))[0] for key in network.inputs)
    parameters = network_parameters(n_inputs, network.hidden, n_actions)
    per_transition = transition_bytes(sum(n * size for n, size in inputs.values()), n_actions)
    needs = {
        f"agent.network.hidden={list(network.hidden)}": (
            parameters * BYTES_PER_PARAMETER,
            f"{parameters:.3g} parameters x {BYTES_PER_PARAMETER} bytes",
        ),
        f"buffer.size={config.buffer.size}": (
            config.buffer.size * per_transition,
            f"{per_transition} bytes per transition",
        ),
        **(others or {}),
    }
    check_needs(needs, config.max_memory_gb)


def check_needs(needs: dict[str, tuple[float, str]], max_memory_gb: float) -> None:
    """ValueError naming the first setting of ``needs`` (setting -> (bytes, how)) that would
    need more than ``max_memory_gb`` (10^9 bytes)."""
    for setting, (size, how) in needs.items():
        if size > max_memory_gb * 1e9:
            raise ValueError(
                f"{setting} would need about {size / 1e9:.3g} GB ({how}), more than "
                f"max_memory_gb={max_memory_gb:g} (raise it to allow)"
            )


def train_default(key: str) -> Any:
    """The default of the top-level setting ``key`` of :class:`TrainConfig`."""
    return {f.name: f.default for f in dataclasses.fields(TrainConfig)}[key]


def register() -> None:
    """Make the schemas known to Hydra (``conf/train.yaml`` and ``conf/eval.yaml`` use them), and
    the resolvers ``${held_out:n}``: the first ``n`` held-out seeds, and ``${train_default:key}``
    (the benchmarks' ``max_memory_gb``)."""
    from hydra.core.config_store import ConfigStore
    from omegaconf import OmegaConf

    OmegaConf.register_new_resolver("held_out", held_out_seeds, replace=True)
    OmegaConf.register_new_resolver("train_default", train_default, replace=True)
    store = ConfigStore.instance()
    store.store(name="train_schema", node=TrainConfig)
    store.store(name="eval_schema", node=EvalConfig)


def typed(cfg) -> Any:
    """The dataclass instance of a composed config: every key known to its schema (checked
    here: Hydra's ``+key=value`` adds keys that ``OmegaConf.to_object`` would drop), every
    ``__post_init__`` check run."""
    from omegaconf import OmegaConf

    check_keys(cfg, OmegaConf.get_type(cfg))
    return OmegaConf.to_object(cfg)


def train_config(config: TrainConfig | Mapping | None = None) -> TrainConfig:
    """``config`` as a :class:`TrainConfig`: itself, the defaults (None), or a mapping of its
    keys (nested dicts or a ``DictConfig``, e.g. ``{"optim": {"lr": 3e-4}}``) on the defaults,
    checked as the command line's (an unknown key or a bad value raises, naming the key), its
    ``${held_out:n}`` resolved as in the YAML."""
    if isinstance(config, TrainConfig):
        return config
    from omegaconf import OmegaConf

    register()
    return typed(OmegaConf.merge(OmegaConf.structured(TrainConfig), config or {}))


def parse_overrides(overrides) -> Any:
    """Dotted ``key=value`` strings (a list; e.g. ``["env.dt=0.02"]``) as one ``DictConfig``
    (its values parsed as YAML); ValueError naming the first that is not one."""
    from omegaconf import OmegaConf

    if isinstance(overrides, str):
        raise ValueError(f"overrides must be a list of key=value strings, got {overrides!r}")
    changes = []
    for override in overrides:
        key, equals, _ = str(override).partition("=")
        if not equals or not all(part.isidentifier() for part in key.split(".")):
            raise ValueError(f"overrides: {override!r} is not key=value with a dotted key")
        try:
            changes.append(OmegaConf.from_dotlist([str(override)]))
        except Exception as error:  # noqa: BLE001 - YAML's parser errors
            raise ValueError(f"overrides: cannot parse {override!r}") from error
    return OmegaConf.merge(OmegaConf.create(), *changes)


def check_keys(cfg, schema: type, prefix: str = "") -> None:
    """ValueError naming the first key of ``cfg`` that the dataclass ``schema`` lacks."""
    fields = {f.name for f in dataclasses.fields(schema)}
    hints = typing.get_type_hints(schema)
    for key in cfg:
        if key not in fields:
            raise ValueError(f"unknown key '{prefix}{key}' (not in {schema.__name__})")
        if dataclasses.is_dataclass(hints[key]):
            check_keys(cfg[key], hints[key], f"{prefix}{key}.")


def as_dict(cfg) -> dict:
    """A composed or typed config as plain dicts, lists and strings (Enums by name)."""
    from omegaconf import OmegaConf

    if not OmegaConf.is_config(cfg):
        cfg = OmegaConf.structured(cfg)
    return OmegaConf.to_container(cfg, resolve=True, enum_to_str=True)
