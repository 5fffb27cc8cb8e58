"""What every ``physicsrl-*`` command does with its command line before running: compose the
config, check it on every rank, and turn a bad value into one line naming the key (exit status
2, printed by the leader only).

The tasks are imported inside the commands' checks: they import MPI (through the simulators),
which must not start before :func:`~physicsrl.launch.relaunch` re-executes the command under
``mpiexec``. The job's own code (torch, TorchRL: ~6 s) is imported after the checks, so that a
bad command line is answered in about a second.
"""

from __future__ import annotations

import dataclasses
import shutil
import subprocess
import sys
from collections.abc import Callable
from typing import NoReturn

from hydra import compose as hydra_compose
from hydra import initialize_config_module
from hydra._internal.config_loader_impl import ConfigLoaderImpl
from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra._internal.utils import create_config_search_path
from hydra.core.global_hydra import GlobalHydra
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import MissingMandatoryValue, OmegaConf

from physicsrl.config import check_sweep_resume, register, typed
from physicsrl.guard import guard
from physicsrl.imports import load_object
from physicsrl.launch import Job, refuse, relaunch, run_hydra

MULTIRUN = {"-m", "--multirun"}
CONFIG_MODULE = "physicsrl.conf"  # the shipped configs (a user's come by hydra.searchpath)


def one_line(error: BaseException) -> str:
    """A one-line description of a config error, naming the key."""
    chain, seen = [], error
    while seen is not None:
        chain.append(seen)
        seen = seen.__cause__ or seen.__context__
    for item in chain:
        missing = getattr(item, "missing_cfg_file", None)  # Hydra's MissingConfigException
        if missing and getattr(item, "options", None):
            group, _, name = missing.rpartition("/")
            return f"{group}={name}: no such option (choose one of {', '.join(item.options)})"
        if getattr(item, "override", None):  # Hydra's OverrideParseException
            reason = str(item).splitlines()[0]
            key, _, value = item.override.partition("=")
            if "=" in value:  # Hydra reads an unquoted '=' as a second assignment
                reason += f" (quote the items that hold '=': {key}='[\"a=1\"]')"
            return f"cannot parse the override '{item.override}': {reason}"
        key = getattr(item, "full_key", None)
        if key and isinstance(item, MissingMandatoryValue):
            return f"{key} is required"
        if key:
            message = str(item).splitlines()[0]
            if "not in" in message or "Could not append" in message or "Key '" in message:
                return f"unknown key '{key}': {message}"
            return f"bad value for '{key}': {message}"
    message = " ".join(str(chain[-1]).split()).split(" Config search path")[0]
    return message or type(chain[-1]).__name__


def compose(config_name: str, overrides: list[str], hydra: bool = False):
    """The job config (no Hydra section: the command line's Hydra settings are left out, but
    where to find configs), or with ``hydra`` the whole config (``overrides`` without
    sweeps); ValueError with a one-line message."""
    register()
    if not hydra:
        overrides = [
            o
            for o in overrides
            if o.startswith("hydra.searchpath")
            or not o.lstrip("+~").startswith(("hydra.", "hydra/"))
        ]
    GlobalHydra.instance().clear()
    try:
        with initialize_config_module(config_module=CONFIG_MODULE, version_base=None):
            return hydra_compose(config_name, overrides=overrides, return_hydra_config=hydra)
    except Exception as error:  # noqa: BLE001 - Hydra and OmegaConf raise many kinds
        raise ValueError(one_line(error)) from error
    finally:
        GlobalHydra.instance().clear()


def validate_or_exit(config_name: str, overrides: list[str], check: Callable) -> None:
    """Make the schemas and resolvers known (:func:`~physicsrl.config.register`: Hydra's
    print-only flags resolve them too), then compose the config of the command line, run every
    range check of its schema and ``check(cfg, job)`` on this rank (``job``: where it runs,
    :func:`sweep`), for the job or, with ``-m``, every job of the sweep (Hydra's basic sweeper:
    the product of the comma-separated values) before any starts; nothing with Hydra's
    print-only flags. On error the leader prints one line (naming the sweep's job) and every
    rank exits with status 2 (all ranks see the same config, so no rank waits)."""
    register()
    flags = {o for o in overrides if o.startswith("-")}
    if not flags <= MULTIRUN:
        return
    arguments = [o for o in overrides if o not in flags]
    try:
        jobs, place = (
            sweep(config_name, arguments)
            if flags
            else ([arguments], run_place(config_name, arguments))
        )
        for number, job in enumerate(jobs, 1):
            try:
                cfg = validate(config_name, job, check, place)
                if flags and "resume" in cfg:
                    check_sweep_resume(cfg.resume)
            except ValueError as error:
                if not flags:
                    raise
                chosen = " ".join(o for o in job if not o.startswith("hydra"))
                raise ValueError(
                    f"{error.args[0]} (sweep job {number} of {len(jobs)}: {chosen})"
                ) from error
    except ValueError as error:
        refuse_config(error)


