"""The README's examples run and do what they claim."""

import re


def test_thermostat_example_trains_a_policy_better_than_both_constant_ones(mpi):
    result = mpi(2, "examples/thermostat.py", "40", timeout=600)
    returns = dict(re.findall(r"([a-zA-Z ]+): (-?[0-9.]+)", result.stdout.splitlines()[-1]))
    returns = {name.strip(): float(value) for name, value in returns.items()}
    assert returns["greedy DQN"] > max(returns["heater off"], returns["heater on"]), returns
