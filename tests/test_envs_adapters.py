"""Gymnasium adapter, determinism across rank counts, the SB3 example (issue 4)."""

import json

import numpy as np
import pytest
from conftest import SMALL_ATP, on_one_and_two_ranks, run_mpi
from gymnasium.utils.env_checker import check_env

from physicsrl.coordinated import Coordinator
from physicsrl.envs import load_config, make_env
from physicsrl.envs.gym import GymnasiumView

SCRIPT = "tests/mpi_scripts/envs_determinism.py"


@pytest.mark.parametrize(
    "groups, overrides",
    [
        (("heat", "quadrants", "heat_stop"), ["env.mesh.cells=16"]),
        (("ms", "catheter", "atp"), SMALL_ATP),
    ],
)
def test_gymnasium_checker(groups, overrides):
    env = make_env(load_config(*groups, overrides), Coordinator())
    with env.task.coordinator:
        check_env(GymnasiumView(env), skip_render_check=True)


def test_same_seed_same_trajectory_on_1_and_2_ranks():
    out = run_mpi(2, SCRIPT, timeout=200).stdout
    line = next(line for line in out.splitlines() if line.startswith("RESULT "))
    result = json.loads(line[len("RESULT ") :])
    assert result["ranks"] == 2
    two, one = result["parallel"], result["serial"]
    for task in ("heat", "atp", "atp_w"):
        assert len(one[task]) == len(two[task])
        for a, b in zip(one[task], two[task], strict=True):
            assert a["action"] == b["action"] and a["done"] == b["done"]
            np.testing.assert_allclose(a["reward"], b["reward"], rtol=1e-6, atol=1e-6)
            for key in ("observation", "final"):
                x, y = np.array(a[key]), np.array(b[key])
                np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6 * np.abs(x).max())  # float32
    # Different seeds gave different episodes (the comparison is not vacuous).
    starts = {episode["observation"][0][0] for episode in one["heat"]}
    assert len(starts) > 1
    # The gate's readings are not the potential's (w in (0, 1]: normalised readings too).
    gate = np.array(one["atp_w"][0]["observation"])
    assert not np.allclose(gate, one["atp"][0]["observation"][: len(gate)])
    assert -1e-6 <= gate.min() and gate.max() <= 1 + 1e-6


@pytest.fixture(scope="module")
def bad_action_runs():
    """``envs_bad_action.py`` on 1 and on 2 ranks (started together), by ranks."""
    return on_one_and_two_ranks("tests/mpi_scripts/envs_bad_action.py")


@pytest.mark.parametrize("ranks", [1, 2])
def test_a_bad_action_is_refused_on_the_leader_and_the_env_goes_on(bad_action_runs, ranks):
    """Out of range, negative, fractional (not truncated to a valid one) and boolean actions:
    one ValueError each on the leader, before any rank steps (on 2 ranks the job is not
    aborted), and the next valid step is the episode's first (the 1- and 2-rank jobs run at
    the same time)."""
    result = bad_action_runs[ranks]
    refused = [line for line in result.stdout.splitlines() if line.startswith("refused:")]
    assert [line.split("got ")[1] for line in refused] == ["2", "-1", "1.7", "0.5", "True"]
    assert "must be an integer in 0..1" in refused[0]
    assert "then step 1" in result.stdout and not result.stderr.count("Traceback")
