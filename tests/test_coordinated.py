"""The coordination layer: single-rank behaviour in-process, replication and faults under MPI."""

import os
import re
import signal
import subprocess
import sys
import time

import pytest
from conftest import MPIEXEC, ROOT

from physicsrl.coordinated import (
    Coordinated,
    CoordinationError,
    Coordinator,
    parallel,
    randint,
    random,
    wait_for,
)

# Each fault and exit below also runs with every rank guarded (physicsrl.guard, as the
# physicsrl-* commands run): the same statuses and lines, and no line of the guard's.
guards = pytest.mark.parametrize(
    "ranks, guard", [(2, []), (3, []), (3, ["-m", "physicsrl.guard"])], ids=["2", "3", "3-guarded"]
)


class Recorder(Coordinated):
    def __init__(self, coordinator=None, namespace=None):
        if coordinator is not None:
            self.register_coordinator(coordinator, namespace)
        self.calls = []

    @parallel
    def record(self, value):
        """Record a value."""
        self.calls.append(value)
        return value * 2

    @parallel
    def fail(self):
        raise ValueError("boom")


def test_namespaces_increment_and_reject_duplicates():
    coordinator = Coordinator()
    assert [coordinator.register(object()) for _ in range(3)] == [0, 1, 2]
    assert coordinator.register(object(), "sim") == "sim"
    with pytest.raises(CoordinationError, match="'sim' is already registered"):
        coordinator.register(object(), "sim")


def test_single_rank_calls_run_locally_and_return():
    coordinator = Coordinator()
    recorder = Recorder(coordinator)
    with coordinator:
        assert recorder.record(21) == 42
        with pytest.raises(ValueError, match="boom"):
            recorder.fail()
        assert recorder.record(1) == 2  # still usable after an exception
    assert recorder.calls == [21, 1]
    assert coordinator._sequence == 0  # one rank: nothing was sent
    assert Recorder.record.__name__ == "record" and Recorder.record.__doc__ == "Record a value."


@pytest.mark.parametrize("spin_s, idle_calls", [(0.0, 4), (60.0, 0)])
def test_wait_for_polls_until_ready_and_calls_idle_only_while_sleeping(spin_s, idle_calls):
    """Five polls find nothing, the sixth a message: all six are made; without a spin phase
    the four polls after the first are separated by sleeps, each followed by ``idle()``;
    within a long spin phase there is no sleep."""
    polls = iter([False] * 5 + [True, "never polled"])
    idle = []
    wait_for(lambda: next(polls), spin_s, 1e-4, oversubscribed=True, idle=lambda: idle.append(1))
    assert next(polls) == "never polled"
    assert len(idle) == idle_calls


def test_misuse_raises_clear_errors():
    coordinator = Coordinator()
    recorder = Recorder(coordinator)
    with pytest.raises(CoordinationError, match="inside 'with coordinator:'"):
        recorder.record(1)
    with pytest.raises(CoordinationError, match="register_coordinator"):
        Recorder().record(1)
    with coordinator:
        with pytest.raises(CoordinationError, match="already inside"):
            coordinator.__enter__()
    with pytest.raises(CoordinationError, match="inside 'with coordinator:'"):
        recorder.record(1)  # the with-block has ended


def test_leader_drawn_random_numbers_are_in_range():
    from mpi4py import MPI

    draws = [randint(MPI.COMM_WORLD, -5, 5) for _ in range(500)]
    assert set(draws) == set(range(-5, 6))
    assert all(0.0 <= random() < 1.0 for _ in range(100))


@pytest.mark.parametrize("ranks", [2, 3])
def test_calls_are_replayed_on_every_rank(mpi, ranks):
    result = mpi(ranks, "tests/mpi_scripts/coord_replay.py", timeout=60)
    assert "ok" in result.stderr


@guards
@pytest.mark.parametrize("where", ["leader", "follower", "followers", "all", "leader-code"])
def test_a_fault_anywhere_ends_every_rank(mpi, guard, ranks, where):
    assert_fault_ends_every_rank(mpi, guard, ranks, where)


def assert_fault_ends_every_rank(mpi, guard, ranks, where, env=None):
    """Within 10 s, non-zero, with the injected fault's traceback once and no other report."""
    start = time.perf_counter()
    result = mpi(
        ranks, *guard, "tests/mpi_scripts/coord_fault.py", where, timeout=30, check=False, env=env
    )
    elapsed = time.perf_counter() - start
    output = result.stdout + result.stderr
    assert result.returncode != 0, output
    assert elapsed < 10, f"took {elapsed:.1f} s to end"
    assert "unreachable" not in output
    assert len(re.findall(rf"RuntimeError: injected fault {where}", output)) == 1, output
    assert "ended before its job did" not in output and "watchdog:" not in output, output


