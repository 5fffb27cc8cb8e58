"""Shared test helpers: run a Python script or module under ``mpiexec -n N`` with a timeout."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path

import pytest

# One OpenMP thread per process, in this process (set before anything imports torch) and in
# every command and MPI rank it starts, as for any MPI code: make test runs two test files at
# once on two cores (pytest-xdist), and threads that wait on each other for a core only slow
# both.
os.environ.setdefault("OMP_NUM_THREADS", "1")

MPIEXEC = Path(sys.executable).with_name("mpiexec")

# A small ATP task: 20 x 20 cells, intervals of 5 time units, 3 decisions + 2 extra waits
# (~0.3 s an episode), for tests where the figures of the report are not what is tested.
SMALL_ATP = [
    "env.mesh.cells=20",
    "env.reset.stimulus_time=2",
    "env.reset.rest_time=3",
    "env.decision_interval=5",
    "env.shock.duration=2.5",
    "env.max_decisions=3",
    "env.extra_waits=2",
]
ROOT = Path(__file__).resolve().parent.parent


def run_mpi(ranks: int, *args: str, timeout: float = 120, env: dict | None = None, check=True):
    """Run ``mpiexec -n ranks python *args``; return the CompletedProcess (text output).

    A hang fails the test (``subprocess.TimeoutExpired``) instead of blocking the suite.
    """
    command = [str(MPIEXEC), "-n", str(ranks), sys.executable, *args]
    result = subprocess.run(
        command,
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONPATH": str(ROOT), **(env or {})},
        cwd=ROOT,
    )
    if check and result.returncode != 0:
        raise AssertionError(
            f"{' '.join(command)} exited {result.returncode}\n{result.stdout}\n{result.stderr}"
        )
    return result


def together(*calls: Callable):
    """The results of ``calls`` (each starts a command and waits for it), made at the same
    time: independent commands share the machine's cores instead of waiting for each other
    (each spends seconds importing torch on one core). The first exception is raised."""
    with ThreadPoolExecutor(len(calls)) as pool:
        futures = [pool.submit(call) for call in calls]
        return [future.result() for future in futures]


def on_one_and_two_ranks(script: str) -> dict[int, subprocess.CompletedProcess]:
    """``script`` run on 1 and on 2 ranks (started together, :func:`together`), by ranks."""
    runs = together(*(partial(run_mpi, ranks, script, timeout=120) for ranks in (1, 2)))
    return dict(zip((1, 2), runs, strict=True))


@pytest.fixture
def mpi():
    return run_mpi
