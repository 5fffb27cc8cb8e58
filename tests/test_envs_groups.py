"""Many environments in one MPI job (physicsrl.envs.groups): layouts, determinism, evaluation
spread over the groups, and layout errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import run_mpi

from physicsrl.envs.members import member_seed
from physicsrl.launch import check_layout


@pytest.mark.parametrize(("ranks", "per_env"), [(2, 1), (4, 2), (2, 2)])
def test_each_environment_is_its_serial_self(tmp_path, ranks, per_env):
    """Environment i of the batch (N = ranks / P groups of P ranks; partial resets by the
    rollout) gives the trajectory of the same task built alone and seeded with
    member_seed(seed, i): so the same N gives the same trajectories with P = 1 and P = 2.
    The held-out episodes spread over the groups equal the serial episodes of those seeds."""
    out = tmp_path / "result.json"
    run_mpi(ranks, "tests/mpi_scripts/envs_groups.py", str(per_env), str(out), timeout=240)
    result = json.loads(out.read_text())
    n = ranks // per_env
    assert result["n"] == n
    # a batched rollout is (N, T, ...); with one group the env is the plain one: (T, ...)
    batched = {k: np.array(v) if n > 1 else np.array(v)[None] for k, v in result["batched"].items()}
    for i, serial in enumerate(result["serial"]):
        np.testing.assert_array_equal(batched["done"][i], serial["done"])
        assert sum(serial["done"]) >= 3  # episodes ended and restarted within the rollout
        # the heat solve's tolerance differs with the rank count (1 vs 2 ranks per group)
        np.testing.assert_allclose(batched["reward"][i], serial["reward"], rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(
            batched["observation"][i], serial["observation"], rtol=1e-6, atol=1e-6
        )
    # the Gymnasium vector form (of the plain env too): the same rewards, autoreset in the step
    vector = np.array(result["vector_rewards"]).T
    np.testing.assert_allclose(vector, batched["reward"], rtol=1e-6, atol=1e-6)
    if n > 1:
        assert len(result["evaluated"]) == 3
        for spread, serial in zip(result["evaluated"], result["serial_eval"], strict=True):
            np.testing.assert_allclose(spread["reward"], serial["reward"], rtol=1e-6, atol=1e-6)
    # distinct members see distinct episodes
    if n > 1:
        assert not np.array_equal(batched["reward"][0], batched["reward"][1])


def test_member_seeds():
    assert member_seed(7, 0) == 7  # one group: the plain env's seed
    assert member_seed(None, 3) is None
    seeds = {member_seed(s, i) for s in range(100) for i in range(64)}
    assert len(seeds) == 6400  # no two (seed, index) pairs share a seed


@pytest.mark.parametrize(
    ("per_env", "world", "text"),
    [(3, 2, "from 1 to"), (0, 2, "from 1 to"), (2, 6, None), (4, 6, "does not divide")],
)
def test_layout_errors(per_env, world, text):
    if text is None:
        check_layout(per_env, world)
        return
    with pytest.raises(ValueError, match=text) as error:
        check_layout(per_env, world)
    assert f"mpi.ranks_per_env={per_env}" in str(error.value)
    assert "\n" not in str(error.value)


@pytest.mark.parametrize(
    ("ranks", "per_env", "mode", "status"),
    [
        (2, 1, "remote", None),
        (2, 1, "learner", None),
        (4, 2, "remote", None),
        (4, 2, "exit", 3),
    ],
)
def test_faults_end_every_group(ranks, per_env, mode, status):
    """An exception in a remote group's simulator or on the learner ends every rank non-zero
    with the traceback printed once; a clean sys.exit(3) on the learner exits 3 on every rank,
    silently. Groups of 2 ranks: a fault inside the remote group, and the clean exit, through
    both groups (each group's leader and its follower; the learner's fault ends the same ranks
    as its clean exit does)."""
    result = run_mpi(
        ranks, "tests/mpi_scripts/envs_groups_fault.py", mode, str(per_env), timeout=60, check=False
    )
    output = result.stdout + result.stderr
    if status is None:
        assert result.returncode != 0
        assert output.count("Traceback") == 1, output
        raised = {"remote": "ValueError: action must be an integer in 0..1, got 5"}
        assert raised.get(mode, "RuntimeError: the learner failed") in output, output
    else:
        assert result.returncode == status, output
        assert "Traceback" not in output
