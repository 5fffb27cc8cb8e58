"""The training runner: the Dojo learns a known optimum; ``physicsrl-train`` under MPI writes
only the leader's run directory; a killed run resumes to the uninterrupted result; bad configs
fail fast with one line.

The MPI runs train the toy chain of ``tests/mpi_scripts/train_toy_env.py`` (a coordinated env
whose every step is a parallel call with an MPI reduction) through ``env.factory``, so that they
take seconds; the heat task is trained by ``physicsrl-train`` itself (see docs).
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import imageio.v2 as imageio
import pytest
import torch
from tensordict import TensorDict

from physicsrl.config import held_out_seeds
from tests.conftest import MPIEXEC, ROOT, SMALL_ATP

BIN = Path(sys.executable).parent
TRAIN = str(BIN / "physicsrl-train")
TOY = ROOT / "tests" / "mpi_scripts" / "train_toy_env.py"
ITERATIONS = 30
QUICK = [
    f"+env.factory={TOY}:make_env",
    f"iterations={ITERATIONS}",
    "collector.frames_per_batch=16",
    "optim.learning_starts=64",
    "eval.every=10",
    "checkpoint.every=10",
    "checkpoint.keep=2",
    "logger.progress=false",
]


def command(run_dir: Path, *extra: str) -> list[str]:
    return [str(MPIEXEC), "-n", "2", TRAIN, *QUICK, f"hydra.run.dir={run_dir}", *extra]


def run(arguments: list[str], cwd: Path, timeout: float = 180) -> subprocess.CompletedProcess:
    environment = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.run(
        arguments, cwd=cwd, capture_output=True, text=True, timeout=timeout, env=environment
    )


def final_state(run_dir: Path) -> dict:
    from physicsrl.checkpoint import read
    from physicsrl.run_directory import checkpoint_path

    return read(checkpoint_path(str(run_dir)))


def checkpoint_name(iteration: int) -> str:
    return f"ckpt-{iteration:012d}.torchrl"


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """One uninterrupted 2-rank run of the toy task (shared by the tests below)."""
    cwd = tmp_path_factory.mktemp("reference")
    run_dir = cwd / "run"
    result = run(command(run_dir), cwd)
    assert result.returncode == 0, result.stdout + result.stderr
    return cwd, run_dir, result


@pytest.mark.parametrize(
    "n_steps, action_costs, optimum", [(1, (), 1.0), (3, (), 1.0), (1, (0.0, 2.0), 0.0)]
)
def test_dojo_learns_a_known_optimum(n_steps, action_costs, optimum):
    """In-process, one rank: greedy return of the 3-step chain reaches its optimum 1, with
    one-step and with 3-step TD targets. With stopping charged 2 in training (more than it
    ever pays) the optimum of what is learnt is never to stop: the evaluated return, in the
    task's own reward, is then 0, with no stop (a wrong stop would also return 0)."""
    sys.path.insert(0, str(TOY.parent))
    from train_toy_env import ToyChainEnv

    from physicsrl import config as c
    from physicsrl.builders import make_q_network
    from physicsrl.coordinated import Coordinator
    from physicsrl.dojo import Dojo

    torch.manual_seed(0)
    coordinator = Coordinator()
    env = ToyChainEnv(coordinator, length=3)
    config = c.TrainConfig(
        agent=c.DQNAgent(
            network=c.Network(hidden=[32, 32]), exploration=c.Exploration(annealing_frames=500)
        ),
        buffer=c.BufferConfig(size=500, batch_size=64),
        collector=c.CollectorConfig(frames_per_batch=16),
        optim=c.OptimConfig(learning_starts=64),
        loss=c.LossConfig(n_steps=n_steps, action_costs=list(action_costs)),
        eval=c.Evaluation(every=0),
        logger=c.LoggerConfig(progress=False),
    )
    with coordinator:
        q_network = make_q_network(env, config.agent.network)
        dojo = Dojo(q_network, env, config, action_counts={"stops": 1})
        summary = dojo.train(60)
    assert summary["iteration"] == 60 and summary["frames"] == 960
    buffer = dojo.replay_buffer
    assert len(buffer) == 500  # the configured capacity
    assert summary["eval"]["return"] == pytest.approx(optimum)
    assert summary["eval"]["success"] == optimum
    assert summary["eval"]["stops"] == optimum  # one stop per episode, at the mark, or none
    stored = buffer[:]
    stops = stored["action"] == 1
    assert stops.any()  # explored
    charged = stored["next", "reward"].flatten()[stops] < 0
    assert charged.all() if action_costs else not charged.any()


def test_the_collectors_first_reset_is_counted_as_simulation():
    """The env's phases (``simulated``: seconds, replica-steps, batch-steps, as the torch
    replicas report them) during training are all in the Dojo's counters, the collector's
    first reset included (an induction there, on the ATP task, was missing from the summary's
    simulation time and phases), and the evaluations' are not."""
    sys.path.insert(0, str(TOY.parent))
    from train_toy_env import ToyChainEnv

    from physicsrl import config as c
    from physicsrl.builders import make_q_network
    from physicsrl.coordinated import Coordinator
    from physicsrl.dojo import Dojo

    class CountedResets(ToyChainEnv):
        def _reset(self, tensordict=None, **kwargs):
            seconds, resets, batches = self.simulated["reset"]
            self.simulated["reset"] = (seconds + 0.25, resets + 1, batches + 1)
            return super()._reset(tensordict, **kwargs)

    coordinator = Coordinator()
    env = CountedResets(coordinator, length=3)
    env.simulated = {"reset": (0.0, 0, 0)}
    config = c.TrainConfig(
        collector=c.CollectorConfig(frames_per_batch=4),
        optim=c.OptimConfig(learning_starts=1000),
        eval=c.Evaluation(every=0, seeds=[1000000000, 1000000001]),
        logger=c.LoggerConfig(progress=False),
    )
    with coordinator:
        dojo = Dojo(make_q_network(env, config.agent.network), env, config)
        summary = dojo.train(3)
    _, resets, _ = env.simulated["reset"]
    assert summary["simulated"]["reset"] == (0.25 * (resets - 2), resets - 2, resets - 2)
    assert summary["time_s"]["simulation"] >= 0.0 and resets - 2 >= 4  # first + one per batch


