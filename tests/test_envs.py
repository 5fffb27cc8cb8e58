"""The heat task, the factory and its configs, rewards (issue 4)."""

import re
from pathlib import Path

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from physicsrl.coordinated import Coordinator
from physicsrl.envs import ATPReward, HeatStop, exact_optimum, load_config, make_env
from physicsrl.envs.baselines import Constant, HeatOptimal
from physicsrl.envs.registry import shipped_option
from physicsrl.evaluation import run_episode
from physicsrl.fem.heat import transient_integral
from physicsrl.tables import mean_metrics

SMALL_HEAT = ["env.mesh.cells=16"]
SHIPPED = Path(__file__).resolve().parents[1] / "conf"


def heat_env(*overrides, seed=0):
    return make_env(
        load_config("heat", overrides=[*SMALL_HEAT, *overrides], seed=seed),
        Coordinator(),
    )


def act(env, action):
    return env.step(TensorDict({"action": torch.tensor(action)}, batch_size=[]))["next"]


def test_heat_specs():
    env = heat_env()
    with env.task.coordinator:
        check_env_specs(env)


def test_default_heat_config_is_the_reference_task():
    """The defaults are the figures of tasks.md: 50 x 50 P1 on [-2, 2]^2 ... and 4 quadrants."""
    env = make_env(load_config(seed=0), Coordinator())
    c = env.task.config
    assert (c.mesh.cells, c.mesh.extent, c.mesh.cell_type) == (50, 2.0, "triangle")
    assert (c.dt, c.boundary_value, c.levels, c.advance_time, c.max_steps) == (
        0.01,
        1.0,
        (-5, 5),
        0.1,
        10,
    )
    assert env.reward_fn == HeatStop(0.1, 1.0)
    assert env.observation_spec["observation"].shape == (4,)


def test_heat_rewards_by_hand():
    """Stop at once: 16 x level (u = level on the area 16). Advancing: -0.1 each, the 10th
    also gets the integral; the episode ends after 10 steps; the quadrants sum to the integral."""
    env = heat_env()
    with env.task.coordinator:
        for level in (-5, 3):
            obs = env.task.reset(level)
            np.testing.assert_allclose(obs, 4 * level, rtol=1e-12)
            out = act(env, 0)
            assert out["reward"].item() == pytest.approx(16 * level, rel=1e-6)
            assert out["done"].item() and out["terminated"].item() and not out["truncated"].item()

        env.task.reset(-5)
        for k in range(1, 11):
            out = act(env, 1)
            assert int(out["step"]) == k
            if k < 10:
                assert out["reward"].item() == pytest.approx(-0.1) and not out["done"].item()
        integral = float(out["observation"].double().sum())
        assert out["reward"].item() == pytest.approx(-0.1 + integral, rel=1e-5)
        assert out["terminated"].item() and -80 < integral < 16  # warmed towards u_D = 1


def test_heat_exact_optimum_matches_brute_force_and_beats_baselines():
    env = heat_env("env.max_steps=5", seed=0)
    with env.task.coordinator:
        optimum = exact_optimum(env)
        # Brute force: every level, every stopping time, through the environment's steps.
        totals = np.zeros((len(optimum.levels), 6))
        for i, level in enumerate(optimum.levels):
            for k in range(6):
                env.task.reset(int(level))
                for j in range(k + (k < 5)):
                    out = act(env, int(j < k))
                    totals[i, k] += out["reward"].item()
                assert out["done"].item()
        np.testing.assert_allclose(optimum.returns, totals, rtol=1e-5, atol=1e-5)
        np.testing.assert_array_equal(optimum.best_stop, totals.argmax(1))
        assert optimum.mean == pytest.approx(totals.max(1).mean(), rel=1e-5)
        # Cold levels (below u_D = 1) warm up; hot ones stop at once.
        assert optimum.best_stop[optimum.levels >= 2].max() == 0
        assert optimum.best_stop[optimum.levels <= -1].min() > 0
        # The optimal policy attains each level's optimum and beats the other baselines.
        seeds = range(30)
        means = {
            name: mean_metrics(run_episode(env, policy, s) for s in seeds)["return"]
            for name, policy in [
                ("stop", Constant(0)),
                ("never", Constant(1)),
                ("optimal", HeatOptimal(optimum)),
            ]
        }
        levels = [int(np.random.default_rng(s).integers(-5, 6)) for s in seeds]
        expected = np.mean([optimum.best_return[level + 5] for level in levels])
        assert means["optimal"] == pytest.approx(expected, rel=1e-5)
        assert means["optimal"] >= max(means["stop"], means["never"])