@pytest.mark.parametrize("ranks", [2, 3])
@pytest.mark.parametrize("where", ["follower", "followers"])
def test_a_follower_fault_under_a_watchdog_shorter_than_its_grace_is_its_traceback(
    mpi, ranks, where
):
    """A failing follower waits 2 s for word that the leader failed too; a watchdog of 0.5 s
    leaves the report to it (it aborted first, and its one line hid the traceback)."""
    assert_fault_ends_every_rank(mpi, [], ranks, where, env={"PHYSICSRL_TIMEOUT": "0.5"})


def test_coordinators_on_split_communicators_work_side_by_side(mpi):
    assert "ok" in mpi(4, "tests/mpi_scripts/coord_misc.py", "side-by-side", timeout=60).stderr


def test_coordinators_free_their_communicator_so_a_process_can_make_thousands(mpi):
    """Each with-block duplicates the communicator and frees it when it ends: 3000 coordinators
    in one process (MPICH has about 2040 communicators), one of them entered twice; and 3000
    ``environments`` blocks, which free their group leaders' communicator."""
    assert "ok" in mpi(2, "tests/mpi_scripts/coord_misc.py", "many", timeout=120).stderr


def test_sequence_check_reports_the_first_divergence(mpi):
    result = mpi(2, "tests/mpi_scripts/coord_misc.py", "divergence", timeout=30, check=False)
    assert result.returncode != 0
    assert (
        "reported: ranks diverged in call 2, step 1: the leader ran nothing, rank 1 ran "
        "Node[0].record" in result.stderr
    ), result.stderr


def test_idle_follower_does_not_spin_a_core(mpi):
    result = mpi(2, "tests/mpi_scripts/coord_misc.py", "idle", timeout=60)
    share = float(re.search(r"follower cpu ([0-9.]+)", result.stderr).group(1))
    assert share < 0.10, f"an idle follower used {share:.1%} of a core"


@guards
@pytest.mark.parametrize("status", [0, 3, 2**40 + 3])  # the OS keeps the low 8 bits
def test_leader_sys_exit_is_every_rank_exit_status(mpi, guard, ranks, status):
    result = mpi(
        ranks, *guard, "tests/mpi_scripts/coord_exit.py", f"exit-{status}", timeout=30, check=False
    )
    assert result.returncode == status & 0xFF, result.stderr
    assert "Traceback" not in result.stderr and "finished" not in result.stderr, result.stderr


@guards
def test_keyboard_interrupt_in_leader_code_ends_every_rank_with_130(mpi, guard, ranks):
    script = "tests/mpi_scripts/coord_exit.py"
    result = mpi(ranks, *guard, script, "interrupt", timeout=30, check=False)
    assert result.returncode == 130, result.stderr
    assert result.stderr.strip() == "interrupted: every rank exits with status 130"


