"""Console entry points: MPI self-launch, one run directory, leader-only files, wheel install."""

import json
import os
import shlex
import subprocess
import sys
import sysconfig
import tomllib
import zipfile
from functools import partial
from pathlib import Path

import pytest

from tests.conftest import MPIEXEC, ROOT, together

BIN = Path(sys.executable).parent
QUICK = ["calls=2000", "repeats=1", "idle_seconds=0.1"]


def run(command, cwd, timeout=120, env=None):
    return subprocess.run(
        command,
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**os.environ, **(env or {})},
    )


def run_directories(root: Path) -> list[Path]:
    return sorted(p.parent for p in root.glob("outputs/bench_ping/*/ping.csv"))


@pytest.mark.parametrize(
    "launch",
    [
        [str(BIN / "physicsrl-bench"), "ping", *QUICK, "mpi.ranks=2"],
        [str(MPIEXEC), "-n", "2", str(BIN / "physicsrl-bench"), "ping", *QUICK],
    ],
    ids=["self-launched", "mpiexec"],
)
def test_ranks_share_one_run_directory_and_only_the_leader_writes(tmp_path, launch):
    result = run(launch, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert result.stdout.count("floor (Bcast 16 B)") == 1  # the table, printed once
    assert "2      physicsrl " in result.stdout  # measured on 2 ranks
    [directory] = run_directories(tmp_path)
    assert sorted(p.name for p in directory.iterdir()) == [
        ".hydra",
        "bench_ping.log",
        "ping.csv",
        "ping.json",
    ]
    assert len(list(tmp_path.rglob(".hydra"))) == 1
    recorded = json.loads((directory / "ping.json").read_text())["command"]
    assert recorded == shlex.join(["physicsrl-bench", "ping", *launch[launch.index("ping") + 1 :]])


def test_mismatched_rank_request_is_a_one_line_error(tmp_path):
    launch = [str(MPIEXEC), "-n", "2", str(BIN / "physicsrl-bench"), "ping", "mpi.ranks=3"]
    result = run(launch, cwd=tmp_path, timeout=60)
    assert result.returncode != 0
    assert "error: mpi.ranks=3, but the MPI launcher started 2 ranks" in result.stderr


@pytest.mark.parametrize(
    "arguments, expected",
    [
        (["pong"], "unknown benchmark 'pong'"),
        (["calls=10"], "calls=10: the first argument names the benchmark"),
        (["-m", "ping", "calls=10,20"], "-m: the first argument names the benchmark"),
    ],
)
def test_unknown_benchmark_is_a_one_line_error(tmp_path, arguments, expected):
    result = run([str(BIN / "physicsrl-bench"), *arguments], cwd=tmp_path)
    assert result.returncode == 2
    assert result.stderr.strip() == f"error: {expected}; choose one of ping, ms, env, groups"


FAULTY_REWARD = """
from dataclasses import dataclass

from physicsrl.envs import REWARDS, Reward


@REWARDS.register("faulty")
@dataclass(frozen=True)
class Faulty(Reward):
    def __call__(self, events):
        raise RuntimeError("the user's reward failed")
"""


def test_an_exception_inside_a_hydra_command_ends_every_rank(tmp_path):
    """A user's reward that raises at the first step, on the leader, while the follower waits
    in the simulator's next call: Hydra alone would catch it and leave the follower waiting.
    Every rank ends, non-zero, with the traceback once."""
    (tmp_path / "faulty.py").write_text(FAULTY_REWARD)
    (tmp_path / "conf" / "reward").mkdir(parents=True)
    (tmp_path / "conf" / "reward" / "faulty.yaml").write_text("name: faulty\nmodule: faulty.py\n")
    settings = [f"hydra.searchpath=[file://{tmp_path / 'conf'}]", "reward=faulty", "mpi.ranks=2"]
    result = run([str(BIN / "physicsrl-train"), *settings], cwd=tmp_path, timeout=90)
    assert result.returncode != 0
    assert result.stderr.count("RuntimeError: the user's reward failed") == 1, result.stderr


@pytest.mark.parametrize(
    "variable, value, message",
    [
        ("PHYSICSRL_TIMEOUT", "abc", "PHYSICSRL_TIMEOUT='abc': must be a number of seconds > 0"),
        ("PHYSICSRL_TIMEOUT", "-1", "PHYSICSRL_TIMEOUT='-1': must be a number of seconds > 0"),
        ("PHYSICSRL_CHECK_SEQUENCE", "yes", "PHYSICSRL_CHECK_SEQUENCE='yes': must be 0 or 1"),
    ],
)
def test_a_bad_coordinator_variable_is_a_one_line_error_before_launching(
    tmp_path, variable, value, message
):
    command = [str(BIN / "physicsrl-bench"), "ping", "mpi.ranks=2"]
    result = run(command, cwd=tmp_path, env={**os.environ, variable: value})
    assert (result.returncode, result.stderr) == (2, f"error: {message}\n")


@pytest.mark.parametrize(
    "settings, message",
    [
        (["ping", "calls=-5"], "bad config: calls=-5: must be an integer >= 1"),
        (["ping", "calls=0"], "bad config: calls=0: must be an integer >= 1"),
        (["ping", "calls=abc", "mpi.ranks=2"], "bad config: calls=abc: must be an integer >= 1"),
        (["ping", "repeats=1.5"], "bad config: repeats=1.5: must be an integer >= 1"),
        (
            ["ping", "idle_seconds=nan"],
            "bad config: idle_seconds=nan: must be a finite number >= 0.0",
        ),
        (["ms", "grid.n=1"], "bad config: grid.n=1: must be an integer >= 2"),
        (["ms", "baseline=maybe"], "bad config: baseline=maybe: must be true or false"),
        (["env", "decisions=0", "mpi.ranks=2"], "bad config: decisions=0: must be an integer >= 1"),
        (["ping", "mpi.ranks=abc"], "mpi.ranks=abc: the number of ranks must be an integer >= 1"),
        (["ping", "mpi.ranks=-1"], "mpi.ranks=-1: the number of ranks must be an integer >= 1"),
        (
            ["ping", "-m", "mpi.ranks=1,2"],
            "mpi.ranks=1,2: the number of ranks cannot be swept (it launches the command): run "
            "one sweep per number of ranks",
        ),
    ],
)
def test_bad_benchmark_settings_are_one_line_errors(tmp_path, settings, message):
    result = run([str(BIN / "physicsrl-bench"), *settings], cwd=tmp_path, timeout=60)
    assert (result.returncode, result.stderr, result.stdout) == (2, f"error: {message}\n", "")


@pytest.mark.parametrize("ranks", ["mpi.ranks=1", "mpi.ranks=2"])
@pytest.mark.parametrize("where", ["proc", "file"])
def test_a_run_directory_that_cannot_be_written_ends_every_rank_in_one_line(tmp_path, ranks, where):
    (tmp_path / "a-file").write_text("")
    directory = {"proc": "/proc/forbidden", "file": str(tmp_path / "a-file" / "run")}[where]
    launch = [str(BIN / "physicsrl-bench"), "ping", *QUICK, f"hydra.run.dir={directory}", ranks]
    result = run(launch, cwd=tmp_path, timeout=60)
    assert result.returncode == 2, result.stderr
    [line] = result.stderr.splitlines()
    assert line.startswith(f"error: hydra.run.dir={directory}: cannot write the run directory")


def test_a_sweep_directory_that_cannot_be_written_is_one_line(tmp_path):
    launch = [str(BIN / "physicsrl-bench"), "ping", "-m", "calls=10,20", "hydra.sweep.dir=/proc/x"]
    result = run([*launch, "mpi.ranks=2"], cwd=tmp_path, timeout=60)
    assert result.returncode == 2, result.stderr
    assert result.stderr.startswith("error: hydra.sweep.dir=/proc/x: cannot write the run")
    assert len(result.stderr.splitlines()) == 1


def test_a_new_run_refuses_a_directory_that_holds_another_runs_checkpoints(tmp_path):
    """A new training run or sweep, or an evaluation, into a directory with checkpoints ends
    every rank in one line before Hydra writes there (the runs' checkpoints mixed: an
    evaluation then read the other run's policy; an evaluation replaced the run's eval.csv,
    its learning curve); resume=true is how to continue it. An evaluation into an earlier
    one's directory too (its GIF stayed beside the new tables). The four commands run at the
    same time."""
    train = [str(BIN / "physicsrl-train"), "iterations=1", "env.mesh.cells=8"]
    evaluate = [str(BIN / "physicsrl-eval"), f"run={tmp_path / 'run'}"]
    for directory, where in ((tmp_path / "run", "."), (tmp_path / "sweep", "1")):
        checkpoints = directory / where / "checkpoints"
        checkpoints.mkdir(parents=True)
        (checkpoints / "ckpt-000000000002.torchrl").write_text("")
    (tmp_path / "run" / "eval.csv").write_text("iteration,return\n2,1.0\n")
    (tmp_path / "evaluated").mkdir()
    (tmp_path / "evaluated" / "eval_summary.csv").write_text("policy,return\n")
    checkpoints = "holds a training run's checkpoints; resume=true continues it"
    runs = [
        (
            "hydra.run.dir",
            [*train, f"hydra.run.dir={tmp_path / 'run'}", "mpi.ranks=2"],
            checkpoints,
        ),
        (
            "hydra.sweep.dir",
            [*train, "-m", "seed=0,1", f"hydra.sweep.dir={tmp_path / 'sweep'}"],
            "holds training runs' checkpoints in its subdirectories; resume=true continues a sweep",
        ),
        ("hydra.run.dir", [*evaluate, f"hydra.run.dir={tmp_path / 'run'}"], checkpoints),
        (
            "hydra.run.dir",
            [*evaluate, f"hydra.run.dir={tmp_path / 'evaluated'}"],
            "holds an earlier evaluation's results",
        ),
    ]
    results = together(*(partial(run, command, cwd=tmp_path) for _, command, _ in runs))
    for (key, _, named), result in zip(runs, results, strict=True):
        assert result.returncode == 2, result.stderr
        [line] = result.stderr.splitlines()
        assert line.startswith(f"error: {key}=") and named in line, line
    assert not (tmp_path / "run" / ".hydra").exists()
    assert (tmp_path / "run" / "eval.csv").read_text() == "iteration,return\n2,1.0\n"


def test_commands_started_together_get_run_directories_of_their_own(tmp_path):
    """The default run directory is the leader's start time to the microsecond: two commands
    started in the same second wrote into one directory (three evaluations kept one's
    results, and all three printed its path)."""
    command = [str(BIN / "physicsrl-bench"), "ping", *QUICK]
    environment = {**os.environ, "PYTHONUNBUFFERED": "1"}
    started = [
        subprocess.Popen(command, cwd=tmp_path, env=environment, stdout=subprocess.PIPE, text=True)
        for _ in range(2)
    ]
    outputs = [process.communicate(timeout=120)[0] for process in started]
    assert [process.returncode for process in started] == [0, 0]
    results = [
        line.split()[-1] for out in outputs for line in out.splitlines() if "results" in line
    ]
    directories = sorted((tmp_path / "outputs" / "bench_ping").iterdir())
    assert len(directories) == 2 and sorted(Path(r).parent for r in results) == directories


def test_print_only_flags_print_once_under_two_ranks(tmp_path):
    bench = str(BIN / "physicsrl-bench")
    config = run([bench, "ping", "--cfg", "job", "mpi.ranks=2"], cwd=tmp_path, timeout=60)
    assert config.returncode == 0 and config.stdout.count("calls: 200000") == 1, config.stdout
    info = run([bench, "ping", "--info"], cwd=tmp_path, timeout=60)
    assert info.returncode == 0 and "Defaults List" in info.stdout, info.stderr
    # an override after --info is not taken for its value (argparse's usage, once per rank)
    info = run([bench, "ping", "--info", "calls=10", "mpi.ranks=2"], cwd=tmp_path, timeout=60)
    assert info.returncode == 0 and info.stdout.count("Defaults List") == 1, info.stderr


def test_print_only_flags_resolve_the_benchmarks_defaults(tmp_path):
    """``physicsrl-bench ms --cfg job --resolve`` prints the memory cap that the YAML takes
    from the training's default (``${train_default:max_memory_gb}``); it raised
    ``UnsupportedInterpolationType``: the resolvers were registered by the checks, which
    print-only flags skip."""
    from physicsrl.config import train_default

    bench = str(BIN / "physicsrl-bench")
    config = run([bench, "ms", "--cfg", "job", "--resolve"], cwd=tmp_path, timeout=60)
    assert config.returncode == 0, config.stderr
    assert f"max_memory_gb: {train_default('max_memory_gb')}" in config.stdout.splitlines()


@pytest.mark.parametrize(
    "command", [["physicsrl-train"], ["physicsrl-eval"], ["physicsrl-bench", "ping"]]
)
def test_help_says_what_the_command_does_once_under_two_ranks(tmp_path, command):
    helped = run([str(BIN / command[0]), *command[1:], "--help", "mpi.ranks=2"], cwd=tmp_path)
    assert helped.returncode == 0, helped.stderr
    assert helped.stdout.startswith(" ".join(command)), helped.stdout[:200]
    assert helped.stdout.count("--hydra-help lists Hydra's own flags") == 1, helped.stdout


def test_without_dolfinx_the_simulators_say_how_to_install_it():
    """``pip install physicsrl`` without the ``fem`` extra, on a machine without DOLFINx: the
    import names the extra (it said ``No module named 'dolfinx'``)."""
    hidden = "import sys; sys.modules['dolfinx'] = None; import physicsrl.envs"
    result = subprocess.run([sys.executable, "-c", hidden], capture_output=True, text=True)
    assert result.returncode == 1
    assert result.stderr.splitlines()[-1] == (
        "ImportError: physicsrl's simulators need DOLFINx 0.11 (with petsc4py and mpi4py): pip "
        "install 'physicsrl[fem]' for the wheels, or load your site's DOLFINx"
    )


def test_configs_are_found_from_a_built_wheel(tmp_path):
    """Build the wheel, install it alone into a fresh venv, run the console script elsewhere.

    The fresh venv borrows the heavy dependencies (torch, DOLFINx, MPI) from the test's
    environment through a .pth file; physicsrl itself comes only from the wheel, and its
    ``__version__`` is pyproject's. The wheel carries the license that pyproject declares, with
    its text.
    """
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "-q",
            "--no-deps",
            "--no-build-isolation",
            str(ROOT),
            "-w",
            str(tmp_path / "dist"),
        ],
        check=True,
        capture_output=True,
        timeout=300,
    )
    fresh = tmp_path / "fresh"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(fresh)], check=True)
    site = next((fresh / "lib").glob("python3*/site-packages"))
    (site / "dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    [wheel] = (tmp_path / "dist").glob("physicsrl-*.whl")
    with zipfile.ZipFile(wheel) as archive:
        [metadata] = [n for n in archive.namelist() if n.endswith(".dist-info/METADATA")]
        assert "License-Expression: MIT" in archive.read(metadata).decode().splitlines()
        licence = metadata.replace("METADATA", "licenses/LICENSE")
        assert archive.read(licence) == (ROOT / "LICENSE").read_bytes()
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "--python",
            str(fresh / "bin" / "python"),
            "install",
            "-q",
            "--no-deps",
            str(wheel),
        ],
        check=True,
        capture_output=True,
        timeout=300,
    )
    env = {"LD_LIBRARY_PATH": str(BIN.parent / "lib")}  # the mpich wheel's libmpi
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    result = run([str(fresh / "bin" / "physicsrl-bench"), "--help"], cwd=elsewhere, env=env)
    assert result.returncode == 0 and "ping" in result.stdout
    result = run(
        [str(fresh / "bin" / "physicsrl-bench"), "ping", "--cfg", "job"], elsewhere, env=env
    )
    assert result.returncode == 0, result.stderr
    assert "calls: 200000" in result.stdout
    where = run(
        [
            str(fresh / "bin" / "python"),
            "-c",
            "import physicsrl; print(physicsrl.__file__, physicsrl.__version__)",
        ],
        elsewhere,
        env=env,
    )
    path, version = where.stdout.split()
    assert path.startswith(str(site))
    with open(ROOT / "pyproject.toml", "rb") as pyproject:
        assert version == tomllib.load(pyproject)["project"]["version"]


