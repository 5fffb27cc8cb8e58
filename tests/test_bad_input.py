"""Bad command lines, tried as a hostile user would: every one ends with status 2 and one line
naming the key, before any work.

The table runs each row through the validation that the commands run before Hydra starts
(:func:`physicsrl.cli.command.validate_or_exit`, in this process: it is a function of the
composed config); a handful of rows run as real commands, some under ``mpiexec -n 2``, to pin
that the line is printed once and that no rank waits.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import MPIEXEC, ROOT

BIN = Path(sys.executable).parent
RUN = "<checkpoint>"  # physicsrl-eval rows: replaced by a checkpoint file

# (command, overrides, what the line must name); command: train, eval or bench_NAME
ROWS = [
    # types
    ("train", ["iterations=abc"], "'iterations'"),
    ("train", ["iterations=1.5"], "'iterations'"),
    ("train", ["agent.lr=abc"], "'agent.lr'"),
    ("train", ["agent.network.hidden=abc"], "'agent.network.hidden'"),
    ("train", ["agent.network.normalize=maybe"], "'agent.network.normalize'"),
    ("train", ["collector.frames_per_batch=many"], "'collector.frames_per_batch'"),
    ("train", ["resume=[1]"], "resume"),
    ("train", ["iterations="], "'iterations'"),
    ("train", ["seed="], "'seed'"),
    # Enum members
    ("train", ["agent.network.activation=sigmoid"], "'agent.network.activation'"),
    ("train", ["buffer.storage=disk"], "'buffer.storage'"),
    ("train", ["loss.loss_function=l3"], "'loss.loss_function'"),
    ("train", ["loss.target.kind=medium"], "'loss.target.kind'"),
    # ranges, NaN and inf
    ("train", ["iterations=0"], "iterations must be an integer >= 1"),
    ("train", ["iterations=-5"], "iterations must be an integer >= 1"),
    ("train", ["seed=-1"], "seed must be an integer >= 0"),
    ("train", ["threads=0"], "threads must be an integer >= 1"),
    ("train", ["agent.lr=inf"], "agent.lr must be a finite number > 0"),
    ("train", ["agent.lr=nan"], "agent.lr must be a finite number > 0"),
    ("train", ["agent.lr=-1e-3"], "agent.lr must be a finite number > 0"),
    ("train", ["optim.lr=0"], "optim.lr must be a finite number > 0"),
    ("train", ["optim.weight_decay=-1"], "optim.weight_decay must be a finite number >= 0"),
    ("train", ["optim.grad_clip=inf"], "optim.grad_clip must be a finite number >= 0"),
    ("train", ["optim.updates_per_batch=-1"], "optim.updates_per_batch must be an integer"),
    ("train", ["optim.learning_starts=-1"], "optim.learning_starts must be an integer"),
    ("train", ["agent.exploration.eps_init=1.5"], "agent.exploration.eps_init must be"),
    ("train", ["agent.exploration.eps_end=-0.1"], "agent.exploration.eps_end must be"),
    ("train", ["agent.exploration.annealing_frames=0"], "annealing_frames must be an integer"),
    ("train", ["agent.exploration.random_action_within=-1"], "random_action_within must be"),
    ("train", ["agent.exploration.probe_episodes=1.5"], "probe_episodes must be"),
    ("train", ["agent.exploration.probe_episodes=0.5"], "probe_episodes needs random_action"),
    ("train", ["agent.network.hidden=[0]"], "agent.network.hidden[0] must be an integer >= 1"),
    ("train", ["agent.network.hidden=[64,-4]"], "agent.network.hidden[1] must be an integer"),
    ("train", ["buffer.size=0"], "buffer.size must be an integer >= 1"),
    ("train", ["buffer.batch_size=0"], "buffer.batch_size must be an integer >= 1"),
    ("train", ["collector.frames_per_batch=0"], "collector.frames_per_batch must be an integer"),
    ("train", ["loss.gamma=0"], "loss.gamma must be a finite number > 0 and <= 1"),
    ("train", ["loss.gamma=1.5"], "loss.gamma must be a finite number > 0 and <= 1"),
    ("train", ["loss.n_steps=0"], "loss.n_steps must be an integer >= 1"),
    ("train", ["loss.action_costs=[0,nan]"], "loss.action_costs[1] must be a finite number"),
    ("train", ["+env.module=nowhere.py"], "env.module 'nowhere.py' cannot be imported"),
    ("train", ["loss.target.tau=0"], "loss.target.tau must be a finite number > 0"),
    ("train", ["loss.target.period=0"], "loss.target.period must be an integer >= 1"),
    ("train", ["checkpoint.every=-1"], "checkpoint.every must be an integer >= 0"),
    ("train", ["checkpoint.keep=0"], "checkpoint.keep must be an integer >= 1"),
    ("train", ["eval.every=-1"], "eval.every must be an integer >= 0"),
    ("train", ["mpi.ranks_per_env=0"], "mpi.ranks_per_env must be an integer >= 1"),
    ("train", ["max_memory_gb=0"], "max_memory_gb must be a finite number > 0"),
    ("train", ["max_memory_gb=nan"], "max_memory_gb must be a finite number > 0"),
    ("train", ["env.max_steps=0"], "env.max_steps must be an integer >= 1"),
    ("train", ["env.dt=-0.01"], "env.dt must be a finite number > 0"),
    ("train", ["env.mesh.cells=0"], "env.mesh.cells must be an integer >= 1"),
    ("train", ["env.levels=[5,-5]"], "env.levels must be a pair [low, high] with low <= high"),
    ("train", ["observation.centre=[0]"], "observation.centre must have 2 entries"),
    (
        "train",
        ["observation.variable=w"],  # the default env: heat, whose only variable is u
        "observation.variable 'w' does not fit the heat task: it simulates u",
    ),
    ("train", ["env=ms", "observation.variable=v"], "observation.variable 'v' does not fit the"),
    # empty and huge values
    ("train", ["eval.seeds=[]"], "eval.seeds must list at least one seed"),
    ("train", ["agent.network.inputs=[]"], "agent.network.inputs must name at least one"),
    ("train", ["agent.network.hidden=[1000000000]"], "agent.network.hidden=[1000000000] would"),
    ("train", ["agent.network.hidden=[100000,100000]"], "agent.network.hidden=[100000, 100000]"),
    ("train", ["buffer.size=100000000000000"], "buffer.size=100000000000000 would need about"),
    ("train", ["env.max_steps=1000000000"], "env.max_steps must be <= 1000"),
    ("train", ["env.mesh.cells=1e9"], "env.mesh.cells must be an integer"),
    # unknown keys and groups
    ("train", ["foo=1"], "unknown key 'foo'"),
    ("train", ["+loss.bogus=1"], "unknown key 'loss.bogus'"),
    ("train", ["+agent.network.depth=3"], "unknown key 'agent.network.depth'"),
    ("train", ["env.nosuch=1"], "unknown key 'env.nosuch'"),
    ("train", ["reward.nosuch=1"], "unknown key 'reward.nosuch'"),
    ("train", ["env=nosuch"], "env=nosuch: no such option (choose one of heat, ms, ms_resolved)"),
    ("train", ["observation=nosuch"], "observation=nosuch: no such option (choose one of"),
    ("train", ["+experiment=nosuch"], "experiment=nosuch: no such option (choose one of atp"),
    ("train", ["agent.network.inputs=[nosuchkey]"], "agent.network.inputs: 'nosuchkey'"),
    # unparsable syntax
    ("train", ["agent.network.hidden=[64,64"], "'agent.network.hidden=[64,64'"),
    ("train", ["eval.seeds=[1,,2]"], "'eval.seeds=[1,,2]'"),
    ("train", ["iterations=${oops"], "'iterations=${oops'"),
    # incompatible pairs
    ("train", ["observation=catheter"], "observation=catheter does not fit the heat task"),
    ("train", ["env=heat", "observation=catheter"], "catheter does not fit the heat task"),
    ("train", ["env=ms", "reward=heat_stop"], "reward=heat_stop does not fit the atp task"),
    ("train", ["env=ms", "agent.network.inputs=[observation,nosuch]"], "'nosuch'"),
    ("train", ["eval.seeds=[3]"], "eval.seeds [3] are also training seeds"),
    ("train", ["env=ms", "env.replicas=4"], "env.replicas must be 1 with model.backend=petsc"),
    ("train", ["env=ms", "env.model.backend=jax"], "env.model.backend must be one of petsc, torch"),
    ("train", ["env=ms", "env.model.device=cuda"], "env.model.device=cuda needs backend=torch"),
    ("train", ["env=ms", "env.model.substeps=2"], "env.model.substeps must be 1 unless scheme"),
    (
        "train",
        ["env=ms", "env.mesh.cells=4000", "env.model.scheme=explicit"],
        "env.model.dt / model.substeps = 0.03 exceeds the explicit scheme's stability limit "
        "0.01803 on 4000 x 4000 cells of side 0.025: raise model.substeps",
    ),
    (
        "train",
        ["env=ms", "env.model.backend=torch", "env.replicas=10000000"],
        "env.replicas=10000000 would need about 1.79e+03 GB (48 bytes per replica and dof)",
    ),
    (
        "train",
        ["env=ms", "env.mesh.cells=100000"],
        "env.mesh.cells=100000 would need about 1e+04 GB (1000 bytes per cell, over "
        "mpi.ranks_per_env=1, per rank)",
    ),
    # physicsrl-eval
    ("eval", ["run=???"], "run is required"),  # as a command line without run=
    ("eval", ["overrides=[env.dt=1]"], "quote the items that hold '=': overrides='[\"a=1\"]'"),
    ("eval", ["fps=0"], "fps must be a finite number > 0"),
    ("eval", ["fps=nan"], "fps must be a finite number > 0"),
    ("eval", ["seeds=[]"], "seeds must be N >= 1, a non-empty list of seeds >= 0, or null"),
    ("eval", ["seeds=0"], "seeds must be N >= 1, a non-empty list of seeds >= 0, or null"),
    ("eval", ["seeds=abc"], "seeds must be N >= 1"),
    ("eval", ["seeds=true"], "seeds must be N >= 1"),
    ("eval", ["seeds=[a,b]"], "seeds[0] must be an integer >= 0, got 'a'"),
    ("eval", ["seeds=[5,-1]"], "seeds[1] must be an integer >= 0, got -1"),
    ("eval", ["gif_seed=abc"], "gif_seed must be an integer >= 0"),
    ("eval", ["gif_seed=-1"], "gif_seed must be an integer >= 0"),
    ("eval", ["fields=maybe"], "'fields'"),
    ("eval", ["gif=maybe"], "'gif'"),
    ("eval", ["nosuch=1"], "unknown key 'nosuch'"),
    ("eval", ["seeds=2000000000"], "seeds=2000000000: N runs N episodes per policy, at most"),
    ("eval", ["seeds=[7,8,7]"], "seeds lists 7 more than once"),
    ("eval", ['overrides=["agent.network.hidden=[32]"]'], "the stored weights fit the run's"),
    ("eval", ['overrides=["eval.seeds=[1000000000,1000000000]"]'], "eval.seeds lists 10000"),
    ("train", ["eval.seeds=${held_out:2000000}"], "2000000 held-out seeds (an episode each)"),
    ("eval", ['overrides=["nosuch=1"]'], "overrides: unknown key 'nosuch'"),
    ("eval", ['overrides=["agent.lr=-1"]'], "overrides: agent.lr must be a finite number > 0"),
    ("eval", ['overrides=["iterations=abc"]'], "overrides: bad value for 'iterations'"),
    ("eval", ['overrides=["agent.network.hidden=[64,64"]'], "cannot parse 'agent.network.hid"),
    ("eval", ["run=/etc/passwd"], "run=/etc/passwd is not a checkpoint file"),
    ("eval", ["run=/nonexistent/run"], "run=/nonexistent/run: no checkpoint file there"),
    # physicsrl-bench
    ("bench_ping", ["calls=0"], "calls=0: must be an integer >= 1"),
    ("bench_ping", ["calls=-5"], "calls=-5: must be an integer >= 1"),
    ("bench_ping", ["repeats=1.5"], "repeats=1.5: must be an integer >= 1"),
    ("bench_ping", ["idle_seconds=inf"], "idle_seconds=inf: must be a finite number"),
    ("bench_ping", ["nosuch=1"], "'nosuch'"),
    ("bench_ms", ["grid.n=1"], "grid.n=1: must be an integer >= 2"),
    ("bench_ms", ["baseline=maybe"], "baseline=maybe: must be true or false"),
    ("bench_ms", ["scheme=foo"], "scheme=foo: must be one of implicit, explicit, both"),
    ("bench_ms", ["rhs=fortran"], "rhs=fortran: must be one of compiled, numpy, form"),
    ("bench_ms", ["steps=1"], "steps=1: must exceed steps_per_call=1"),
    ("bench_ms", ["steps=10", "steps_per_call=10"], "steps=10: must exceed steps_per_call=10"),
    ("bench_groups", ["mpi.ranks_per_env=3"], "mpi.ranks_per_env=3 must be an integer from 1"),
    ("bench_groups", ["decisions=16"], "decisions=16: must be at most env.max_decisions=15"),
    ("bench_env", ["decisions=0"], "decisions=0: must be an integer >= 1"),
    ("bench_groups", ["decisions=0"], "decisions=0: must be an integer >= 1"),
    ("bench_groups", ["noop_steps=-1"], "noop_steps=-1: must be an integer >= 1"),
    ("bench_groups", ['overrides=["env.mesh.cells=-1"]'], "env.mesh.cells must be an integer"),
    ("bench_env", ['overrides=["env.nosuch=1"]'], "env.nosuch is not a setting of env"),
    ("bench_env", ['overrides=["env.dt"]'], "overrides: 'env.dt' is not key=value"),
    # memory (physicsrl-train's estimates, max_memory_gb)
    ("bench_ms", ["grid.n=100000"], "grid.n=100000 would need about 3e+04 GB (3 simulator(s)"),
    ("bench_ms", ["grid.n=2000", "max_memory_gb=1"], "more than max_memory_gb=1"),
    ("bench_ms", ["max_memory_gb=nan"], "max_memory_gb=nan: must be a finite number"),
    ("bench_env", ['overrides=["env.mesh.cells=100000"]'], "env.mesh.cells=100000 would need"),
    (
        "bench_groups",
        ['overrides=["env.model.backend=torch","env.mesh.cells=1000","env.replicas=1000"]'],
        "env.replicas=1000 would need about 48.1 GB",
    ),
    # -m sweeps: every job, before any starts
    ("train", ["-m", "iterations=-5,3"], "iterations must be an integer >= 1, got -5 (sweep job 1"),
    ("train", ["-m", "iterations=3,-5"], "got -5 (sweep job 2 of 2: iterations=-5)"),
    ("train", ["-m", "agent.lr=1e-3,inf"], "agent.lr must be a finite number > 0, got inf"),
    ("train", ["-m", "seed=0,1", "foo=1"], "unknown key 'foo'"),
    ("train", ["-m", "seed=0,1", "resume=/x"], "resume=/x: in a sweep every job would continue"),
    ("train", ["+cluster=slurm"], "SlurmLauncher (hydra/launcher) submits sweeps only: add -m"),
    ("train", ["-m", "agent.network.hidden=[64],[0]"], "agent.network.hidden[0] must be"),
    ("train", ["--multirun", "env=heat,ms", "observation=catheter"], "does not fit the heat task"),
    ("bench_ping", ["-m", "calls=10,0"], "calls=0: must be an integer >= 1 (sweep job 2"),
]


def check_of(command: str):
    """The check the command runs after composing (:func:`validate_or_exit`'s ``check``)."""
    from physicsrl.cli import bench, train
    from physicsrl.cli import eval as evaluate

    if command == "train":
        return train.check_task
    if command == "eval":
        return evaluate.check
    return lambda cfg, job: bench.check(cfg, job, command[6:])


@pytest.fixture(scope="module")
def checkpoint_file(tmp_path_factory) -> Path:
    from torchrl.checkpoint import Checkpoint, JSONCheckpointAdapter

    path = tmp_path_factory.mktemp("eval") / "ckpt.torchrl"
    Checkpoint().register("extra", {}, adapter=JSONCheckpointAdapter()).save(path, format="archive")
    return path


@pytest.mark.parametrize("command, overrides, named", ROWS)
def test_a_bad_command_line_is_one_line_naming_the_key(
    capsys, checkpoint_file, command, overrides, named
):
    from physicsrl.cli.command import validate_or_exit

    if command == "eval":
        overrides = [f"run={checkpoint_file}", *overrides]
    with pytest.raises(SystemExit) as exit_:
        validate_or_exit(command, overrides, check_of(command))
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: bad config: "), err
    assert named in lines[0], lines[0]


def test_the_benchmarks_memory_cap_is_physicsrl_train_s():
    from physicsrl.cli.command import compose
    from physicsrl.config import TrainConfig

    default = TrainConfig().max_memory_gb
    for name in ("ms", "env", "groups"):
        assert compose(f"bench_{name}", []).max_memory_gb == default
    assert compose("bench_ms", ["max_memory_gb=64"]).max_memory_gb == 64


def test_the_table_is_at_least_60_rows_over_every_command():
    assert len(ROWS) >= 60
    assert {command.split("_")[0] for command, _, _ in ROWS} == {"train", "eval", "bench"}
    assert any("-m" in overrides for _, overrides, _ in ROWS)


@pytest.mark.parametrize(
    "preset", sorted(path.stem for path in (ROOT / "conf" / "experiment").glob("*.yaml"))
)
def test_every_experiment_preset_passes_the_validation(capsys, preset):
    """The converse of the table: each ``+experiment=`` preset composes and passes every check,
    but a CUDA preset on a machine without CUDA, which gets the one line saying so."""
    import torch

    from physicsrl.cli.command import validate_or_exit

    try:
        validate_or_exit("train", [f"+experiment={preset}"], check_of("train"))
    except SystemExit as exit_:
        assert exit_.code == 2 and not torch.cuda.is_available()
        assert capsys.readouterr().err.startswith(
            "error: bad config: env.model.device=cuda: torch finds no CUDA device"
        )
    else:
        assert capsys.readouterr().err == ""


# Real commands: the line comes once, under 1 and 2 ranks, and every rank ends.
PROCESSES = [
    (1, ["physicsrl-train", "agent.network.hidden=[1000000000]"], "would need about 140 GB"),
    (2, ["physicsrl-train", "-m", "iterations=-5,3"], "(sweep job 1 of 2: iterations=-5)"),
    (2, ["physicsrl-train", "observation=catheter"], "catheter does not fit the heat task"),
    (
        2,
        ["physicsrl-train", "env=ms", "env.model.backend=torch", "mpi.ranks_per_env=2"],
        "mpi.ranks_per_env=2: env.model.backend=torch runs each group's env.replicas on one rank",
    ),
    (2, ["physicsrl-eval", f"run={RUN}", 'overrides=["nosuch=1"]'], "unknown key 'nosuch'"),
    (2, ["physicsrl-train", "-m", "seed=0,1", "--cfg", "job"], "--multirun and --cfg: Hydra"),
    (2, ["physicsrl-train", "--nosuch", "seed=1"], "--nosuch: no such flag"),
    (2, ["physicsrl-train", "resume=true"], "resume=true: no run with a checkpoint under"),
]


def test_real_commands_print_one_line_once_and_every_rank_ends(tmp_path, checkpoint_file):
    """The rows of :data:`PROCESSES`, started together (each one a command line; 2: under
    ``mpiexec -n 2``): status 2, one line on stderr, nothing on stdout, nothing written."""
    started = []
    for ranks, (program, *arguments), named in PROCESSES:
        arguments = [a.replace(RUN, str(checkpoint_file)) for a in arguments]
        launch = [str(MPIEXEC), "-n", "2"] if ranks == 2 else []
        command = [*launch, str(BIN / program), *arguments]
        cwd = tmp_path / str(len(started))
        cwd.mkdir()
        process = subprocess.Popen(
            command, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        started.append((process, cwd, named))
    for process, cwd, named in started:
        out, err = process.communicate(timeout=120)
        assert process.returncode == 2, err
        assert out == "" and len(err.splitlines()) == 1 and named in err, err
        assert not list(cwd.iterdir())  # no run directory


@pytest.mark.parametrize(
    "command, arguments, loaded",
    [
        ("train", ["iterations=-1"], []),
        ("train", ["resume=nosuch"], ["dolfinx"]),  # a valid config: its task was checked
        ("eval", ["run=nosuch"], []),
        ("eval", ["run=."], []),  # a directory without checkpoints
        ("bench", ["ping", "calls=-5"], []),
    ],
)
def test_a_bad_command_line_is_refused_before_torch_loads(tmp_path, command, arguments, loaded):
    """The refusal costs the command line's parsing (and the task's check, which imports the
    simulators), not torch's ~2 s import (the bench's took it: its tables' module imported torch
    for the CPU's name in a results file; a resume of no run, and an evaluation of a directory
    without checkpoints, took it before the checkpoints were looked for)."""
    script = (
        f"import sys; sys.argv = {['physicsrl-' + command, *arguments]!r}\n"
        f"from physicsrl.cli.{command} import main\n"
        "try:\n    main()\nfinally:\n    print(sorted({'torch', 'dolfinx'} & set(sys.modules)))"
    )
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, cwd=tmp_path
    )
    assert (result.returncode, result.stdout) == (2, f"{loaded}\n"), result.stderr
    assert len(result.stderr.splitlines()) == 1, result.stderr


def test_a_sweep_is_validated_with_its_config_s_params_and_globs(tmp_path, capsys):
    """``hydra.sweeper.params`` set by an experiment's YAML join the command line's sweep in
    the checks (its bad job ran after the good one); ``glob(...)`` of a group expands (it was
    refused: 'ConfigLoader is not set')."""
    from physicsrl.cli.command import sweep_jobs, validate_or_exit
    from physicsrl.cli.train import check_task

    experiment = tmp_path / "conf" / "experiment" / "sweep.yaml"
    experiment.parent.mkdir(parents=True)
    experiment.write_text(
        "# @package _global_\nhydra:\n  sweeper:\n    params:\n      iterations: 2,-5\n"
    )
    overrides = ["-m", f"hydra.searchpath=[file://{tmp_path / 'conf'}]", "+experiment=sweep"]
    with pytest.raises(SystemExit) as exit_:
        validate_or_exit("train", overrides, check_task)
    assert exit_.value.code == 2
    assert "got -5 (sweep job 2 of 2: iterations=-5" in capsys.readouterr().err
    jobs = sweep_jobs(["env=glob(he*)", "seed=0,1"])
    assert jobs == [["env=heat", "seed=0"], ["env=heat", "seed=1"]]


@pytest.mark.parametrize(
    "override, baselines, named",
    [
        ("observation.splines=3", False, ["stored weights do not fit", "[128, 21]", "[128, 13]"]),
        ("env.model.dt=0.2", True, ["overrides: 10 reset draws in a row gave non-finite"]),
    ],
)
def test_eval_overrides_that_the_stored_run_cannot_take_are_one_line_on_two_ranks(
    tmp_path, override, baselines, named
):
    """The report's stored ATP agent with a 3-spline catheter (13 inputs where it has 21): its
    size is known once the env is built, then one line names the shapes and every rank ends
    with status 2 (it was a 21-line traceback). With dt = 0.2 every reset diverges (the
    stimulus blows up under forward Euler), here found by the baselines' search for the best
    single shock: one line, status 2 (it was a traceback)."""
    stored = ROOT / "experiments" / "results" / "atp_agent.torchrl"
    options = ["seeds=1", "gif=false", "curve=false", f"baselines={str(baselines).lower()}"]
    command = [str(MPIEXEC), "-n", "2", str(BIN / "physicsrl-eval"), f"run={stored}", *options]
    result = subprocess.run(
        [*command, f'overrides=["{override}"]', f"hydra.run.dir={tmp_path}"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2, result.stderr
    [line] = [line for line in result.stderr.splitlines() if line.startswith("error")]
    assert all(text in line for text in named), line
    assert "Traceback" not in result.stderr
