"""The ATP task, the catheter, stimulus regions, snapshot resets and baselines (issue 4)."""

import json
import math
import subprocess
import sys
from dataclasses import dataclass

import dolfinx_solver  # noqa: F401 (loads MPI before dolfinx)
import numpy as np
import pytest
import torch
import ufl
from conftest import SMALL_ATP, on_one_and_two_ranks
from dolfinx import fem, mesh
from mpi4py import MPI
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from physicsrl.config import held_out_seeds
from physicsrl.coordinated import Coordinator
from physicsrl.envs import ATPReward, Catheter, Observation, load_config, make_env
from physicsrl.envs.baselines import (
    Constant,
    EveryKth,
    Schedule,
    atp_baselines,
    best_single_shock,
)
from physicsrl.envs.members import member_seed
from physicsrl.envs.snapshots import SnapshotCache
from physicsrl.evaluation import run_episode
from physicsrl.fem.errors import InvalidValue
from physicsrl.fem.integrals import WeightedIntegrals, form_rows


def atp_env(*overrides, seed=0):
    config = load_config("ms", overrides=[*SMALL_ATP, *overrides], seed=seed)
    return make_env(config, Coordinator())


def act(env, action):
    return env.step(TensorDict({"action": torch.tensor(action)}, batch_size=[]))["next"]


def integral(env):
    return env.task.integrals(env.task.simulator.u_n())[0]


def test_atp_specs():
    env = atp_env()
    with env.task.coordinator:
        check_env_specs(env)


def test_default_atp_config_is_the_reference_task():
    cfg = load_config("ms")
    assert cfg.env.mesh.cells == 60 and cfg.env.mesh.extent == 50 and cfg.env.model.dt == 0.03
    assert (cfg.env.decision_interval, cfg.env.max_decisions, cfg.env.extra_waits) == (50, 15, 20)
    assert list(cfg.env.shock.centre) == [0, 25] and cfg.env.shock.radius == 25
    assert (cfg.env.reset.stimulus_time, cfg.env.reset.rest_time) == (15, 85)
    assert cfg.observation.mu == 33 and list(cfg.observation.distances) == [37.5, 32.5, 17.5, 12.5]
    assert (cfg.reward.shock_cost, cfg.reward.success_reward) == (10, 500)


def check_rest_range(fixed, ranged, low: float, high: float, before_rest) -> None:
    """``ranged`` (``rest_time=[low, high]``) draws the rest after its other draws, which stay
    those of ``fixed`` (``rest_time=low``: the generator's stream is unchanged); the agent
    starts at model time ``before_rest(draws)`` + rest, with another field than after a rest
    of ``low``."""
    draws = {
        name: [env.task.draw(np.random.default_rng(s)) for s in range(20)]
        for name, env in (("fixed", fixed), ("ranged", ranged))
    }
    assert all(d[3] == low for d in draws["fixed"])
    assert [d[:3] for d in draws["ranged"]] == [d[:3] for d in draws["fixed"]]
    rests = np.array([d[3] for d in draws["ranged"]])
    assert low <= rests.min() and rests.max() <= high and np.ptp(rests) > (high - low) / 2
    task, first = ranged.task, draws["ranged"][0]
    with task.coordinator:
        task.reset(*first)
        late = task.simulator.u_n().x.array.copy()
        assert task.simulator.t == pytest.approx(before_rest(first) + first[3], abs=0.03)
        task.reset(*first[:3], low)
        assert task.simulator.t == pytest.approx(before_rest(first) + low, abs=0.03)
        assert np.abs(task.simulator.u_n().x.array - late).max() > 0.01


def test_a_rest_range_starts_the_agent_at_a_drawn_time():
    """``reset.rest_time=[3, 13]``: the rest after the stimulus (2 time units) is drawn."""
    fixed, ranged = atp_env(), atp_env("env.reset.rest_time=[3,13]")
    check_rest_range(fixed, ranged, 3.0, 13.0, lambda draws: 2.0)