@pytest.mark.parametrize("status", [3])
@pytest.mark.parametrize("ranks", [2, 3])
def test_a_vanished_follower_ends_the_job_at_once_with_its_status(mpi, ranks, status):
    """Unguarded, a follower that calls ``os._exit(K)``, K > 0, in a parallel call: MPICH's
    mpiexec kills every other rank (SIGKILL, no handler runs) and returns the status of the
    first process it sees end, K or 9 (a killed one), so the job ends at once but no rank can
    name the vanished one. ``os._exit(0)`` is not tested unguarded: it usually ends the job
    with status 0, and under load it once left the others waiting (the guard's case)."""
    script = "tests/mpi_scripts/coord_exit.py"
    result = mpi(ranks, script, f"vanish-{status}", timeout=30, check=False)
    assert result.returncode in (status, 9), result.stderr
    assert "finished" not in result.stderr and "Traceback" not in result.stderr


@pytest.mark.parametrize("status", ["0", "3", "SIGKILL"])
@pytest.mark.parametrize("ranks", [2, 3])
def test_a_guarded_rank_that_vanishes_is_named_and_fails_the_job(mpi, ranks, status):
    """The same under ``python -m physicsrl.guard``, and a rank killed by SIGKILL (the OOM
    killer): the vanished rank's guard names it in one line and aborts the job with its status
    (1 for ``os._exit(0)``, 128 + 9 for SIGKILL), whichever rank the launcher sees end first.

    When the guard only exited non-zero, MPICH's launcher returned the first status it saw (1,
    or 9 for the rank it killed) and, about once in 1,000 runs (twice in CI), left the other
    ranks waiting: its proxy idled in ``poll`` with the guard reaped. The test still runs a job
    that has not ended after 10 s (a job takes ~1.5 s) once more: a second hang fails it."""
    guarded = ["-m", "physicsrl.guard", "tests/mpi_scripts/coord_exit.py", f"vanish-{status}"]
    try:
        result = mpi(ranks, *guarded, timeout=10, check=False)
    except subprocess.TimeoutExpired:
        result = mpi(ranks, *guarded, timeout=30, check=False)
    assert result.returncode == {"0": 1, "3": 3, "SIGKILL": 128 + 9}[status], result.stderr
    [line] = [line for line in result.stderr.splitlines() if "ended before" in line]
    how = "killed by SIGKILL" if status == "SIGKILL" else f"exited with status {status}"
    assert line == (
        f"error: rank {ranks - 1} ended before its job did ({how}); the launcher ends every rank"
    )
    assert "finished" not in result.stderr and "Traceback" not in result.stderr


