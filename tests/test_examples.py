"""The README's examples run and do what they claim; every example runs on 1 and 2 ranks."""

import functools
import re
import subprocess
import sys
from functools import partial
from pathlib import Path

import pytest

from tests.conftest import ROOT, run_mpi, together

PAIR = r"([a-zA-Z ]+): (-?[0-9.]+)"

EXAMPLES = sorted((ROOT / "examples").glob("*.py"))
# The arguments of a short run of each example, by ranks: the thermostat's 40 iterations
# serially also train it (test below).
SMOKE = {
    "thermostat.py": {1: ["40"], 2: ["2"]},
    "sb3_heat.py": dict.fromkeys((1, 2), ["--steps", "300", "env.mesh.cells=8"]),
}


@functools.cache
def run_example(name: str, ranks: int) -> str:
    """The standard output of a short run of the example ``name`` on ``ranks`` ranks: serially
    (1) or under ``mpiexec -n 2`` (2). Each run is made once, for every test that reads it;
    the serial runs of all examples are started together, at the first one asked for."""
    if ranks == 1:
        result = serial_runs()[name]
        assert result.returncode == 0, result.stderr
        return result.stdout
    return run_mpi(2, *example_arguments(name, 2), timeout=300).stdout


def example_arguments(name: str, ranks: int) -> list[str]:
    return [str(ROOT / "examples" / name), *SMOKE.get(name, {}).get(ranks, [])]


def run_serially(name: str) -> subprocess.CompletedProcess:
    command = [sys.executable, *example_arguments(name, 1)]
    return subprocess.run(command, capture_output=True, text=True, timeout=300, cwd=ROOT)


@functools.cache
def serial_runs() -> dict[str, subprocess.CompletedProcess]:
    """Example name -> its serial run; the runs (one process each) at the same time."""
    names = [example.name for example in EXAMPLES]
    return dict(zip(names, together(*(partial(run_serially, name) for name in names)), strict=True))


@pytest.mark.parametrize("ranks", [1, 2])
@pytest.mark.parametrize("example", EXAMPLES, ids=lambda path: path.name)
def test_every_example_runs(example, ranks):
    """A short run of each example (its smoke arguments), serially and under mpiexec -n 2."""
    run_example(example.name, ranks)


def test_thermostat_example_trains_a_policy_better_than_both_constant_ones():
    last = run_example("thermostat.py", 1).splitlines()[-1]
    returns = {name.strip(): float(value) for name, value in re.findall(PAIR, last)}
    assert returns["greedy DQN"] > max(returns["heater off"], returns["heater on"]), returns


NUMBER = r"(-?[0-9.]+)"
SB3_BASELINES = re.compile(rf"exact optimum {NUMBER}; stop at once {NUMBER}; never stop {NUMBER}")


def test_sb3_example_compares_its_agent_with_the_exact_optimum():
    """Serially and on 2 ranks the example prints the same exact optimum (the simulation is
    distributed; the optimum does not depend on it), above both trivial policies, and a trained
    agent's mean return that it bounds (each greedy episode is a stopping time of its level)."""
    optima = set()
    for ranks in (1, 2):
        text = run_example("sb3_heat.py", ranks)
        agent = float(re.search(rf"mean return {NUMBER}", text).group(1))
        optimum, stop, never = map(float, SB3_BASELINES.search(text).groups())
        assert agent <= optimum + 1e-3 and optimum >= max(stop, never), text
        optima.add((optimum, stop, never))
    assert len(optima) == 1, optima


def readme_blocks() -> list[str]:
    """The README's Python blocks that are whole scripts (not those with ``...`` in them)."""
    parts = (ROOT / "README.md").read_text().split("```python\n")[1:]
    return [part[: part.index("```")] for part in parts if "..." not in part[: part.index("```")]]


# what each block prints under 2 ranks (a regular expression), by a line of the block
README_PRINTS = {
    "dojo.train(24)": r"^\{.*'return': ",  # the quickstart's evaluation
    "counter.add(2.5)": r"^5\.0$",  # 2.5 on each of 2 ranks, once (the leader prints)
}