def test_training_goes_on_from_a_training_seed_after_an_evaluation():
    """With episodes running across batches (``reset_at_each_iter: false``) the evaluation
    reseeds the env with held-out seeds; training then goes on from the generator of
    ``train_seed(seed, iteration)``, never from a held-out one (a task with a pool of training
    draws would otherwise draw held-out episodes, or never the pool). The learning rate is
    the agent's unless ``optim.lr`` is set."""
    from physicsrl import config as c

    config = c.TrainConfig(
        seed=3,
        agent=c.DQNAgent(lr=3e-4),
        collector=c.CollectorConfig(frames_per_batch=8, reset_at_each_iter=False),
        optim=c.OptimConfig(learning_starts=64),
        eval=c.Evaluation(every=2, seeds=c.held_out_seeds(2)),
        logger=c.LoggerConfig(progress=False),
    )
    dojo = train_toy_chain(config, 2)
    assert [row["iteration"] for row in dojo.history] == [2]
    assert dojo.env.rng.bit_generator.seed_seq.entropy == c.train_seed(3, 2)
    assert dojo.optimizer.param_groups[0]["lr"] == 3e-4
    assert replace(config, optim=c.OptimConfig(lr=1e-2)).learning_rate == 1e-2


def test_a_batch_is_a_whole_number_of_steps_of_every_environment():
    """TorchRL's collector rounds ``frames_per_batch`` up to a multiple of the environments;
    the Dojo's batch (its counts, its warning) is that number."""
    from physicsrl.config import CollectorConfig

    assert [CollectorConfig(frames_per_batch=8).frames(n) for n in (1, 3, 6)] == [8, 9, 12]
    assert CollectorConfig(frames_per_env=5).frames(3) == 15


def test_the_dojo_takes_a_mapping_of_the_configs_keys_checked_as_the_command_lines():
    """``Dojo(q, env, {"optim": {"lr": 3e-4}, ...})``: a dict or a ``DictConfig`` of the
    config's keys is the :class:`~physicsrl.config.TrainConfig` of those on the defaults, with
    the command line's checks: an unknown key, a wrong type or a bad value raises naming the
    key, before anything is built; so does a number of iterations to train that is not one.
    The YAML's ``${held_out:n}`` resolves there too."""
    sys.path.insert(0, str(TOY.parent))
    from omegaconf import OmegaConf
    from train_toy_env import ToyChainEnv

    from physicsrl import config as c
    from physicsrl.builders import make_q_network
    from physicsrl.coordinated import Coordinator
    from physicsrl.dojo import Dojo

    env = ToyChainEnv(Coordinator(), length=3)
    q_network = make_q_network(env)
    settings = {
        "iterations": 2,
        "optim": {"lr": 3e-4},
        "buffer": {"storage": "memmap"},
        "eval": {"seeds": "${held_out:2}"},  # as the YAML writes them
    }
    expected = c.TrainConfig(
        iterations=2,
        optim=c.OptimConfig(lr=3e-4),
        buffer=c.BufferConfig(storage=c.Storage.memmap),
        eval=c.Evaluation(seeds=c.held_out_seeds(2)),
    )
    OmegaConf.clear_resolver("held_out")  # as in a script that has not run a command
    for config in (settings, OmegaConf.create(settings)):
        assert Dojo(q_network, env, config).config == expected
    for bad, named in [
        ({"optim": {"nosuch": 1}}, "full_key: optim.nosuch"),
        ({"agent": {"lr": "fast"}}, "full_key: agent.lr"),
        ({"iterations": 0}, "iterations must be an integer >= 1, got 0"),
        ({"eval": {"seeds": [0]}}, r"eval.seeds \[0\] are also training seeds"),
    ]:
        with pytest.raises((KeyError, ValueError), match=named):
            Dojo(q_network, env, bad)
    with pytest.raises(ValueError, match="iterations must be an integer >= 1, got 2.5"):
        Dojo(q_network, env).train(2.5)


def test_a_python_caller_may_give_an_enum_setting_by_its_value():
    """``BufferConfig(storage="tensor")`` is the member ``Storage.tensor``, as the YAML's value
    is (the string used to pass, and the factories' ``is`` tests then built the other kind:
    a memory-mapped buffer); a value that is no member's raises naming the key."""
    from torchrl.data import LazyTensorStorage

    from physicsrl import config as c
    from physicsrl.builders import make_buffer

    assert make_buffer(c.BufferConfig(storage="tensor"))._storage.__class__ is LazyTensorStorage
    assert c.TargetConfig(kind="soft").kind is c.TargetKind.soft
    assert c.LossConfig(loss_function="l2").loss_function is c.LossFunction.l2
    assert c.Network(activation=c.Activation.tanh).activation is c.Activation.tanh
    message = "agent.network.activation must be one of relu, tanh, elu, gelu, got 'sigmoid'"
    with pytest.raises(ValueError, match=message):
        c.Network(activation="sigmoid")


def train_toy_chain(
    config, iterations: int, log_dir: Path | None = None, resume: Path | None = None
):
    """The Dojo of ``config`` trained ``iterations`` on the toy chain of length 3 (one rank),
    from the checkpoint ``resume`` if given."""
    sys.path.insert(0, str(TOY.parent))
    from train_toy_env import ToyChainEnv

    from physicsrl.builders import make_q_network
    from physicsrl.coordinated import Coordinator
    from physicsrl.dojo import Dojo

    coordinator = Coordinator()
    env = ToyChainEnv(coordinator, length=3)
    with coordinator:
        dojo = Dojo(make_q_network(env, config.agent.network), env, config, log_dir=log_dir)
        if resume is not None:
            dojo.load_checkpoint(resume)
        dojo.train(iterations)
    return dojo