@pytest.mark.parametrize("where", ["everywhere", "last"])
def test_a_guarded_scripts_own_exception_ends_every_rank_with_one_traceback(mpi, where):
    """An exception in a guarded script's own code, outside any ``with coordinator`` block: a
    bad setting that every rank reads alike, or the last rank failing while the others wait in
    a collective. Every rank ends with status 1 and the traceback is printed once (it was
    printed by every rank), by the leader when it fails too."""
    script = ["-m", "physicsrl.guard", "tests/mpi_scripts/coord_exit.py", f"raise-{where}"]
    result = mpi(3, *script, timeout=30, check=False)
    assert result.returncode == 1, result.stderr
    assert result.stderr.count("Traceback") == 1, result.stderr
    rank = 0 if where == "everywhere" else 2
    assert f"ValueError: a bad setting, read on rank {rank}\n" in result.stderr, result.stderr


def test_the_guard_runs_a_module_and_refuses_a_missing_script_in_one_line(mpi):
    guarded = ["-m", "physicsrl.guard", "-m", "tests.mpi_scripts.coord_exit", "exit-3"]
    result = mpi(2, *guarded, timeout=30, check=False)
    assert result.returncode == 3 and not result.stderr, result.stderr
    result = mpi(2, "-m", "physicsrl.guard", "nosuch.py", timeout=30, check=False)
    assert (result.returncode, result.stderr) == (2, "error: no script nosuch.py\n")
    result = mpi(2, "-m", "physicsrl.guard", "-m", "no.such.module", timeout=30, check=False)
    assert (result.returncode, result.stderr) == (2, "error: no module no.such.module\n")