def test_atp_failure_and_success_by_hand():
    # Never succeeding: -10 per shock, 0 per wait; terminated (failure) at the 3rd decision.
    env = atp_env("env.success_threshold=-1e30")
    with env.task.coordinator:
        env.reset()
        rewards = [act(env, a) for a in (1, 0, 1)]
        assert [r["reward"].item() for r in rewards] == [-10, 0, -10]
        assert [r["terminated"].item() for r in rewards] == [False, False, True]
        assert not any(r["truncated"].item() or r["success"].item() for r in rewards)
        assert [int(r["step"]) for r in rewards] == [1, 2, 3]

    # Integrals after 5 waits, to pick a threshold first crossed during the extra waits.
    long = atp_env("env.max_decisions=5", "env.extra_waits=0", "env.success_threshold=-1e30")
    with long.task.coordinator:
        long.reset()
        integrals = []
        for _ in range(5):
            act(long, 0)
            integrals.append(integral(long))
    threshold = float(min(integrals[3:]) + 1e-9 * abs(min(integrals[3:])))
    first = next(j for j, value in enumerate(integrals) if value < threshold) + 1

    env = atp_env(f"env.success_threshold={threshold!r}")
    with env.task.coordinator:
        env.reset()
        for k in range(1, 4):
            out = act(env, 0)
            if k == first or k == 3:
                break
        assert out["terminated"].item() and out["success"].item()
        # 500 minus the decisions and extra waits taken (the extra waits are in the last step).
        assert out["reward"].item() == 500 - first


@pytest.fixture(scope="module")
def diverged_runs():
    """``envs_diverged.py`` on 1 and on 2 ranks (started together), by ranks."""
    return on_one_and_two_ranks("tests/mpi_scripts/envs_diverged.py")


@pytest.mark.parametrize("ranks", [1, 2])
def test_divergence_truncates_and_training_goes_on(diverged_runs, ranks):
    """dt = 0.1 with the shock's current blows up: the step ends the episode as truncated with
    "diverged" set, and the next reset starts a normal episode; on 2 ranks the follower, which
    raised the same error in the parallel call, goes on serving (the 1- and 2-rank jobs run
    at the same time)."""
    result = diverged_runs[ranks]
    line = next(line for line in result.stdout.splitlines() if line.startswith("RESULT "))
    steps = json.loads(line.removeprefix("RESULT "))
    shock = {"diverged": True, "truncated": True, "terminated": False, "done": True}
    assert steps["shock"] == {**shock, "reward": -10.0}
    assert steps["reset"] == dict.fromkeys(shock, False) | {"finite": True}
    assert not steps["wait"]["diverged"]


def test_catheter_positions():
    positions = Catheter().positions()
    assert positions.shape == (20, 2)
    np.testing.assert_allclose(positions[0], [0, 37.5], atol=1e-12)  # spline 0 points up
    angle = math.pi / 2 - 2 * math.pi / 5
    np.testing.assert_allclose(positions[4], 37.5 * np.array([math.cos(angle), math.sin(angle)]))
    np.testing.assert_allclose(np.hypot(*positions.T), np.tile([37.5, 32.5, 17.5, 12.5], 5))


@pytest.mark.parametrize("cell_type", ["quadrilateral", "triangle"])
def test_catheter_is_mesh_independent(cell_type):
    """Same smooth field on 60 x 60 and 240 x 240: the readings agree within 5% (in fact
    ~0.2%); for a linear field they equal 2 pi / mu^2 u(electrode) to rounding."""
    catheter = Catheter()
    readings = {}
    for n in (60, 240):
        domain = mesh.create_rectangle(
            MPI.COMM_WORLD, [[-50, -50], [50, 50]], [n, n], getattr(mesh.CellType, cell_type)
        )
        V = fem.functionspace(domain, ("Lagrange", 1))
        integrals = WeightedIntegrals(V, catheter.rows(V))
        u = fem.Function(V)
        u.interpolate(lambda x: 1 + 0.5 * np.sin(x[0] / 10) * np.cos(x[1] / 13))
        readings[n] = integrals(u)
        u.interpolate(lambda x: 2 + 0.01 * x[0] - 0.02 * x[1])
        p = catheter.positions()
        np.testing.assert_allclose(
            integrals(u), 2 * np.pi / 33**2 * (2 + 0.01 * p[:, 0] - 0.02 * p[:, 1]), rtol=1e-10
        )
    np.testing.assert_allclose(readings[60], readings[240], rtol=0.05)
    np.testing.assert_allclose(readings[60], readings[240], rtol=0.005)