def test_the_last_checkpoint_holds_the_final_evaluation(tmp_path):
    """A run whose last iteration is checkpointed in the loop (4, every 2) but not evaluated
    there (every 3): the final evaluation's row is in the last checkpoint as well as in
    ``eval.csv``, so a resumed run (loaded from the run directory) keeps it, its columns in
    the same order (a JSON round trip sorts them); a resume with another learning rate,
    discount or final epsilon runs with them, not with the values that the loaded state
    holds."""
    from physicsrl import config as c
    from physicsrl.checkpoint import Checkpoints, CheckpointsError, read
    from physicsrl.dojo import Dojo

    config = c.TrainConfig(
        collector=c.CollectorConfig(frames_per_batch=8),
        eval=c.Evaluation(every=3, seeds=c.held_out_seeds(2)),
        checkpoint=c.CheckpointConfig(every=2),
        logger=c.LoggerConfig(progress=False, tensorboard=False),
    )
    dojo = train_toy_chain(config, 4, log_dir=tmp_path)
    checkpoints = Checkpoints(tmp_path / "checkpoints", keep=3)
    changed = replace(  # settings that the loaded state holds: they take effect
        config,
        agent=c.DQNAgent(lr=3e-4, exploration=c.Exploration(eps_end=0.2)),
        loss=c.LossConfig(gamma=0.5),
    )
    resumed = Dojo(dojo.q_network, dojo.env, changed)
    (tmp_path / "empty").mkdir()
    with pytest.raises(CheckpointsError, match=f"no readable checkpoint in {tmp_path}/empty/"):
        resumed.load_checkpoint(tmp_path / "empty")  # a directory without a run
    resumed.load_checkpoint(tmp_path)  # the run directory: its newest checkpoint
    assert [list(row) for row in resumed.history] == [list(row) for row in dojo.history]
    assert resumed.optimizer.param_groups[0]["lr"] == 3e-4
    assert float(resumed.loss.value_estimator.gamma) == 0.5
    assert float(resumed.exploration[-1].eps_end) == pytest.approx(0.2)
    assert [p.name for p in checkpoints.paths()] == [checkpoint_name(i) for i in (2, 4)]
    stored = read(checkpoints.latest(), ["history", "counters"])
    assert [row["iteration"] for row in stored["history"]] == [3, 4]
    assert "evaluation" in stored["counters"]["time_s"]
    assert [r["iteration"] for r in csv.DictReader((tmp_path / "eval.csv").open())] == ["3", "4"]


def test_a_resume_of_a_finished_run_says_there_is_nothing_to_train(tmp_path, caplog):
    """A resume of a finished run warns that there is nothing to train; a new run in the
    finished run's directory (without loading its checkpoint) is refused before it writes."""
    from physicsrl import config as c
    from physicsrl.checkpoint import Checkpoints

    config = c.TrainConfig(
        collector=c.CollectorConfig(frames_per_batch=8),
        eval=c.Evaluation(every=0, seeds=c.held_out_seeds(2)),
        logger=c.LoggerConfig(progress=False, tensorboard=False),
    )
    train_toy_chain(config, 2, log_dir=tmp_path)
    assert "nothing to train" not in caplog.text
    latest = Checkpoints(tmp_path / "checkpoints", keep=3).latest()
    written = latest.read_bytes()
    with pytest.raises(FileExistsError, match=f"log_dir={tmp_path} holds another run's"):
        train_toy_chain(config, 3, log_dir=tmp_path)  # a new run there: refused, nothing written
    assert Checkpoints(tmp_path / "checkpoints", keep=3).latest().read_bytes() == written
    dojo = train_toy_chain(config, 2, log_dir=tmp_path, resume=latest)
    assert "nothing to train: iteration 2 of 2 is done" in caplog.text
    assert dojo.counters.iteration == 2 and [r["iteration"] for r in dojo.history] == [2]


def test_a_resume_with_another_batch_size_samples_it(tmp_path, monkeypatch):
    """The replay buffer's state holds its batch size; a resume with ``buffer.batch_size``
    changed samples the new size, not the stored one."""
    from torchrl.data import ReplayBuffer

    from physicsrl import config as c
    from physicsrl.checkpoint import Checkpoints

    config = c.TrainConfig(
        collector=c.CollectorConfig(frames_per_batch=8),
        optim=c.OptimConfig(learning_starts=8, updates_per_batch=2),
        buffer=c.BufferConfig(batch_size=6),
        eval=c.Evaluation(every=0),
        checkpoint=c.CheckpointConfig(every=1),
        logger=c.LoggerConfig(progress=False, tensorboard=False),
    )
    train_toy_chain(config, 2, log_dir=tmp_path)
    sizes, sample = [], ReplayBuffer.sample

    def spy(buffer, *args, **kwargs):
        batch = sample(buffer, *args, **kwargs)
        sizes.append(len(batch))
        return batch

    monkeypatch.setattr(ReplayBuffer, "sample", spy)
    changed = replace(config, buffer=c.BufferConfig(batch_size=5))
    latest = Checkpoints(tmp_path / "checkpoints", keep=3).latest()
    train_toy_chain(changed, 4, log_dir=tmp_path, resume=latest)
    assert sizes == [5] * 4


def test_charge_actions_subtracts_each_actions_cost_from_its_reward():
    from tensordict import TensorDict

    from physicsrl.dojo import charge_actions

    rewards = torch.tensor([[1.0], [2.0], [3.0]])
    for action in (torch.tensor([0, 1, 2]), torch.eye(3, dtype=torch.bool)):  # index, one-hot
        data = TensorDict(
            action=action, next=TensorDict(reward=rewards, batch_size=[3]), batch_size=[3]
        )
        out = charge_actions(data, torch.tensor([0.0, 40.0]))
        assert out["next", "reward"].flatten().tolist() == [1.0, -38.0, 3.0]
        assert data["next", "reward"].flatten().tolist() == [1.0, 2.0, 3.0]  # not in place