def test_heat_optimum_under_refinement_is_the_exact_series_one():
    """The heat task's results at two resolutions, against the exact solution: the integral
    of u at the k-th decision is 16 u_D + (level - u_D) S(t_k)^2 (physicsrl.fem.heat), which
    gives each level's optimal return. At the default (50 x 50, dt = 0.01) and refined
    (100 x 100, dt = 0.0025) the exact optimum stops where the series' does, and its mean
    return is within 0.05 of the series', the refined one at least 3x closer."""
    times = 0.1 * np.arange(11)
    transient = np.concatenate([[16.0], transient_integral(times[1:], 2.0)])
    levels = np.arange(-5, 6)
    returns = 16 + (levels[:, None] - 1) * transient - 0.1 * np.arange(11)
    errors = []
    for overrides in ([], ["env.mesh.cells=100", "env.dt=0.0025"]):
        env = make_env(load_config("heat", overrides=overrides, seed=0), Coordinator())
        with env.task.coordinator:
            optimum = exact_optimum(env)
        np.testing.assert_array_equal(optimum.best_stop, returns.argmax(axis=1))
        errors.append(abs(optimum.mean - returns.max(axis=1).mean()))
    assert errors[0] < 0.05 and errors[0] / errors[1] > 3


def test_same_seed_same_episode():
    env = heat_env(seed=5)
    with env.task.coordinator:
        first = [env.reset()["observation"].sum().item() for _ in range(5)]
        env.set_seed(5)
        assert [env.reset()["observation"].sum().item() for _ in range(5)] == first
        assert len(set(first)) > 1


@pytest.mark.parametrize("seed", [-1, 1.5, "5"])
def test_a_seed_that_is_not_an_integer_from_0_is_refused_naming_it(seed):
    """``env.set_seed`` of a single env and of a batch's members: numpy said ``expected
    non-negative integer`` (or SeedSequence's TypeError), and a batch truncated 1.5 to 1."""
    from physicsrl.envs.members import member_seed

    message = f"^{re.escape(f'seed must be an integer >= 0, got {seed!r}')}$"
    with pytest.raises(ValueError, match=message):
        heat_env().set_seed(seed)
    with pytest.raises(ValueError, match=message):
        member_seed(seed, 1)
    assert member_seed(None, 1) is None and member_seed(np.int64(3), 0) == 3


def test_atp_reward_by_hand():
    r = ATPReward()
    assert r({"shock": True, "success": False, "failure": False, "steps": 3}) == -10
    assert r({"shock": False, "success": True, "failure": False, "steps": 4}) == 496
    assert r({"shock": True, "success": True, "failure": False, "steps": 15 + 7}) == -10 + 500 - 22
    assert r({"shock": False, "success": False, "failure": True, "steps": 35}) == 0
    assert (
        ATPReward(failure_reward=-50)(
            {"shock": True, "success": False, "failure": True, "steps": 35}
        )
        == -60
    )
    h = HeatStop()
    assert h({"advanced": True, "ended": False, "integral": 7.0}) == -0.1
    assert h({"advanced": True, "ended": True, "integral": 7.0}) == pytest.approx(6.9)
    assert h({"advanced": False, "ended": True, "integral": -3.0}) == -3.0


@pytest.mark.parametrize(
    "groups, override, message",
    [
        (("heat", "quadrants", "heat_stop"), "env.dt=-1", "env.dt"),
        (("heat", "quadrants", "heat_stop"), "env.advance_time=0.015", "env.advance_time"),
        (("heat", "quadrants", "heat_stop"), "env.levels=[3,1]", "env.levels"),
        (("heat", "quadrants", "heat_stop"), "env.mesh.cell_type=hexagon", "env.mesh.cell_type"),
        (("heat", "quadrants", "heat_stop"), "env.mesh.cells=0", "env.mesh.cells"),
        (("heat", "quadrants", "heat_stop"), "env.colour=red", "env.colour"),
        (("heat", "quadrants", "heat_stop"), "env.name=chess", "env.name"),
        (("heat", "quadrants", "heat_stop"), "reward.step_cost=abc", "reward.step_cost"),
        (("heat", "quadrants", "atp"), "seed=0", "reward.name"),
        (("heat", "catheter", "heat_stop"), "seed=0", "observation.distances"),
        (("ms", "catheter", "atp"), "observation.mu=0", "observation.mu"),
        (("ms", "catheter", "atp"), "observation.distances=[]", "observation.distances"),
        (("ms", "catheter", "atp"), "env.model.tau_in=-0.3", "env.model.tau_in"),
        (("ms", "catheter", "atp"), "env.shock.duration=60", "env.shock.duration"),
        (("ms", "catheter", "atp"), "env.reset.half_width=[4,2]", "env.reset.half_width"),
        (("ms", "catheter", "atp"), "env.max_decisions=0", "env.max_decisions"),
        (("ms", "catheter", "atp"), "env.decision_interval=0.01", "env.decision_interval"),
        (("ms", "catheter", "atp"), "env.cross_field.s1_time=1", "env.cross_field.s1_time"),
        (("heat", "quadrants", "heat_stop"), "envs.mesh.cells=8", "'envs' is not one of"),
        (("heat", "quadrants", "heat_stop"), "seed=-3", "seed must be an integer >= 0, got -3"),
        # refused before the mesh is made (else: std::bad_alloc, or swapping for minutes)
        (("heat", "quadrants", "heat_stop"), "env.mesh.cells=100000", "cells=100000 would need"),
        (("ms", "catheter", "atp"), "max_memory_gb=0.001", "more than max_memory_gb=0.001"),
    ],
)
def test_bad_config_values_raise_naming_the_key(groups, override, message):
    with pytest.raises(ValueError, match=message.replace(".", r"\.")):
        make_env(load_config(*groups, [override]), Coordinator())