def test_an_observation_reads_u_unless_told_and_its_subclass_may_require_fields():
    @dataclass(frozen=True)
    class Probe(Observation):
        point: tuple[float, float]  # no default: the base's variable is keyword-only

    assert Probe((1.0, 2.0)).variable == "u" == Catheter().variable
    assert Probe((1.0, 2.0), variable="w").variable == "w"


def test_integrals_of_two_variables_are_one_reduction_of_each_own_rows():
    """Rows that weigh u and rows that weigh w, in one call: for linear u and w the catheter
    reads 2 pi / mu^2 times each at the electrodes, and the domain's integral of u is exact."""
    domain = mesh.create_rectangle(MPI.COMM_WORLD, [[-50, -50], [50, 50]], [30, 30])
    V = fem.functionspace(domain, ("Lagrange", 1))
    catheter = Catheter()
    rows = np.vstack([form_rows(V, [1.0]), catheter.rows(V), catheter.rows(V)])
    integrals = WeightedIntegrals(V, rows, [0] * 21 + [1] * 20)
    u, w = fem.Function(V), fem.Function(V)
    u.interpolate(lambda x: 2 + 0.01 * x[0] - 0.02 * x[1])
    w.interpolate(lambda x: 0.5 - 0.003 * x[0] + 0.004 * x[1])
    values = integrals(u, w)
    x, y = catheter.positions().T
    kernel = 2 * np.pi / 33**2
    assert values[0] == pytest.approx(2 * 100**2, rel=1e-12)
    np.testing.assert_allclose(values[1:21], kernel * (2 + 0.01 * x - 0.02 * y), rtol=1e-10)
    np.testing.assert_allclose(values[21:], kernel * (0.5 - 0.003 * x + 0.004 * y), rtol=1e-10)
    with pytest.raises(InvalidValue, match="expected 2 functions, got 1"):
        integrals(u)


def test_shock_region_is_a_cell_average_of_the_disk():
    env = atp_env("env.mesh.cells=60")
    shock = env.task.shock
    area = fem.assemble_scalar(fem.form(shock * ufl.dx)) / 50.0
    assert area == pytest.approx(math.pi * 25**2, rel=0.01)
    assert shock.x.array.min() >= 0 and shock.x.array.max() == pytest.approx(50)


def test_snapshot_reset_is_identical_and_solves_no_step(tmp_path):
    """A reset to a stored draw restores the induced state bit for bit (and the same future)
    without a time step: the simulator's phase timings do not move (not a timed test: an
    induction's 568 steps move them)."""
    overrides = [
        "env.mesh.cells=60",
        "env.reset.rest_time=15",
        f"env.snapshots.directory={tmp_path}",
    ]
    env = atp_env(*overrides)
    task = env.task
    draws = [(1.5, 3.0, 20.0, 15.02), (-4.0, 2.5, 12.0, 15.0)]  # 15.02: 501 steps of 0.03
    with task.coordinator:
        untouched = dict(task.simulator.timings)
        first = task.reset(*draws[0])
        assert task.simulator.timings != untouched  # induced: stepped
        u, w = task.simulator.u_n().x.array.copy(), task.simulator.w_n().x.array.copy()
        t = task.simulator.t
        assert t == pytest.approx(17.04, abs=1e-9)  # 67 steps of the stimulus's 2, 501 of 15.02
        after = act(env, 0)["observation"]
        task.reset(*draws[1])
        stepped = dict(task.simulator.timings)
        again = task.reset(*draws[0])
        assert task.simulator.timings == stepped  # restored: no step
        np.testing.assert_array_equal(again, first)
        np.testing.assert_array_equal(task.simulator.u_n().x.array, u)
        np.testing.assert_array_equal(task.simulator.w_n().x.array, w)
        assert task.simulator.t == t
        np.testing.assert_array_equal(act(env, 0)["observation"], after)  # same future

    fresh = atp_env(*overrides[:2], "env.snapshots.capacity=0")  # induces every time
    with fresh.task.coordinator:
        np.testing.assert_array_equal(fresh.task.reset(*draws[0]), first)
        np.testing.assert_array_equal(fresh.task.simulator.u_n().x.array, u)

    loaded = atp_env(*overrides)  # reads the files written by the resets above
    assert len(loaded.task.snapshots) == 0
    with loaded.task.coordinator:
        assert all(draw in loaded.task.snapshots for draw in draws)
        untouched = dict(loaded.task.simulator.timings)
        np.testing.assert_array_equal(loaded.task.reset(*draws[0]), first)
        assert loaded.task.simulator.timings == untouched
        np.testing.assert_array_equal(loaded.task.simulator.w_n().x.array, w)