@pytest.mark.parametrize("ranks", [2, 3])
def test_a_vanished_follower_under_the_watchdog_is_named(ranks):
    """``mpiexec -disable-auto-cleanup`` with ``PHYSICSRL_TIMEOUT``: the survivors wait for the
    vanished rank in the call's collective until the watchdog aborts the job, non-zero, naming
    the ranks whose call did not finish (the vanished one among them)."""
    launch = [str(MPIEXEC), "-disable-auto-cleanup", "-n", str(ranks), sys.executable]
    result = subprocess.run(
        [*launch, "tests/mpi_scripts/coord_exit.py", "vanish-0"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT), "PHYSICSRL_TIMEOUT": "1"},
    )
    assert result.returncode != 0
    [line] = [line for line in result.stderr.splitlines() if line.startswith("watchdog:")]
    assert "not finished after 1 s on ranks [0, " in line and f"{ranks - 1}]" in line, line


def test_a_cuda_run_is_refused_in_one_line_where_torch_finds_no_cuda_device(tmp_path):
    """``env.model.device=cuda`` (the GPU presets) is checked before anything is built: one line
    where torch finds no CUDA device, nothing where it does (as on the GPU machines)."""
    import torch

    from physicsrl.launch import check_backend

    if torch.cuda.is_available():
        check_backend("torch", 1, "cuda")
        return
    with pytest.raises(ValueError, match="env.model.device=cuda: torch finds no CUDA device"):
        check_backend("torch", 1, "cuda")
    command = [str(BIN / "physicsrl-train"), "+experiment=atp_resolved_timing_batched"]
    result = run([*command, "env.mesh.cells=12", "env.replicas=2"], cwd=tmp_path, timeout=120)
    assert result.returncode == 2 and len(result.stderr.splitlines()) == 1, result.stderr
    assert "torch finds no CUDA device" in result.stderr and not list(tmp_path.iterdir())
