"""The Slurm launcher config run for real: a Hydra multirun of two jobs of 2 MPI ranks each
through the submitit launcher, on a single-node Slurm started by tests/slurm/local_slurm.sh
(``make test-slurm`` installs and starts it where it can; without it these tests skip)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slurm


def slurm_is_up() -> str | None:
    """Why the local Slurm cannot be used, or None when it can."""
    if not os.environ.get("SLURM_CONF") or shutil.which("sinfo") is None:
        return "no local Slurm (run `make test-slurm`, which starts one)"
    state = subprocess.run(["sinfo", "-h", "-o", "%t"], capture_output=True, text=True)
    return None if state.stdout.strip() == "idle" else f"Slurm node not idle: {state.stdout!r}"


def test_sweep_of_two_mpi_jobs(tmp_path):
    reason = slurm_is_up()
    if reason:
        pytest.skip(reason)
    train = Path(sys.executable).with_name("physicsrl-train")
    command = [
        str(train),
        "-m",
        "+cluster=slurm",
        "hydra.launcher.tasks_per_node=2",
        "hydra.launcher.mem_gb=2",
        "hydra.launcher.partition=local",
        "hydra.launcher.timeout_min=10",
        "hydra.launcher.setup=['export SLURM_MPI_TYPE=pmi2']",  # the local Slurm's PMI plugin
        f"hydra.sweep.dir={tmp_path}/sweep",
        "seed=0,1",
        "iterations=3",
        "eval.every=3",
        "eval.seeds=[1000000000,1000000001]",
        "eval.baselines=false",
    ]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert result.returncode == 0, result.stdout + result.stderr
    for job in ("0", "1"):
        directory = tmp_path / "sweep" / job
        summary = json.loads((directory / "summary.json").read_text())["summary"]
        assert summary["iteration"] == 3
        assert (directory / "checkpoints" / "ckpt-000000000003.torchrl").is_file()
        log = (directory / "train.log").read_text()
        assert "2 ranks" in log  # the two tasks formed one MPI job
    configs = [(tmp_path / "sweep" / j / ".hydra" / "config.yaml").read_text() for j in "01"]
    assert "seed: 0" in configs[0] and "seed: 1" in configs[1]
