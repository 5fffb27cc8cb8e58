"""Console entry points under MPI: self-launch, one Hydra run directory, leader-only output.

Every ``physicsrl-*`` command runs either under a launcher (``mpiexec -n 4 physicsrl-train``,
``srun``) or self-launched with the override ``mpi.ranks=4``, which re-executes the command
under the ``mpiexec`` that belongs to the installed MPI. All ranks then agree on the run
directory (Hydra's default is a per-process timestamp, and ranks start seconds apart), only the
leader writes Hydra's files and logs, and an exception on any rank ends every rank with a
non-zero exit instead of leaving the others waiting (Hydra alone would catch it and exit 1).
Bad launch requests (``mpi.ranks=abc``, ``mpi.ranks_per_env`` that does not divide the ranks
into groups, a run directory that cannot be written) end every rank with status 2 and one line
from the leader, before any work.
"""

from __future__ import annotations

import contextlib
import io
import math
import os
import re
import shutil
import sys
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import NoReturn

RANKS = re.compile(r"^\+{0,2}mpi\.ranks=(.*)$")
LAUNCHER_SIZE = ("PMI_SIZE", "OMPI_COMM_WORLD_SIZE", "PMIX_SIZE", "MPI_LOCALNRANKS")
LAUNCHER_RANK = ("PMI_RANK", "OMPI_COMM_WORLD_RANK", "PMIX_RANK", "SLURM_PROCID")
CONFIGS = "pkg://physicsrl.conf"
# Hydra flags that print something and run no job: only the leader runs them.
PRINT_ONLY = ("help", "hydra_help", "cfg", "info", "shell_completion")


def refuse(message: str) -> NoReturn:
    """End this rank with status 2; the leader prints ``error: message`` (one line per job)."""
    if launched_rank() == 0:
        print(f"error: {message}", file=sys.stderr)
    raise SystemExit(2)


@dataclass(frozen=True)
class Job:
    """Where each job of a command runs: on ``ranks`` MPI ranks, on this machine or not (Hydra's
    Slurm launcher submits each job of a sweep to run elsewhere)."""

    ranks: int
    here: bool = True

    @classmethod
    def local(cls) -> Job:
        """This process's job: the ranks its MPI launcher started (1 without one)."""
        return cls(launched_size() or 1)


def launched_size() -> int | None:
    """The number of ranks the MPI launcher started, or None when started without one."""
    for variable in LAUNCHER_SIZE:
        if variable in os.environ:
            return int(os.environ[variable])
    return None


def launched_rank() -> int:
    """This process's rank as the MPI launcher numbered it (0 without a launcher)."""
    for variable in LAUNCHER_RANK:
        if variable in os.environ:
            return int(os.environ[variable])
    return 0


def requested_ranks(overrides: list[str]) -> int | None:
    """The last ``mpi.ranks=N`` among the command-line overrides."""
    ranks = None
    for override in overrides:
        if match := RANKS.match(override):
            ranks = match.group(1)
    if ranks is None:
        return None
    if "," in ranks:
        refuse(
            f"mpi.ranks={ranks}: the number of ranks cannot be swept (it launches the "
            "command): run one sweep per number of ranks"
        )
    if not ranks.strip().isdigit() or int(ranks) < 1:
        refuse(f"mpi.ranks={ranks}: the number of ranks must be an integer >= 1")
    return int(ranks)


def mpiexec() -> str:
    """The ``mpiexec`` of this environment's MPI (the mpich wheel puts it beside python)."""
    beside = Path(sys.executable).with_name("mpiexec")
    found = str(beside) if beside.exists() else shutil.which("mpiexec")
    if found is None:
        refuse("mpi.ranks needs mpiexec, which is neither beside python nor on PATH")
    return found


TIMEOUT_ENV = "PHYSICSRL_TIMEOUT"
CHECK_ENV = "PHYSICSRL_CHECK_SEQUENCE"


def timeout_from_environment() -> float | None:
    """The coordinator's watchdog timeout, ``PHYSICSRL_TIMEOUT`` seconds (None: unset or
    empty); ValueError unless it is a number > 0."""
    text = os.environ.get(TIMEOUT_ENV, "").strip()
    if not text:
        return None
    try:
        seconds = float(text)
    except ValueError:
        seconds = math.nan
    if not seconds > 0 or math.isinf(seconds):
        raise ValueError(f"{TIMEOUT_ENV}={text!r}: must be a number of seconds > 0")
    return seconds


def check_sequence_from_environment() -> bool:
    """Whether ``PHYSICSRL_CHECK_SEQUENCE`` (0 or 1; unset: 0) asks the coordinator to check
    every call's sequence; ValueError otherwise."""
    text = os.environ.get(CHECK_ENV, "0").strip() or "0"
    if text not in ("0", "1"):
        raise ValueError(f"{CHECK_ENV}={text!r}: must be 0 or 1")
    return text == "1"