WRITE_SNAPSHOTS = """
import sys
import numpy as np
from mpi4py import MPI
from physicsrl.envs.snapshots import SnapshotCache
cache = SnapshotCache(0, sys.argv[1], "settings", MPI.COMM_SELF)
for i in range(300):
    u = np.full(20_000, float(i % 4))
    cache.put((float(i % 4),), u, u + 0.5)
"""


def test_jobs_writing_the_same_snapshots_at_once_leave_whole_files(tmp_path):
    """Two processes storing the same snapshots in one library (two jobs of a sweep, or two
    groups of one job) leave readable files (a shared temporary name let one process rename
    or truncate the other's half-written file: errors and bad CRCs)."""
    command = [sys.executable, "-c", WRITE_SNAPSHOTS, str(tmp_path)]
    writers = [subprocess.Popen(command, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    assert [writer.wait(60) for writer in writers] == [0, 0], writers[0].stderr.read()
    reader = SnapshotCache(0, str(tmp_path), "settings", MPI.COMM_SELF)
    for key in range(4):
        u, w = reader.get((float(key),))
        assert (u == key).all() and (w == key + 0.5).all()
    assert len(list(tmp_path.glob("*/*.npz"))) == 4  # no temporary file left


def test_prefill_and_pool():
    env = atp_env("env.reset.pool=3")
    with env.task.coordinator:
        assert env.task.prefill(env.task.sampler.pool) == 3
        assert env.task.prefill(env.task.sampler.pool) == 0
        draws = {env.task.draw(np.random.default_rng(s)) for s in range(20)}
        assert draws == set(env.task.sampler.pool)
        member = member_seed(5, 3)  # a training member's seed, above the held-out start
        assert env.task.draw(np.random.default_rng(member)) in draws

        held_out = [env.task.draw(np.random.default_rng(s)) for s in held_out_seeds(20)]
        assert not set(held_out) & draws and len(set(held_out)) == 20  # outside the pool
        seed = held_out_seeds(1)[0]
        assert env.task.draw(np.random.default_rng(seed)) == held_out[0]  # the same draw again
        assert env.task.draw(np.random.default_rng(member_seed(seed, 3))) not in draws


def test_atp_baselines():
    """The reward of each baseline's episodes (-10 per shock, 500 - steps on success), and the
    single-shock search (all schedules in one batched comparison) equal to running each
    schedule's episodes one by one."""
    env = atp_env()
    seeds = [0, 1]

    def evaluate(env, policy, seeds):
        return [run_episode(env, policy, s)["return"] for s in seeds]

    with env.task.coordinator:
        never = evaluate(env, Constant(0), seeds)
        always = evaluate(env, Constant(1), seeds)
        every = evaluate(env, EveryKth(2), seeds)  # shocks at decisions 0 and 2 of 3
        # Failure: 0 (plus -10 per shock); success after s steps: 500 - s (s <= 3 + 2 extra).
        assert all(r == 0 or 495 <= r <= 499 for r in never)
        assert all(r == -30 or 500 - 5 - 30 <= r <= 500 - 1 - 10 for r in always)
        assert all(r == -20 or 500 - 5 - 20 <= r <= 499 for r in every)
        schedule, means = best_single_shock(env, seeds)
        one_by_one = {
            k: np.mean(evaluate(env, Constant(0) if k is None else Schedule([k]), seeds))
            for k in (None, 0, 1, 2)
        }
        assert means == pytest.approx(one_by_one)
        best = max(one_by_one, key=one_by_one.get)
        assert schedule.steps == frozenset([] if best is None else [best])
    assert "best single shock (decision 2)" in atp_baselines(env, seeds, single_shock=2)
    assert ATPReward().events == env.task.events