@pytest.mark.parametrize("one_hot", [False, True])
def test_one_random_action_per_episode_at_a_decision_within_the_horizon(one_hot):
    """``OneRandomAction``: each of 400 episodes of 6 decisions in 8 environments (batched, the
    greedy action 0 throughout) deviates exactly once, at a decision below ``within`` (4),
    uniformly enough to reach every one of them, to another action (of 3); the same seed
    repeats the draws, and a deterministic rollout is untouched."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from physicsrl.builders import OneRandomAction

    def episodes(seed: int, kind=ExplorationType.RANDOM) -> torch.Tensor:
        torch.manual_seed(seed)
        module, actions = OneRandomAction(within=4, n_actions=3), []
        for _ in range(400):
            for step in range(6):
                greedy = torch.zeros(8, dtype=torch.long)
                td = TensorDict(
                    step=torch.full((8, 1), step),
                    action=torch.nn.functional.one_hot(greedy, 3).bool() if one_hot else greedy,
                    batch_size=[8],
                )
                with set_exploration_type(kind):
                    action = module(td)["action"]
                actions.append(action.long().argmax(-1) if one_hot else action)
        return torch.stack(actions).reshape(400, 6, 8)  # (episode, decision, environment)

    actions = episodes(0)
    deviated = actions != 0
    assert (deviated.sum(1) == 1).all()  # once per episode and environment
    when = deviated.float().argmax(1)
    assert set(when.flatten().tolist()) == {0, 1, 2, 3}
    assert set(actions[deviated].tolist()) == {1, 2}
    assert torch.equal(episodes(0), actions) and not torch.equal(episodes(1), actions)
    assert (episodes(0, ExplorationType.DETERMINISTIC) == 0).all()


def test_probe_episodes_take_action_0_but_at_their_one_decision():
    """``OneRandomAction(probes=0.25)`` with the greedy action 1 throughout, 800 episodes of 6
    decisions in 8 environments: a quarter of the episodes (1600 of 6400, to 4 standard
    deviations) are probes, which take action 0 but at one decision below ``within`` (4),
    where they take 1; the others take 1 but at one such decision, where they take 0."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from physicsrl.builders import OneRandomAction

    torch.manual_seed(0)
    module, actions = OneRandomAction(within=4, n_actions=2, probes=0.25), []
    for _ in range(800):
        for step in range(6):
            td = TensorDict(
                step=torch.full((8, 1), step),
                action=torch.ones(8, dtype=torch.long),
                batch_size=[8],
            )
            with set_exploration_type(ExplorationType.RANDOM):
                actions.append(module(td)["action"])
    actions = torch.stack(actions).reshape(800, 6, 8).transpose(1, 2).reshape(-1, 6)
    probes = actions.sum(1) == 1
    assert ((actions.sum(1) == 1) | (actions.sum(1) == 5)).all()
    assert abs(int(probes.sum()) - 1600) < 4 * (6400 * 0.25 * 0.75) ** 0.5
    assert (actions[:, 4:] == (~probes)[:, None]).all()  # the one other action is below 4
    assert set(actions[probes].argmax(1).tolist()) == {0, 1, 2, 3}


def test_n_step_transitions_sum_rewards_and_stop_at_episode_ends():
    """Rewards 1 per step, an episode ending at step 2, n = 3, gamma = 1/2: the known sums,
    next states and done flags; the DQN target bootstraps only where the episode goes on."""
    from tensordict import TensorDict
    from torchrl.data import Categorical, Composite, Unbounded

    from physicsrl import builders
    from physicsrl.config import LossConfig, Network
    from physicsrl.dojo import n_step_transitions

    ended = torch.tensor([[False], [False], [True], [False], [False], [False]])
    data = TensorDict(
        observation=torch.arange(6.0)[:, None],
        action=torch.zeros(6, dtype=torch.int64),
        next=TensorDict(
            observation=torch.arange(1.0, 7.0)[:, None],
            reward=torch.ones(6, 1),
            done=ended,
            terminated=ended.clone(),
            truncated=torch.zeros(6, 1, dtype=torch.bool),
            batch_size=[6],
        ),
        batch_size=[6],
    )
    out = n_step_transitions(data, 3, 0.5)
    assert out["next", "reward"].flatten().tolist() == [1.75, 1.5, 1.0, 1.75, 1.5, 1.0]
    assert out["next", "observation"].flatten().tolist() == [3, 3, 3, 6, 6, 6]
    assert out["next", "terminated"].flatten().tolist() == [True] * 3 + [False] * 3
    assert out["steps_to_next_obs"].flatten().tolist() == [3, 2, 1, 3, 2, 1]

    env = SimpleNamespace(
        observation_spec=Composite(observation=Unbounded(shape=(1,))),
        action_spec_unbatched=Categorical(2),
    )
    q_network = builders.make_q_network(env, Network(hidden=[4], normalize=False))
    loss = builders.make_loss(q_network, env, LossConfig(gamma=0.5, double_dqn=False))
    target = loss.value_estimator.value_estimate(out.clone()).flatten()
    with torch.no_grad():
        best_next = q_network(out["next"].select("observation").clone())["chosen_action_value"]
    bootstrap = 0.5 ** out["steps_to_next_obs"].flatten() * best_next.flatten()
    expected = out["next", "reward"].flatten() + torch.tensor([0, 0, 0, 1, 1, 1]) * bootstrap
    assert torch.allclose(target, expected)


def test_n_step_transitions_of_a_batch_of_environments_are_each_its_own():
    """A collection of N = 2 environments (shape (2, T)) with episodes ending at different
    steps: each row's n-step transitions equal those of that environment alone."""
    from tensordict import TensorDict

    from physicsrl.dojo import n_step_transitions

    def steps(ends: list[int], offset: float) -> TensorDict:
        ended = torch.zeros(7, 1, dtype=torch.bool)
        ended[ends] = True
        return TensorDict(
            observation=offset + torch.arange(7.0)[:, None],
            action=torch.zeros(7, dtype=torch.int64),
            next=TensorDict(
                observation=offset + torch.arange(1.0, 8.0)[:, None],
                reward=offset + torch.arange(7.0)[:, None],
                done=ended,
                terminated=ended.clone(),
                batch_size=[7],
            ),
            batch_size=[7],
        )

    alone = [steps([1], 0.0), steps([4], 10.0)]
    batch = n_step_transitions(torch.stack(alone), 3, 0.5)
    for row, data in enumerate(alone):
        expected = n_step_transitions(data, 3, 0.5)
        for key in (
            ("next", "reward"),
            ("next", "observation"),
            ("next", "done"),
            "steps_to_next_obs",
        ):
            assert torch.equal(batch[row][key], expected[key]), (row, key)


