"""The README's examples run and do what they claim."""

import re


def test_thermostat_example_trains_a_policy_better_than_both_constant_ones(mpi):
    result = mpi(2, "examples/thermostat.py", "40", timeout=600)
    returns = dict(re.findall(r"([a-zA-Z ]+): (-?[0-9.]+)", result.stdout.splitlines()[-1]))
    returns = {name.strip(): float(value) for name, value in returns.items()}
    assert returns["greedy DQN"] > max(returns["heater off"], returns["heater on"]), returns


def test_readme_quickstart_runs_under_mpi(mpi, tmp_path):
    from tests.conftest import ROOT

    readme = (ROOT / "README.md").read_text()
    section = readme[readme.index("### Quickstart in Python") :]
    code = section[section.index("```python") + len("```python") : section.index("```\n\n")]
    script = tmp_path / "quickstart.py"
    script.write_text(code)
    result = mpi(2, str(script), timeout=600)
    assert "'return':" in result.stdout
