"""Shared test helpers: run a Python script or module under ``mpiexec -n N`` with a timeout."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

MPIEXEC = Path(sys.executable).with_name("mpiexec")
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
        env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
        cwd=ROOT,
    )
    if check and result.returncode != 0:
        raise AssertionError(
            f"{' '.join(command)} exited {result.returncode}\n{result.stdout}\n{result.stderr}"
        )
    return result


@pytest.fixture
def mpi():
    return run_mpi