def test_q_network_reads_its_inputs_concatenated():
    """``inputs: [observation, step]``: the MLP sees (observation, step as a float) in that
    order; an input the env does not have is a one-line error naming it."""
    from torchrl.data import Bounded, Categorical, Composite, Unbounded

    from physicsrl import builders
    from physicsrl.config import Network

    env = SimpleNamespace(
        observation_spec=Composite(
            observation=Unbounded(shape=(3,)), step=Bounded(0, 15, shape=(1,), dtype=torch.int64)
        ),
        action_spec_unbatched=Categorical(2),
    )
    network = Network(inputs=["observation", "step"], hidden=[8], normalize=False)
    q_network = builders.make_q_network(env, network)
    assert q_network.in_keys == ["observation", "step"]
    observation, step = torch.randn(5, 3), torch.arange(5)[:, None]
    values = q_network(TensorDict(observation=observation, step=step, batch_size=[5]))
    mlp = q_network.module[0].module  # Inputs(MLP)
    expected = mlp[0](torch.cat([observation, step.float()], -1))
    assert torch.allclose(values["action_value"], expected)
    with pytest.raises(ValueError, match="agent.network.inputs.*'time'"):
        builders.make_q_network(env, Network(inputs=["observation", "time"]))


def test_mpi_run_writes_checkpoints_events_and_log_only_in_the_leader_run_dir(reference):
    cwd, run_dir, result = reference
    assert result.stdout.count("held-out seeds, mean per episode") == 1  # leader prints once
    assert "greedy DQN" in result.stdout
    checkpoints = sorted(p.name for p in (run_dir / "checkpoints").iterdir())
    assert checkpoints == [checkpoint_name(20), checkpoint_name(30)]  # every 10, keep 2
    assert list((run_dir / "tensorboard").glob("events.out.tfevents.*"))
    assert (run_dir / "train.log").read_text().count("eval at iteration") == 3
    assert (run_dir / "summary.json").exists() and (run_dir / "eval.csv").exists()
    # nothing anywhere else: one .hydra, no follower run directory or log
    assert [p.relative_to(cwd) for p in cwd.rglob(".hydra")] == [Path("run/.hydra")]
    assert sorted(p.name for p in cwd.iterdir()) == ["run"]
    assert not list(cwd.rglob("*.tmp"))

    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run_dir / "tensorboard"))
    events.Reload()
    tags = set(events.Tags()["scalars"])
    for tag in (
        "train/loss",
        "train/return",
        "train/epsilon",
        "eval/return",
        "eval/success_rate",
        "perf/env_steps_per_s",
        "time/simulation_s",
        "time/coordination_s",
        "time/learner_s",
    ):
        assert tag in tags, tag
    # the learning curve's cost axes: env steps, wall seconds, core-seconds (2 ranks)
    with open(run_dir / "eval.csv") as stream:
        rows = list(csv.DictReader(stream))
    axes = {
        "eval_by_env_steps": [int(r["frames"]) for r in rows],
        "eval_by_wall_s": [round(float(r["wall_s"])) for r in rows],
        "eval_by_core_s": [round(float(r["wall_s"]) * 2) for r in rows],
    }
    for axis, steps in axes.items():
        assert cost_axis_steps(run_dir, axis) == steps, axis
    state = final_state(run_dir)
    assert state["counters"]["iteration"] == ITERATIONS