def ctrl_c(ranks: int, guard: list[str], case: str, tmp_path, follower_only=False):
    """Run ``coord_exit.py ctrl-c-<case>`` under ``mpiexec -n ranks``; once every rank is ready,
    send SIGINT to the launcher's process group, as a terminal's Ctrl-C does (or to the last
    rank only); return the exit status and the output."""
    script = ["tests/mpi_scripts/coord_exit.py", f"ctrl-c-{case}"]
    output = tmp_path / "stderr"
    with output.open("w") as stderr:
        job = subprocess.Popen(
            [str(MPIEXEC), "-n", str(ranks), sys.executable, *guard, *script],
            stderr=stderr,
            cwd=ROOT,
            env={**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONPATH": str(ROOT)},
            start_new_session=True,
        )
        try:
            deadline = time.monotonic() + 60
            while output.read_text().count("ready") < ranks and time.monotonic() < deadline:
                time.sleep(0.05)
            time.sleep(0.2)  # the leader back in its own code, the followers idle
            if follower_only:
                last = re.search(rf"rank {ranks - 1} ready, pid (\d+)", output.read_text())
                os.kill(int(last.group(1)), signal.SIGINT)
            else:
                os.killpg(job.pid, signal.SIGINT)
            status = job.wait(timeout=20)
        finally:
            if job.poll() is None:
                os.killpg(job.pid, signal.SIGKILL)
    launcher = ("[mpiexec@", "Abort(130)")  # MPICH's own lines
    said = [line for line in output.read_text().splitlines() if line and "ready" not in line]
    return status, [line for line in said if not line.startswith(launcher)]


@guards
@pytest.mark.parametrize(
    "case, where",
    [
        ("idle", "interrupted"),
        ("call", "[rank 0] interrupted in a parallel call"),
        ("plain", "[rank 0] interrupted"),
    ],
)
def test_ctrl_c_ends_every_rank_with_130_in_one_line(guard, ranks, case, where, tmp_path):
    """A terminal's Ctrl-C interrupts every rank: idle followers wait for the leader's word
    (they printed a traceback each), inside a parallel call the leader aborts every rank with
    status 130 (status 1 and a traceback), and so does ``abort_on_error`` (a traceback per
    rank)."""
    status, said = ctrl_c(ranks, guard, case, tmp_path)
    assert (status, said) == (130, [f"{where}: every rank exits with status 130"])


@pytest.mark.parametrize("case", ["idle", "call"])
def test_a_follower_interrupted_alone_ends_every_rank_naming_it(case, tmp_path):
    status, said = ctrl_c(3, [], case, tmp_path, follower_only=True)
    where = (
        "interrupted, and the leader was not"
        if case == "idle"
        else "interrupted in a parallel call"
    )
    assert (status, said) == (130, [f"[rank 2] {where}: every rank exits with status 130"])


@guards
def test_watchdog_aborts_a_call_that_some_ranks_never_finish(mpi, guard, ranks):
    start = time.perf_counter()
    result = mpi(
        ranks,
        *guard,
        "tests/mpi_scripts/coord_exit.py",
        "followers-collective",
        timeout=30,
        check=False,
        env={"PHYSICSRL_TIMEOUT": "1"},
    )
    assert result.returncode != 0
    assert time.perf_counter() - start < 10
    followers = list(range(1, ranks))
    line = (
        f"watchdog: parallel call Job.step (call 2) has not finished after 1 s on ranks "
        f"{followers}; aborting every rank"
    )
    assert result.stderr.count("watchdog:") == 1 and line in result.stderr, result.stderr
    assert "ended before its job did" not in result.stderr  # the abort was reported


def test_watchdog_lets_calls_that_finish_run_to_the_end(mpi):
    result = mpi(2, "tests/mpi_scripts/coord_exit.py", "watched", env={"PHYSICSRL_TIMEOUT": "1"})
    assert result.stderr.count("finished") == 2, result.stderr


def test_watchdog_without_thread_multiple_is_refused_on_every_rank(mpi):
    """The watchdog's thread needs THREAD_MULTIPLE: without it every rank refuses at the
    start of the with-block (the leader alone refused, and the followers waited forever)."""
    env = {"PHYSICSRL_TIMEOUT": "5", "MPI4PY_RC_THREAD_LEVEL": "funneled"}
    start = time.perf_counter()
    result = mpi(2, "tests/mpi_scripts/coord_exit.py", "watched", timeout=30, check=False, env=env)
    assert result.returncode != 0 and time.perf_counter() - start < 20
    assert "needs MPI initialised with THREAD_MULTIPLE" in result.stderr, result.stderr


def test_bad_settings_and_arguments_are_refused_naming_them():
    from mpi4py import MPI

    for settings, named in [
        ({"max_sleep_s": -1}, "max_sleep_s=-1"),
        ({"spin_s": "0.1"}, "spin_s='0.1'"),
        ({"check": "no"}, "check='no'"),
        ({"timeout": float("inf")}, "timeout=inf"),
        ({"comm": None}, "comm=None"),
    ]:
        with pytest.raises(CoordinationError, match=re.escape(named)):
            Coordinator(**settings)
    with pytest.raises(ValueError, match="a = 5 must be <= b = 1"):
        randint(MPI.COMM_WORLD, 5, 1)
    with pytest.raises(TypeError):
        randint(MPI.COMM_WORLD, 1.5, 3)  # returned 1
    with pytest.raises(TypeError, match="runs only where it is iterated"):

        class Stream(Coordinated):
            @parallel
            def values(self):
                yield 1


def test_bad_timeout_is_refused(monkeypatch):
    monkeypatch.setenv("PHYSICSRL_TIMEOUT", "soon")
    with pytest.raises(CoordinationError, match="PHYSICSRL_TIMEOUT='soon': must be a number"):
        Coordinator()
    with pytest.raises(CoordinationError, match="timeout=-1: must be a number of seconds > 0"):
        Coordinator(timeout=-1)
