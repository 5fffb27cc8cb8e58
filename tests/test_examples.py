"""The README's examples run and do what they claim; every example runs on 1 and 2 ranks."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import ROOT

EXAMPLES = sorted((ROOT / "examples").glob("*.py"))
SMOKE = {"thermostat.py": ["2"], "sb3_heat.py": ["--steps", "300", "env.mesh.cells=8"]}


@pytest.mark.parametrize("ranks", [1, 2])
@pytest.mark.parametrize("example", EXAMPLES, ids=lambda path: path.name)
def test_every_example_runs(mpi, example, ranks):
    """A short run of each example (its smoke arguments), serially and under mpiexec -n 2."""
    arguments = [str(example), *SMOKE.get(example.name, [])]
    if ranks == 1:
        result = subprocess.run(
            [sys.executable, *arguments], capture_output=True, text=True, timeout=300, cwd=ROOT
        )
        assert result.returncode == 0, result.stderr
    else:
        mpi(2, *arguments, timeout=300)


def test_thermostat_example_trains_a_policy_better_than_both_constant_ones(mpi):
    result = mpi(2, "examples/thermostat.py", "40", timeout=600)
    returns = dict(re.findall(r"([a-zA-Z ]+): (-?[0-9.]+)", result.stdout.splitlines()[-1]))
    returns = {name.strip(): float(value) for name, value in returns.items()}
    assert returns["greedy DQN"] > max(returns["heater off"], returns["heater on"]), returns


def test_readme_quickstart_runs_under_mpi(mpi, tmp_path):
    readme = (ROOT / "README.md").read_text()
    section = readme[readme.index("### Quickstart in Python") :]
    code = section[section.index("```python") + len("```python") : section.index("```\n\n")]
    script = tmp_path / "quickstart.py"
    script.write_text(code)
    result = mpi(2, str(script), timeout=600)
    assert "'return':" in result.stdout


def test_a_task_outside_the_package_trains_and_evaluates_from_the_command_line(tmp_path):
    """The thermostat is its module and its YAML: ``env=thermostat`` from a user's config
    directory brings its observation and reward (the task's pairs), trains on 2 ranks, and
    ``physicsrl-eval`` finds the task again from the run's config (its ``env.module``)."""
    bin_dir = Path(sys.executable).parent
    run = tmp_path / "run"
    train = [str(bin_dir / "physicsrl-train"), "hydra.searchpath=[file://examples/conf]"]
    train += ["env=thermostat", "mpi.ranks=2", "iterations=2", "logger.progress=false"]
    result = subprocess.run(
        [*train, f"hydra.run.dir={run}"], capture_output=True, text=True, timeout=300, cwd=ROOT
    )
    assert result.returncode == 0, result.stderr
    assert "heater on" in result.stdout and "heating" in result.stdout
    evaluate = [str(bin_dir / "physicsrl-eval"), f"run={run}", "seeds=2", "gif=false"]
    evaluate += ["curve=false", f"hydra.run.dir={tmp_path / 'eval'}"]
    result = subprocess.run(evaluate, capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert result.returncode == 0, result.stderr
    assert "greedy DQN" in result.stdout and "heater off" in result.stdout