def relaunch(overrides: list[str]) -> None:
    """Re-execute this command under mpiexec if ``mpi.ranks=N`` asks for more ranks.

    Under a launcher the request must match the launcher's size; nothing happens otherwise.
    The coordinator's environment variables are checked first (one line, status 2).
    """
    try:
        timeout_from_environment(), check_sequence_from_environment()
    except ValueError as error:
        refuse(str(error))
    ranks = requested_ranks(overrides)
    size = launched_size()
    if ranks is None or ranks == (size or 1):
        return
    if size is not None:
        refuse(f"mpi.ranks={ranks}, but the MPI launcher started {size} ranks")
    os.environ["PYTHONUNBUFFERED"] = "1"
    command = [mpiexec(), "-n", str(ranks), sys.executable, sys.argv[0], *sys.argv[1:]]
    os.execv(command[0], command)


def run_hydra(config_name: str, task: Callable, arguments: list[str]) -> None:
    """Run ``task(cfg)`` as a Hydra app with command-line ``arguments`` on every rank."""
    import hydra
    from mpi4py import MPI
    from omegaconf import OmegaConf

    from physicsrl.coordinated import abort_on_error

    comm = MPI.COMM_WORLD
    started = comm.bcast(datetime.now() if comm.rank == 0 else None, root=0)
    OmegaConf.register_new_resolver(
        "leader_now", lambda pattern: started.strftime(pattern), replace=True
    )
    # Hydra takes flags first and overrides as one run of positional arguments: add ours there.
    from hydra._internal.utils import get_args_parser

    # the overrides apart, so that an optional flag value (--info) cannot take one
    overrides = [a for a in arguments if not a.startswith("-") and ("=" in a or a[:1] == "~")]
    rest = [argument for argument in arguments if argument not in overrides]
    with contextlib.redirect_stderr(sys.stderr if comm.rank == 0 else io.StringIO()):
        parsed, unknown = get_args_parser().parse_known_args(rest)  # usage errors: status 2
    modes = [
        f"--{m}"
        for m in ("run", "multirun", "cfg", "info", "shell_completion")
        if getattr(parsed, m)
    ]
    if len(modes) > 1:  # Hydra's own refusal is a traceback
        refuse(f"{' and '.join(modes)}: Hydra takes one of --run, --multirun (-m), --cfg, --info")
    unknown_flags = [u for u in unknown if u.startswith("-")]
    if unknown_flags:  # Hydra's refusal is its usage, from every rank
        refuse(f"{unknown_flags[0]}: no such flag (--help lists them)")
    if comm.rank != 0 and any(getattr(parsed, flag) for flag in PRINT_ONLY):
        return
    given = overrides + parsed.overrides + [u for u in unknown if not u.startswith("-")]
    flags = [argument for argument in arguments if argument not in given]
    extra = [f"hydra.job.name={config_name}"]  # names the log file
    if comm.rank != 0:
        extra += [
            "hydra.output_subdir=null",
            "hydra/job_logging=disabled",
            "hydra/hydra_logging=disabled",
        ]

    def guarded(cfg) -> None:
        with abort_on_error(comm):
            task(cfg)

    # Flags last: a bare ``--info`` would take the next override as its value.
    sys.argv = [sys.argv[0], *given, *extra, *flags]
    hydra.main(config_path=CONFIGS, config_name=config_name, version_base=None)(guarded)()


def output_dir() -> Path:
    """The run directory of the current Hydra job (the same on every rank)."""
    from hydra.core.hydra_config import HydraConfig

    return Path(HydraConfig.get().runtime.output_dir)


def sweeping() -> bool:
    """Whether the current Hydra job is one job of a sweep (``-m``); False outside Hydra."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def check_layout(ranks_per_env: int, world_size: int) -> None:
    """ValueError in one line unless ``ranks_per_env`` is a divisor of ``world_size``."""
    if not (isinstance(ranks_per_env, int) and 1 <= ranks_per_env <= world_size):
        raise ValueError(
            f"mpi.ranks_per_env={ranks_per_env!r} must be an integer from 1 to the job's "
            f"{world_size} ranks"
        )
    if world_size % ranks_per_env:
        raise ValueError(
            f"mpi.ranks_per_env={ranks_per_env} does not divide the job's {world_size} ranks "
            "into groups"
        )


def check_backend(backend: str | None, ranks_per_env: int, device: str | None = None) -> None:
    """ValueError in one line if ``env.model.backend`` is ``torch`` with groups of more than
    one rank (each group's replicas, ``env.replicas``, run on one rank), or on ``device`` cuda
    where torch finds no CUDA device."""
    if backend == "torch" and ranks_per_env != 1:
        raise ValueError(
            f"mpi.ranks_per_env={ranks_per_env}: env.model.backend=torch runs each group's "
            "env.replicas on one rank (mpi.ranks_per_env=1)"
        )
    if backend == "torch" and device == "cuda":
        import torch  # seconds: only for a run on the GPU

        if not torch.cuda.is_available():
            raise ValueError(
                "env.model.device=cuda: torch finds no CUDA device on this machine "
                "(env.model.device=cpu runs the replicas on its CPU)"
            )
