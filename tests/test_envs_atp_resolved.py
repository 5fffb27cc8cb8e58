"""The resolved ATP task's S1-S2 cross-field induction and its snapshot library, on a scaled
version: a 20 mm square at h = 0.25 with the explicit scheme (the full task: 100 mm at h = 0.1),
S1 from the top edge and S2 when the top of S1's refractory tail lies near the middle."""

import json

import dolfinx_solver  # noqa: F401 (loads MPI before dolfinx)
import numpy as np
from conftest import run_mpi
from test_envs_atp import check_rest_range
from test_fem_monodomain import topological_charges

from physicsrl.coordinated import Coordinator
from physicsrl.envs import load_config, make_env

SCALED = [
    "env.mesh.cells=80",
    "env.mesh.extent=10",
    "env.model.scheme=explicit",
    "env.induction=cross_field",
    "env.cross_field.s1_bottom=8",
    "env.cross_field.s1_time=220",
    "env.cross_field.s2_delay=[0,10]",
    "env.cross_field.s2_edge=[-3,3]",
    "env.cross_field.s2_bottom=[-6,-4]",
    "env.cross_field.rest_time=20",
    "env.decision_interval=5",
    "env.shock.duration=2.5",
    "env.max_decisions=2",
    "env.extra_waits=0",
    "env.shock.centre=[0,5]",
    "env.shock.radius=5",
    "observation.distances=[7.5,6.5,3.5,2.5]",
]


def resolved_env(*overrides):
    return make_env(load_config("ms", overrides=[*SCALED, *overrides]), Coordinator())


def test_s2_in_the_s1_tail_breaks_the_wave():
    """The S1 state is a planar wave (no phase singularity); after S2 the wave has a free end,
    a phase singularity (net topological charge +-1), for each of three draws."""
    env = resolved_env()
    task = env.task
    with task.coordinator:
        for seed in range(3):
            task.reset(*task.draw(np.random.default_rng(seed)))
            charges = topological_charges(task.simulator)
            assert abs(charges.sum()) == 1, (seed, charges.sum())
            assert (task.simulator.u_n().x.array > 0.5).mean() > 0.05
        task.simulator.u_n().x.array[:], task.simulator.w_n().x.array[:] = task._s1_state
        assert not topological_charges(task.simulator).any()


def test_a_rest_range_starts_the_agent_at_a_drawn_phase():
    """``cross_field.rest_time=[20, 40]``: the rest after S2 is drawn; the agent starts at
    s1_time + delay + S2's stimulus_time + rest."""
    fixed, ranged = resolved_env(), resolved_env("env.cross_field.rest_time=[20,40]")
    check_rest_range(fixed, ranged, 20.0, 40.0, lambda draws: 220 + draws[0] + 2)


SAME_ON_RANKS = """
import json, sys
import dolfinx_solver
import numpy as np
sys.path.insert(0, "tests")
from test_envs_atp_resolved import resolved_env
env = resolved_env()
with env.task.coordinator:
    if env.task.coordinator.is_leader():
        draws = env.task.draw(np.random.default_rng(7))
        reading = env.task.reset(*draws)
        print(json.dumps({"draws": draws, "reading": reading.tolist()}))
"""


def test_draws_and_induced_state_same_on_1_and_2_ranks():
    """A seed gives the same draws on every call, and the same induced state (the catheter's
    readings, to round-off) on 1 rank (in this process) and 2 ranks."""
    task = resolved_env().task
    with task.coordinator:
        draws = task.draw(np.random.default_rng(7))
        reading = task.reset(*draws)
    assert task.draw(np.random.default_rng(7)) == draws
    f = task.config.cross_field
    assert all(
        low <= x <= high
        for x, (low, high) in zip(
            draws, (f.s2_delay, f.s2_edge, f.s2_bottom, f.rest_time), strict=True
        )
    )
    two_ranks = json.loads(run_mpi(2, "-c", SAME_ON_RANKS).stdout.splitlines()[-1])
    assert tuple(two_ranks["draws"]) == draws
    np.testing.assert_allclose(reading, two_ranks["reading"], rtol=1e-9, atol=1e-12)


def test_snapshot_library_round_trips_through_disk(tmp_path):
    """A reset stores its induced state on disk; a new env with the same settings reads it
    back instead of inducing (identical state), one with other settings does not."""
    directory = f"env.snapshots.directory={tmp_path}"
    first = resolved_env(directory)
    draws = first.task.draw(np.random.default_rng(3))
    with first.task.coordinator:
        reading = first.task.reset(*draws)
        u = first.task.simulator.u_n().x.array.copy()
    again = resolved_env(directory, "env.snapshots.capacity=0")
    with again.task.coordinator:
        assert draws in again.task.snapshots
        np.testing.assert_array_equal(again.task.reset(*draws), reading)
        np.testing.assert_array_equal(again.task.simulator.u_n().x.array, u)
        assert again.task._s1_state is None  # nothing was simulated
    other = resolved_env(directory, "env.cross_field.rest_time=10")
    with other.task.coordinator:
        assert draws not in other.task.snapshots