def cost_axis_steps(run_dir: Path, axis: str) -> list[int]:
    """The steps of the TensorBoard points of ``<axis>/return`` (in ``tensorboard/<axis>``)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run_dir / "tensorboard" / axis))
    events.Reload()
    return [event.step for event in events.Scalars(f"{axis}/return")]


def start_and_wait_for(arguments, cwd: Path, checkpoint: Path) -> subprocess.Popen:
    """Start ``arguments`` in a new session; return once ``checkpoint`` exists."""
    process = subprocess.Popen(
        arguments,
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    deadline = time.monotonic() + 150
    while not checkpoint.exists():
        if process.poll() is not None or time.monotonic() > deadline:
            os.killpg(process.pid, signal.SIGKILL)
            raise AssertionError(f"no {checkpoint.name} in time:\n{process.stdout.read()}")
        time.sleep(0.05)
    return process


def test_a_rank_that_vanishes_mid_training_is_named(tmp_path):
    """``physicsrl-train`` guards its ranks (:mod:`physicsrl.guard`): a follower that calls
    ``os._exit(0)`` in the env's 40th parallel call ends the job at once, with status 1 and one
    line naming it. A job that has not ended after 60 s runs once more (the guard test in
    ``test_launch.py`` says why)."""
    try:
        result = run(command(tmp_path / "run", "+env.vanish_at=40"), tmp_path, timeout=60)
    except subprocess.TimeoutExpired:
        result = run(command(tmp_path / "again", "+env.vanish_at=40"), tmp_path, timeout=60)
    assert result.returncode == 1, result.stderr
    assert result.stderr.count("ended before its job did") == 1, result.stderr
    assert "error: rank 1 ended before its job did (exited with status 0)" in result.stderr


def test_one_sigint_to_mpiexec_stops_guarded_training_cleanly(tmp_path):
    """SIGINT to ``mpiexec`` reaches the jobs of the guarded ranks of ``physicsrl-train`` and
    not their guards' deaths (:mod:`physicsrl.guard`): the run checkpoints, prints its summary
    and exits with 130."""
    run_dir = tmp_path / "run"
    arguments = command(run_dir, "iterations=100000")
    process = start_and_wait_for(arguments, tmp_path, run_dir / "checkpoints" / checkpoint_name(10))
    process.send_signal(signal.SIGINT)
    output, _ = process.communicate(timeout=60)
    assert process.returncode == 130, output
    assert "stopped early: received SIGINT" in output and "KeyboardInterrupt" not in output


def test_killed_run_resumes_to_the_uninterrupted_result(reference, tmp_path):
    """SIGKILL after a checkpoint, resume; SIGTERM that run (it checkpoints and stops), resume
    again to the end: counters, evaluations (TensorBoard's too), networks, optimizer and
    buffer equal the uninterrupted run's."""
    _, reference_dir, _ = reference
    run_dir = tmp_path / "run"
    checkpoints = run_dir / "checkpoints"
    process = start_and_wait_for(command(run_dir), tmp_path, checkpoints / checkpoint_name(10))
    os.killpg(process.pid, signal.SIGKILL)  # mpiexec and both ranks: no chance to clean up
    process.wait(timeout=30)
    killed_at = final_state(run_dir)["counters"]["iteration"]
    assert 10 <= killed_at < ITERATIONS

    # resume, then stop it with SIGTERM (to mpiexec, which forwards it to the ranks)
    process = start_and_wait_for(
        command(run_dir, f"resume={run_dir}"),
        tmp_path,
        checkpoints / checkpoint_name(killed_at + 10),
    )
    process.send_signal(signal.SIGTERM)
    output, _ = process.communicate(timeout=60)
    assert process.returncode != 0
    assert "stopped early: received SIGTERM" in output, output
    log = (run_dir / "train.log").read_text()
    frames = killed_at * 16
    assert (
        f"resumed from {checkpoints / checkpoint_name(killed_at)} at iteration {killed_at}, "
        f"{frames} frames, buffer {frames}" in log
    )  # counters and buffer restored
    stopped_at = final_state(run_dir)["counters"]["iteration"]
    assert killed_at + 10 <= stopped_at <= ITERATIONS

    result = run(command(run_dir, "resume=true"), tmp_path)  # the newest run: this one
    assert result.returncode == 0, result.stdout + result.stderr
    assert f"at iteration {stopped_at}, " in (run_dir / "train.log").read_text()

    resumed, uninterrupted = final_state(run_dir), final_state(reference_dir)
    counters = ("iteration", "frames", "episodes", "updates")
    assert [resumed["counters"][k] for k in counters] == [
        uninterrupted["counters"][k] for k in counters
    ]
    assert timeless(resumed["history"]) == timeless(uninterrupted["history"])  # same numbers
    steps = [cost_axis_steps(d, "eval_by_env_steps") for d in (run_dir, reference_dir)]
    assert steps[0] == steps[1]  # TensorBoard's points by env steps: none lost, none twice
    header = [(d / "eval.csv").read_text().splitlines()[0] for d in (run_dir, reference_dir)]
    assert header[0] == header[1]  # the same columns in the same order
    for key, value in uninterrupted["q_network"].items():
        if isinstance(value, torch.Tensor):
            assert torch.equal(resumed["q_network"][key], value), key
    for key, value in uninterrupted["loss"].items():  # online and target networks
        assert torch.equal(resumed["loss"][key], value), key
    buffers = written(resumed["replay_buffer"]), written(uninterrupted["replay_buffer"])
    assert same(*buffers)  # contents and cursor
    assert same(resumed["optimizer"], uninterrupted["optimizer"])


def timeless(history: list[dict]) -> list[dict]:
    """Evaluation rows without the training's wall time (``wall_s``, different in every run)."""
    return [{k: v for k, v in row.items() if k != "wall_s"} for row in history]


def written(buffer: dict) -> dict:
    """A replay buffer's state with its storage cut to the rows written so far (the rest is
    the uninitialised memory of ``torch.empty``, different in every process)."""
    storage = buffer["_storage"]
    rows = {key: value[: storage["_len"]] for key, value in storage["_storage"].items()}
    return {**buffer, "_storage": {**storage, "_storage": rows}}


def same(a, b) -> bool:
    """Recursive equality of nested dicts, lists, tensors and tensordicts."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor):
        return torch.equal(a, b)
    if hasattr(a, "to_dict") and hasattr(b, "to_dict"):
        return same(a.to_dict(), b.to_dict())
    return a == b


@pytest.mark.parametrize(
    "override, message",
    [
        ("foo=1", "unknown key 'foo'"),
        ("optim.lr=abc", "'optim.lr'"),
        ("collector.frames_per_batch=many", "'collector.frames_per_batch'"),
        ("+loss.bogus=1", "unknown key 'loss.bogus'"),
    ],
)
def test_bad_config_is_a_one_line_error_on_every_rank(tmp_path, override, message):
    started = time.monotonic()
    result = run([str(MPIEXEC), "-n", "2", TRAIN, override], tmp_path, timeout=120)
    assert result.returncode == 2
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: bad config:"), result.stderr
    assert message in lines[0]
    assert time.monotonic() - started < 120
    assert not list(tmp_path.iterdir())  # nothing was run or written


def test_eval_command_tables_a_trained_run(reference, tmp_path):
    """``physicsrl-eval run=<run dir>`` under 2 ranks: table printed once, CSVs (one row per
    seed of the run's ``eval.seeds``, the first 10 held out) and the learning curve in its own
    run directory; the greedy policy's mean is the training's final evaluation (same policy,
    same seeds, another code path)."""
    _, run_dir, _ = reference
    out = tmp_path / "eval"
    arguments = [str(MPIEXEC), "-n", "2", str(BIN / "physicsrl-eval"), f"run={run_dir}"]
    result = run([*arguments, f"hydra.run.dir={out}"], tmp_path, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout.count("greedy DQN") == 1
    assert f"{checkpoint_name(ITERATIONS)} (iteration {ITERATIONS}" in result.stdout
    assert "10 held-out seeds, mean per episode" in result.stdout
    for name in ("eval.csv", "eval_summary.csv", "learning_curve.png"):
        assert (out / name).exists(), name
    assert "no baselines" not in result.stdout  # the run's own seeds: the bars are drawn
    rows = list(csv.DictReader((out / "eval.csv").open()))
    assert [int(row["seed"]) for row in rows] == held_out_seeds(10)
    means = {row["policy"]: row for row in csv.DictReader((out / "eval_summary.csv").open())}
    trained = json.loads((run_dir / "summary.json").read_text())["summary"]["eval"]
    assert trained["iteration"] == ITERATIONS
    assert float(means["greedy DQN"]["return"]) == pytest.approx(trained["return"])


def test_eval_command_rebuilds_a_run_trained_from_python(tmp_path):
    """A Dojo built in Python records its config in its checkpoints. With the task's groups in
    it (``{**load_config(...), ...}``), ``physicsrl-eval run=<log_dir>`` rebuilds the env and
    tables the policy, whose mean is the Dojo's own final evaluation (same policy and seeds,
    another process); without them, one line says how (it was a KeyError's traceback)."""
    from physicsrl.builders import make_q_network
    from physicsrl.coordinated import Coordinator
    from physicsrl.dojo import Dojo
    from physicsrl.envs import load_config, make_env

    groups = load_config("heat", seed=0, overrides=["env.mesh.cells=8"])
    coordinator = Coordinator()
    env = make_env(groups, coordinator)
    settings = {
        "iterations": 2,
        "eval": {"seeds": held_out_seeds(3)},
        "logger": {"progress": False},
    }
    with coordinator:
        for name, config in (("with", {**groups, **settings}), ("without", settings)):
            Dojo(make_q_network(env), env, config, log_dir=tmp_path / name).train()
    final = Dojo(make_q_network(env), env, {**groups, **settings})
    final.load_checkpoint(tmp_path / "with")
    evaluate = [str(BIN / "physicsrl-eval"), "gif=false", "curve=false", "baselines=false"]
    result = run([*evaluate, f"run={tmp_path / 'with'}", "hydra.run.dir=out"], tmp_path)
    assert result.returncode == 0, result.stdout + result.stderr
    [mean] = csv.DictReader((tmp_path / "out" / "eval_summary.csv").open())
    assert float(mean["return"]) == pytest.approx(final.history[-1]["return"])
    result = run([*evaluate, f"run={tmp_path / 'without'}", "hydra.run.dir=out2"], tmp_path)
    assert result.returncode == 2 and len(result.stderr.splitlines()) == 1, result.stderr
    assert "its config names no task (env.name)" in result.stderr


@pytest.mark.parametrize(
    "command, override, message",
    [
        ("train", "agent.lr=inf", "agent.lr must be a finite number > 0, got inf"),
        ("train", "optim.lr=nan", "optim.lr must be a finite number > 0"),
        ("train", "agent.exploration.annealing_frames=-1", "annealing_frames must be an integer"),
        ("train", "loss.n_steps=0", "loss.n_steps must be an integer >= 1, got 0"),
        ("train", "loss.n_steps=-1", "loss.n_steps must be an integer >= 1, got -1"),
        ("train", "checkpoint.keep=-1", "checkpoint.keep must be an integer >= 1, got -1"),
        ("train", "agent.network.hidden=[0]", "agent.network.hidden[0] must be an integer >= 1"),
        ("train", "agent.network.hidden=[64,-4]", "agent.network.hidden[1] must be an integer"),
        ("train", "eval.seeds=[]", "eval.seeds must list at least one seed"),
        ("train", "eval.seeds=[3]", "eval.seeds [3] are also training seeds"),
        ("train", "loss.gamma=0", "loss.gamma must be a finite number > 0 and <= 1, got 0.0"),
        ("train", "buffer.storage=disk", "'buffer.storage'"),
        ("train", "+agent.network.depth=3", "unknown key 'agent.network.depth'"),
        ("eval", "fps=0", "fps must be a finite number > 0, got 0.0"),
        ("eval", "seeds=[]", "seeds must be N >= 1, a non-empty list of seeds >= 0, or null"),
        ("eval", "seeds=0", "seeds must be N >= 1, a non-empty list of seeds >= 0, or null; got 0"),
        ("eval", "run=/etc/passwd", "run=/etc/passwd is not a checkpoint file"),
    ],
)
def test_bad_values_are_refused_by_the_typed_config(capsys, tmp_path, command, override, message):
    """The range checks of physicsrl/config.py and the commands' own checks, as they run them
    before any work: exit status 2 and one line naming the key."""
    from torchrl.checkpoint import Checkpoint

    from physicsrl.cli import eval as evaluate
    from physicsrl.cli import train
    from physicsrl.cli.command import validate_or_exit

    check = {"train": train.check_task, "eval": evaluate.check}[command]
    Checkpoint(counters={}).save(tmp_path / "ckpt.torchrl", format="archive")
    overrides = [override] if command == "train" else [f"run={tmp_path / 'ckpt.torchrl'}", override]
    with pytest.raises(SystemExit) as exit_:
        validate_or_exit(command, overrides, check)
    assert exit_.value.code == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and message in lines[0], lines


def test_defaults_are_defined_once():
    """The composed train config equals the typed config's defaults (the YAML sets none but
    the groups)."""
    from physicsrl.cli.command import compose
    from physicsrl.config import TrainConfig, as_dict

    composed = as_dict(compose("train", []))
    defaults = as_dict(TrainConfig())
    for group in ("env", "observation", "reward"):  # the task's groups: their own YAML
        composed.pop(group), defaults.pop(group)
    assert composed == defaults


def test_an_env_brings_its_observation_and_reward_unless_chosen():
    """``env=NAME`` composes with the observation and reward of its YAML's defaults list, in a
    single run and in each job of a sweep; the command line's choice wins."""
    from physicsrl.cli.command import compose, sweep_jobs

    def chosen(*overrides):
        cfg = compose("train", list(overrides))
        return cfg.observation.name, cfg.reward.name

    assert chosen() == ("quadrants", "heat_stop")
    assert chosen("env=ms") == chosen("env=ms_resolved") == ("catheter", "atp")
    assert chosen("env=ms", "observation=quadrants") == ("quadrants", "atp")
    jobs = sweep_jobs(["env=heat,ms"])
    assert [chosen(*job) for job in jobs] == [("quadrants", "heat_stop"), ("catheter", "atp")]


def test_eval_writes_the_fields_of_an_episode_for_paraview(tmp_path):
    """``physicsrl-eval fields=true`` under 2 ranks (two environments, and one on both ranks),
    on the heat task with a policy that always advances (3 decisions of 0.1): the VTX series
    read back holds u on all 81 nodes at times 0, 0.1, 0.2, 0.3; at t = 0 u is the drawn
    integer level, later u_D = 1 on the boundary,
    and its distance from u_D decays at every step (implicit Euler); the PNG is rendered from
    the data read back; the episode's GIF has one frame per decision."""
    import numpy as np
    from torchrl.checkpoint import Checkpoint

    from physicsrl.checkpoint import State
    from physicsrl.fem.output import read_series  # dolfinx before adios2 (their libraries)

    pytest.importorskip("adios2", reason="reading the series back needs the fields extra")

    small = ["env.mesh.cells=8", "env.max_steps=3", "eval.seeds=[1000000000]"]
    quick = ["iterations=1", "collector.frames_per_batch=5", "optim.learning_starts=5"]
    off = ["eval.every=0", "eval.baselines=false", "logger.tensorboard=false"]
    arguments = [TRAIN, *small, *quick, *off, "logger.progress=false"]
    trained = run([*arguments, f"hydra.run.dir={tmp_path / 'run'}"], tmp_path)
    assert trained.returncode == 0, trained.stderr
    state = final_state(tmp_path / "run")
    *_, weight, bias = state["q_network"]  # the last layer: Q = (0, 1), always advance
    state["q_network"][weight].zero_()
    state["q_network"][bias].copy_(torch.tensor([0.0, 1.0]))
    advance = tmp_path / "advance.torchrl"
    Checkpoint(
        format="archive",
        q_network=State(lambda: state["q_network"], None),
        counters=State(lambda: state["counters"], None),
        extra=state["extra"],
    ).save(advance)
    evaluate = [str(MPIEXEC), "-n", "2", str(BIN / "physicsrl-eval"), f"run={advance}"]
    options = ["seeds=1", "baselines=false", "curve=false", "fields=true"]  # and the GIF
    for per_env in (1, 2):  # two environments; one on both ranks (its mesh split)
        out = tmp_path / f"eval_{per_env}"
        layout = f"mpi.ranks_per_env={per_env}"
        result = run([*evaluate, *options, layout, f"hydra.run.dir={out}"], tmp_path)
        assert result.returncode == 0, result.stdout + result.stderr
        assert result.stdout.count("fields of seed 1000000000 (u at 4 times)") == 1, result.stdout
        series = read_series(out / "fields.bp")
        assert np.allclose(series.times, [0.0, 0.1, 0.2, 0.3], atol=1e-12)
        u = series.values["u"]
        assert u.shape == (4, 81) and len(np.unique(series.points, axis=0)) == 81
        level = np.unique(u[0])
        assert len(level) == 1 and level[0] == round(level[0]) and level[0] != 1.0
        boundary = np.abs(series.points[:, :2]).max(axis=1) > 2 - 1e-9
        assert boundary.sum() == 32 and np.all(u[1:, boundary] == 1.0)
        distance = np.sqrt(((u - 1.0) ** 2).mean(axis=1))
        assert distance[0] > 0 and np.all(np.diff(distance) < 0), distance
        assert (out / "fields.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        # the GIF of the episode: the field after the reset and after each decision but the last
        # (the rollout ends there)
        assert "episode of seed 1000000000: actions [1, 1, 1]" in result.stdout, result.stdout
        frames = imageio.mimread(out / "episode.gif")
        assert len(frames) == 3 and frames[0].ndim == 3 and frames[0].shape[-1] == 3


def test_a_non_finite_loss_stops_training_with_one_line_and_keeps_the_last_checkpoint(tmp_path):
    """A learning rate of 1e30 (finite, so accepted) blows the weights up at the second update
    (iteration 4, the first with learning_starts frames): under 2 ranks every rank exits
    non-zero, the leader prints one line naming the iteration and what became non-finite, and
    the checkpoint of iteration 2 stays the newest, with finite weights."""
    from physicsrl.checkpoint import read
    from physicsrl.run_directory import checkpoint_path

    run_dir = tmp_path / "run"
    result = run(command(run_dir, "optim.lr=1e30", "checkpoint.every=2"), tmp_path)
    assert result.returncode == 1, result.stdout + result.stderr
    errors = [line for line in result.stderr.splitlines() if "error" in line.lower()]
    assert errors == [
        "error: iteration 4, update 2: the loss became nan; training stopped "
        "(the checkpoint of iteration 2 is kept)"
    ], result.stderr
    assert "Traceback" not in result.stderr
    latest = checkpoint_path(str(run_dir))
    assert latest.name == "ckpt-000000000002.torchrl"
    loss = read(latest, ["loss"])["loss"]
    assert all(torch.isfinite(v).all() for v in loss.values() if v.is_floating_point())


def test_a_time_step_on_which_every_reset_diverges_stops_training_with_one_line(tmp_path):
    """dt = 0.2 on the ATP task: forward Euler blows the stimulated cells up during the reset's
    stimulus (current 50 for 2 time units), so every reset draw comes out non-finite; under 2
    ranks every rank exits with status 1 and the leader prints one line, no traceback."""
    arguments = [str(MPIEXEC), "-n", "2", TRAIN, "env=ms", *SMALL_ATP, "env.model.dt=0.2"]
    result = run([*arguments, "iterations=1", f"hydra.run.dir={tmp_path / 'run'}"], tmp_path)
    assert result.returncode == 1, result.stdout + result.stderr
    errors = [line for line in result.stderr.splitlines() if line.startswith("error")]
    assert errors == [
        "error: 10 reset draws in a row gave non-finite states: the time step is likely too "
        "large for the scheme (lower env.model.dt or env.dt)"
    ], result.stderr
    assert "Traceback" not in result.stderr


def test_a_rank_that_only_serves_the_simulator_imports_no_torch(tmp_path):
    """One heat environment on 2 ranks (``mpi.ranks_per_env=2``), started by MPMD ``mpiexec``
    so that rank 1 alone reports its imports (``PYTHONPROFILEIMPORTTIME``): the run trains and
    prints its summary, then ``physicsrl-eval`` tables its policy, and in both rank 1, which
    serves the leader's simulator calls, imported the task and the layout but never torch,
    TorchRL or tensordict (it builds the task alone; the leader imports them through the
    ``import`` statements that this report lists)."""
    run_dir = tmp_path / "run"
    train = [TRAIN, "iterations=2", "collector.frames_per_batch=8", "eval.baselines=false"]
    train += ["logger.progress=false", f"hydra.run.dir={run_dir}"]
    evaluate = [str(BIN / "physicsrl-eval"), f"run={run_dir}", "gif=false", "curve=false"]
    evaluate += [f"hydra.run.dir={tmp_path / 'eval'}"]
    for arguments in (train, evaluate):
        arguments = [*arguments, "mpi.ranks_per_env=2"]
        traced = ["-env", "PYTHONPROFILEIMPORTTIME", "1"]
        command = [str(MPIEXEC), "-n", "1", *arguments, ":", "-n", "1", *traced, *arguments]
        result = run(command, tmp_path)
        assert result.returncode == 0, result.stdout + result.stderr
        assert result.stdout.count("held-out seeds, mean per episode") == 1, result.stdout
        imported = {line.split("|")[-1].strip() for line in result.stderr.splitlines()}
        assert {"physicsrl.envs.heat", "physicsrl.envs.layout"} <= imported  # its job ran
        assert not imported & {"torch", "torchrl", "tensordict"}, arguments[0]