def refuse_config(error: ValueError | str) -> NoReturn:
    """The leader prints ``error: bad config: <one line>``; every rank exits with status 2."""
    message = error.args[0] if isinstance(error, ValueError) and error.args else str(error)
    refuse(f"bad config: {' '.join(str(message).split())}")


def validate(config_name: str, overrides: list[str], check: Callable, place: Job):
    """Compose, type (a config with a schema) and ``check(cfg, place)`` the config of
    ``overrides``, a job that runs at ``place``; return it. ValueError with one line."""
    try:
        cfg = compose(config_name, overrides)
        if dataclasses.is_dataclass(OmegaConf.get_type(cfg)):
            typed(cfg)
        check(cfg, place)
    except ValueError:
        raise
    except Exception as error:  # noqa: BLE001 - OmegaConf's errors name the key
        raise ValueError(one_line(error)) from error
    return cfg


def sweep(config_name: str, overrides: list[str]) -> tuple[list[list[str]], Job]:
    """The jobs of a sweep, as Hydra's basic sweeper will launch them (the config's
    ``hydra.sweeper.params``, which an experiment's YAML may set, then the command line's),
    and where each runs (:func:`job_place` of the sweep's launcher)."""
    settings = compose(config_name, sweep_jobs(overrides)[0], hydra=True).hydra
    params = [f"{key}={value}" for key, value in (settings.sweeper.params or {}).items()]
    return sweep_jobs([*params, *overrides]), job_place(settings.launcher)


def run_place(config_name: str, overrides: list[str]) -> Job:
    """Where a run (no ``-m``) runs: here; ValueError if its config picks a submitit launcher,
    which Hydra uses for sweeps only (the run would run here, unsaid)."""
    target = str(compose(config_name, overrides, hydra=True).hydra.launcher.get("_target_", ""))
    if "submitit" in target:
        raise ValueError(
            f"{target.rsplit('.', 1)[-1]} (hydra/launcher) submits sweeps only: add -m to submit "
            "this run as a sweep of one job"
        )
    return Job.local()


def job_place(launcher) -> Job:
    """Where each job of a sweep launched by ``launcher`` (its ``hydra.launcher`` config)
    runs: here (:meth:`Job.local`), or, with Hydra's Slurm launcher (``+cluster=slurm``),
    elsewhere on its nodes x tasks_per_node ranks. ValueError for a submitit launcher under
    several ranks: each would submit the sweep."""
    target = str(launcher.get("_target_", ""))
    if "submitit" in target and Job.local().ranks > 1:
        raise ValueError(
            f"{target.rsplit('.', 1)[-1]} (hydra/launcher) submits the sweep from one process: "
            "drop mpi.ranks and mpiexec (every rank would submit it); each job's ranks are "
            "hydra.launcher.tasks_per_node"
        )
    if not target.endswith("SlurmLauncher"):
        return Job.local()
    check_slurm_answers()
    return Job(int(launcher.nodes) * int(launcher.tasks_per_node), here=False)


def check_slurm_answers() -> None:
    """ValueError in one line unless this machine can submit to a running Slurm: ``sbatch`` on
    the PATH and the controller answering ``scontrol ping`` (else submitit's traceback)."""
    launcher = "hydra/launcher=submitit_slurm (+cluster=slurm)"
    if shutil.which("sbatch") is None:
        raise ValueError(f"{launcher} submits with sbatch, not on this PATH: run it on the cluster")
    try:
        ping = subprocess.run(["scontrol", "ping"], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired) as error:
        raise ValueError(f"{launcher}: scontrol ping failed ({error})") from None
    if ping.returncode != 0:
        said = [line for line in (ping.stdout + ping.stderr).splitlines() if line[:1] not in "* "]
        raise ValueError(
            f"{launcher}: the Slurm controller does not answer (scontrol ping: "
            f"{said[-1].strip() if said else f'status {ping.returncode}'})"
        )


def sweep_jobs(overrides: list[str]) -> list[list[str]]:
    """The overrides of each job of a sweep of ``overrides``, as Hydra's basic sweeper
    expands them; ``glob(...)`` of a group lists its shipped options."""
    loader = ConfigLoaderImpl(
        config_search_path=create_config_search_path(f"pkg://{CONFIG_MODULE}")
    )
    try:
        parsed = OverridesParser.create(config_loader=loader).parse_overrides(overrides)
        return BasicSweeper.split_arguments(parsed, None)[0]
    except Exception as error:  # noqa: BLE001 - the parser raises several kinds
        raise ValueError(one_line(error)) from error


def main(config_name: str, task: str, check: Callable) -> None:
    """Launch (``mpi.ranks``), guard each rank (:mod:`physicsrl.guard`), validate (every job
    of a ``-m`` sweep; not with Hydra's print-only flags), then ``task(cfg)`` on every rank
    under Hydra (``task``: "module:function")."""
    overrides = sys.argv[1:]
    relaunch(overrides)
    guard()
    validate_or_exit(config_name, overrides, check)

    def job(cfg) -> None:  # the job's code (torch where a rank holds an env): after the checks
        load_object(task)(cfg)

    run_hydra(config_name, job, overrides)