def test_make_env_refuses_torch_replicas_too_large_for_memory():
    """The torch replicas' state (48 bytes per replica and dof, on one rank) is estimated before
    any is made: 100,000 replicas of the 60 x 60 grid (3,721 dofs) are 17.9 GB."""
    overrides = ["env.model.backend=torch", "env.replicas=100000"]
    with pytest.raises(ValueError, match=r"^env\.replicas=100000 would need about 17\.9 GB"):
        make_env(load_config("ms", overrides=overrides), Coordinator())


@pytest.mark.parametrize(
    "overrides, message",
    [
        ("env.dt=0.02", "overrides must be a list of key=value strings, got 'env.dt=0.02'"),
        (["env.dt"], "overrides: 'env.dt' is not key=value with a dotted key"),
        (["env..dt=1"], "overrides: 'env..dt=1' is not key=value with a dotted key"),
        (["env.dt=[1"], "overrides: cannot parse 'env.dt=[1'"),
    ],
)
def test_load_config_refuses_an_override_that_is_not_key_value(overrides, message):
    """Each was taken: a string as its characters, ``env.dt`` as ``env.dt=None``, ``env..dt``
    as a key named '', or the YAML parser's error of several lines."""
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        load_config("heat", overrides=overrides)


@pytest.mark.parametrize("group", ["env", "observation", "reward"])
def test_load_config_names_a_groups_options_when_one_does_not_exist(group):
    options = ", ".join(sorted(p.stem for p in (SHIPPED / group).glob("*.yaml")))
    with pytest.raises(
        ValueError, match=rf"^{group}=nosuch: no such option \(choose one of {options}\)$"
    ):
        load_config(**{"env": "heat", group: "nosuch"})


@pytest.mark.parametrize("option", sorted(p.stem for p in (SHIPPED / "env").glob("*.yaml")))
def test_load_config_is_the_groups_hydra_composes(option):
    """``load_config(option)`` (no Hydra) gives every shipped env exactly the groups
    ``physicsrl-train env=<option>`` composes: the observation and reward its YAML chooses, and a
    variant's base (``ms_resolved`` on ``ms``)."""
    from physicsrl.checks import plain
    from physicsrl.cli.command import compose

    composed = plain(compose("train", [f"env={option}"]))
    groups = ("env", "observation", "reward")
    loaded = plain(load_config(option))
    assert {g: loaded[g] for g in groups} == {g: composed[g] for g in groups}


@pytest.mark.parametrize(
    "group, option",
    [("env", "heat"), ("env", "ms")]
    + [(g, p.stem) for g in ("observation", "reward") for p in (SHIPPED / g).glob("*.yaml")],
)
def test_a_shipped_base_yaml_states_its_classs_defaults(group, option):
    """The YAML of a task, observation or reward (not a variant of another, such as
    ``ms_resolved``) sets each of its settings to the default of its dataclass: the settings that
    a Python user gets without the YAML, and that an older run's record lacks, are the shipped
    ones."""
    from physicsrl.checks import build
    from physicsrl.envs import OBSERVATIONS, REWARDS, TASKS

    registry = {"env": TASKS, "observation": OBSERVATIONS, "reward": REWARDS}[group]
    found, settings = registry.lookup(shipped_option(group, option))
    cls = found.Config if group == "env" else found
    assert build(cls, settings, group) == cls()
