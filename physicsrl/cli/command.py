"""What every ``physicsrl-*`` command does with its command line before running: add the task's
observation and reward to ``env=NAME``, compose the config, check it on every rank, and turn a
bad value into one line naming the key (exit status 2, printed by the leader only).

The config and the tasks are imported inside the functions: they import MPI (through the
simulators), which must not start before :func:`~physicsrl.launch.relaunch` re-executes the
command under ``mpiexec``.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable

from omegaconf import OmegaConf

from physicsrl.launch import relaunch, run_hydra


def with_pairs(overrides: list[str]) -> list[str]:
    """Add the observation and reward that go with ``env=NAME`` (the task's ``pairs``) unless
    they are given. Without ``env=`` nothing is added: the defaults list or a preset chooses."""
    chosen = {o.split("=", 1)[0].lstrip("+~"): o.split("=", 1)[1] for o in overrides if "=" in o}
    if "env" not in chosen:
        return overrides
    from physicsrl.envs import TASKS
    from physicsrl.envs.factory import shipped

    try:
        task = TASKS.classes.get(OmegaConf.load(shipped("env", chosen["env"])).get("name"))
    except FileNotFoundError:
        return overrides  # composing names the unknown option
    pairs = dict(zip(("observation", "reward"), getattr(task, "pairs", None) or (), strict=False))
    return [
        *overrides,
        *(f"{group}={option}" for group, option in pairs.items() if group not in chosen),
    ]


def one_line(error: BaseException) -> str:
    """A one-line description of a config error, naming the key."""
    chain, seen = [], error
    while seen is not None:
        chain.append(seen)
        seen = seen.__cause__ or seen.__context__
    for item in chain:
        key = getattr(item, "full_key", None)
        if key:
            message = str(item).splitlines()[0]
            if "not in" in message or "Could not append" in message or "Key '" in message:
                return f"unknown key '{key}': {message}"
            return f"bad value for '{key}': {message}"
    message = " ".join(str(chain[-1]).split()).split(" Config search path")[0]
    message = message or type(chain[-1]).__name__
    first = " ".join(str(chain[0]).split())
    return first if first and first != message and len(chain) == 1 else message


def compose(config_name: str, overrides: list[str]):
    """The job config (no Hydra section), or ValueError with a one-line message."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    from physicsrl.config import register

    register()
    job_overrides = [o for o in overrides if not o.lstrip("+~").startswith(("hydra.", "hydra/"))]
    GlobalHydra.instance().clear()
    try:
        with initialize_config_module(config_module="physicsrl.conf", version_base=None):
            return hydra_compose(config_name=config_name, overrides=job_overrides)
    except Exception as error:  # noqa: BLE001 - Hydra and OmegaConf raise many kinds
        raise ValueError(one_line(error)) from error
    finally:
        GlobalHydra.instance().clear()


def rank_from_launcher() -> int:
    for variable in ("PMI_RANK", "OMPI_COMM_WORLD_RANK", "PMIX_RANK", "SLURM_PROCID"):
        if variable in os.environ:
            return int(os.environ[variable])
    return 0


def validate_or_exit(config_name: str, overrides: list[str], check: Callable) -> None:
    """Compose the config, run every range check of its schema and ``check(cfg)`` on this rank;
    on error the leader prints one line and every rank exits with status 2 (all ranks see the
    same config, so no rank waits)."""
    from physicsrl.config import typed

    try:
        cfg = compose(config_name, overrides)
        try:
            typed(cfg)
        except ValueError:
            raise
        except Exception as error:  # noqa: BLE001 - OmegaConf's errors name the key
            raise ValueError(one_line(error)) from error
        check(cfg)
    except Exception as error:  # noqa: BLE001
        message = error.args[0] if isinstance(error, ValueError) and error.args else str(error)
        if rank_from_launcher() == 0:
            print(f"error: bad config: {' '.join(str(message).split())}", file=sys.stderr)
        raise SystemExit(2) from None


def main(config_name: str, task: str, check: Callable, pairs: bool = False) -> None:
    """Launch (``mpi.ranks``), add the task's pairs to ``env=`` (``pairs``), validate (not for
    Hydra's flags), then ``task(cfg)`` on every rank under Hydra (``task``: "module:function")."""
    overrides = sys.argv[1:]
    relaunch(overrides)
    from physicsrl.builders import load_object
    from physicsrl.config import register

    overrides = with_pairs(overrides) if pairs else overrides
    register()
    if not [o for o in overrides if o.startswith("-")]:
        validate_or_exit(config_name, overrides, check)
    run_hydra(config_name, load_object(task), overrides)