@pytest.mark.parametrize("block", readme_blocks(), ids=lambda code: code.splitlines()[-1].strip())
def test_readme_python_blocks_run_under_mpi(mpi, tmp_path, block):
    """Each complete Python block of the README runs under ``mpiexec -n 2`` and prints what
    the README says it prints."""
    script = tmp_path / "readme_block.py"
    script.write_text(block)
    result = mpi(2, str(script), timeout=600)
    for line, printed in README_PRINTS.items():
        if line in block:
            assert len(re.findall(printed, result.stdout, re.MULTILINE)) == 1, result.stdout


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
    # 2 environments x 10 of the default 20 frames per batch never end its 20-step episodes
    assert "no training episode ended" in result.stdout  # +experiment=thermostat sets 20 each
    # seed 1 seeded the run's training batch 1: the table does not call the seeds held out
    evaluate = [str(bin_dir / "physicsrl-eval"), f"run={run}", "seeds=[1,1000000000]"]
    evaluate += ["gif=false", f"hydra.run.dir={tmp_path / 'eval'}"]
    result = subprocess.run(evaluate, capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert result.returncode == 0, result.stderr
    assert "greedy DQN" in result.stdout and "heater off" in result.stdout
    assert "warning: seeds [1] seeded this run's training batches" in result.stdout
    assert "2 seeds, mean per episode" in result.stdout
    # the curve is of the run's own seeds: these seeds' baselines are not drawn beside it
    assert "(no baselines: these seeds or settings are not the run's)" in result.stdout


# a `physicsrl-train` or `physicsrl-bench` command written in a document or a config comment:
# the command, a benchmark's name, then its overrides (key=value, +key=value) and -m, up to the
# first other word (prose, a comment, a placeholder, Hydra's print-only flags)
OVERRIDE = r"(?:-m|[+~]?[\w.]+=[^\s`|<>)]*)"
DOCUMENTED = re.compile(
    rf"physicsrl-(train|bench)((?: +(?:ping|ms|env|groups)(?=[\s`]))?(?: +{OVERRIDE}(?=[\s`|]))*)"
)


def documented_commands() -> dict[tuple[str, str], str]:
    """(command, arguments) -> the file that first writes it, for the commands of the READMEs
    and of the YAML files' comments, as far as they are concrete."""
    documents = [ROOT / "README.md", *ROOT.glob("*/README.md"), *ROOT.glob("*/*/README.md")]
    documents += sorted((ROOT / "conf").rglob("*.yaml"))
    commands: dict[tuple[str, str], str] = {}
    for document in documents:
        for match in DOCUMENTED.finditer(document.read_text()):
            key = (match.group(1), match.group(2).strip())
            commands.setdefault(key, str(document.relative_to(ROOT)))
    return commands


def test_every_command_line_in_the_docs_is_a_valid_config():
    """Each concrete ``physicsrl-train`` (every job of a ``-m`` sweep) and ``physicsrl-bench``
    command of the READMEs and the config comments passes the command's own validation (the
    keys, types and ranges, the task's fit; not the layout over ranks, which depends on the
    job): a renamed key cannot hide in the docs."""
    import shlex

    from physicsrl.cli.bench import check as check_bench
    from physicsrl.cli.command import sweep_jobs, validate
    from physicsrl.cli.train import check_run
    from physicsrl.launch import Job

    commands = documented_commands()
    assert len(commands) >= 30, commands  # the extraction still finds them
    refused = []
    for (command, arguments), document in commands.items():
        words = shlex.split(arguments)
        try:
            if command == "bench":
                if words:
                    check = functools.partial(check_bench, name=words[0])
                    validate(f"bench_{words[0]}", words[1:], check, Job.local())
                continue
            sweep = "-m" in words
            words = [w for w in words if w != "-m"]
            for job in sweep_jobs(words) if sweep else [words]:
                validate("train", job, lambda cfg, _: check_run(cfg), Job.local())
        except ValueError as error:
            refused.append(f"{document}: physicsrl-{command} {arguments}: {error}")
    assert not refused, "\n".join(refused)
