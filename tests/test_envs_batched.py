"""The batched ATP environment: TorchRL batch semantics, partial resets, determinism, and
equality with the PETSc-backed task on the same draws."""

from __future__ import annotations

import physicsrl.fem  # noqa: F401  (first: loads the MPI library that dolfinx links to)

# isort: split

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from physicsrl.coordinated import Coordinator
from physicsrl.envs import load_config, make_env
from physicsrl.envs.batched import make_batched_env

# A small, short ATP task: 16 x 16 cells, induction 9 time units, decisions of 3.
SMALL = (
    "env.mesh.cells=16",
    "env.reset.stimulus_time=3.0",
    "env.reset.rest_time=6.0",
    "env.decision_interval=3.0",
    "env.shock.duration=1.5",
    "env.max_decisions=2",
    "env.extra_waits=2",
    "env.success_threshold=-1.0",  # never: episodes run to failure with extra waits
)


def batched(replicas, seed=3, extra=()):
    cfg = load_config("ms", "catheter", "atp", [*SMALL, *extra], seed=seed)
    cfg["env"]["replicas"] = replicas
    cfg["env"]["model"]["backend"] = "torch"
    return make_batched_env(cfg)


def test_check_env_specs_and_batch_shapes():
    env = batched(3)
    check_env_specs(env)
    td = env.rollout(3, break_when_any_done=False)
    assert td.batch_size == torch.Size([3, 3])
    assert td["next", "observation"].shape == (3, 3, 20)
    # decision 2 of 2 without success: failure after the extra waits, every replica
    assert td["next", "terminated"][:, 1].all() and not td["next", "terminated"][:, 0].any()


def test_partial_reset_and_determinism():
    """Replica i's episodes depend only on (seed, i, episode count): replicas 0 and 1 of a
    batch of 2 and of a batch of 3 start alike; a reset of replica 1 alone starts its second
    episode (a new draw) and leaves replica 0's state untouched."""
    two, three = batched(2), batched(3)
    first_two, first_three = two.reset(), three.reset()
    np.testing.assert_array_equal(
        first_two["observation"].numpy(), first_three["observation"][:2].numpy()
    )
    action = TensorDict({"action": torch.tensor([1, 0])}, batch_size=[2])
    two.step(action)
    u0 = two.u[0].clone()
    reset = two.reset(TensorDict({"_reset": torch.tensor([[False], [True]])}, batch_size=[2]))
    assert torch.equal(two.u[0], u0)
    assert two.episodes.tolist() == [1, 2]
    assert two.draw(1, 1) != two.draw(1, 0)
    fresh = batched(2)
    fresh.episodes[1] = 1  # as if replica 1 had finished one episode
    fresh._start([1])
    np.testing.assert_array_equal(
        reset["observation"][1].numpy(), fresh._integrals(fresh.u)[1, 1:].astype(np.float32)
    )


@pytest.mark.parametrize("scheme", ["implicit", "explicit"])
def test_replica_equals_the_petsc_task_on_the_same_draws(scheme):
    """Each replica's observations and rewards over an episode (shock, then wait, then the
    extra waits) equal those of the DOLFINx/PETSc task reset with the same draw, to the
    float32 rounding of the observation (relative 1e-5) plus an absolute 1e-8 for the implicit
    scheme (both CG solvers stop at rtol 1e-10; readings are up to 1e-2) and 1e-12 for the
    explicit one (the same arithmetic in another order)."""
    extra = (f"env.model.scheme={scheme}",)
    env = batched(2, extra=extra)
    reference = make_env(
        load_config("ms", "catheter", "atp", [*SMALL, *extra], seed=0), Coordinator()
    )
    start = env.reset()
    actions = ([1, 0], [0, 1])
    steps = [env.step(TensorDict({"action": torch.tensor(a)}, batch_size=[2])) for a in actions]
    tolerance = {"rtol": 1e-5, "atol": 1e-8 if scheme == "implicit" else 1e-12}
    with reference.task.coordinator:
        for i in range(2):
            expected = reference.task.reset(*env.draw(i, 0))
            np.testing.assert_allclose(start["observation"][i], expected, **tolerance)
            for action, td in zip(actions, steps, strict=True):
                t = reference.task.step(action[i])
                np.testing.assert_allclose(td["next", "observation"][i], t.observation, **tolerance)
                assert td["next", "reward"][i, 0] == pytest.approx(
                    reference.reward_fn(t.events), rel=1e-6
                )
                assert bool(td["next", "terminated"][i]) == t.terminated


def test_bad_settings_are_named():
    cfg = load_config("ms", "catheter", "atp", SMALL)
    cfg["env"]["model"]["backend"] = "torch"
    cfg["env"]["model"]["device"] = "tpu"
    with pytest.raises(ValueError, match="env.model.device must be one of cpu, cuda, got 'tpu'"):
        make_batched_env(cfg)
    cfg["env"]["model"]["device"] = "cpu"
    cfg["env"]["replicas"] = 0
    with pytest.raises(ValueError, match="env.replicas must be an integer >= 1, got 0"):
        make_batched_env(cfg)
