"""The run directory: the Hydra callback that checks it before Hydra writes there, and the run
that ``resume=`` continues.

The callback is named in ``conf/common.yaml`` (``hydra.callbacks``); a module of its own so
that importing :mod:`physicsrl.launch` (before an MPI re-launch) does not import Hydra, and
without torch, so that a bad run directory or ``resume=`` is refused before torch loads.
"""

from __future__ import annotations

import json
import os
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback

from physicsrl.launch import refuse


class WritableRunDirectory(Callback):
    """Hydra callback (``hydra.callbacks`` in ``common.yaml``): before Hydra writes its files,
    the leader checks that the run (or sweep) directory can be written, and, for a new
    training run (``resume`` unset) or an evaluation (``run`` set), that it holds no training
    run's checkpoints (Hydra would write into it: a new run's checkpoints would mix with the
    other's, an evaluation would replace the run's ``eval.csv`` and ``.hydra/``), and for an
    evaluation no earlier evaluation's results (its GIF or fields would stay beside the new
    tables); if not, every rank ends with status 2 and one line naming the directory, instead
    of the leader failing in Hydra's log setup while the followers wait for it. A training run
    with ``resume`` set is refused so, first, if :func:`find_run` finds no run to continue."""

    def on_run_start(self, config, **kwargs) -> None:
        evaluation = "run" in config
        resume = None if evaluation else config.get("resume")
        taken = {}
        if evaluation or ("resume" in config and not resume):
            taken[RUN] = CHECKPOINTS
        if evaluation:
            taken["eval_summary.csv"] = "an earlier evaluation's results; name a new directory"
        directory = config.hydra.run.dir

        def check() -> None:
            if resume:  # before the directory is made: a refused resume writes nothing
                find_run(str(resume), Path(directory).parent)
            check_directory("hydra.run.dir", directory, taken)

        agree(check)

    def on_multirun_start(self, config, **kwargs) -> None:
        new_runs = "resume" in config and not config.resume
        taken = {JOBS: SWEEP_CHECKPOINTS} if new_runs else {}
        agree(lambda: check_directory("hydra.sweep.dir", config.hydra.sweep.dir, taken))


RUN, JOBS = "checkpoints/ckpt-*", "*/checkpoints/ckpt-*"  # a run's, a sweep's checkpoints
RESUMED = "resumed.txt"  # in the run directory of a command that continued another run
CHECKPOINTS = (
    "a training run's checkpoints; resume=true continues it, a new run or an evaluation needs "
    "another directory"
)
SWEEP_CHECKPOINTS = (
    "training runs' checkpoints in its subdirectories; resume=true continues a sweep there, a "
    "new sweep needs another directory"
)


def agree(check: Callable[[], Any], errors: tuple[type[Exception], ...] = (OSError,)) -> Any:
    """The leader runs ``check``; every rank gets its value, or learns that it raised one of
    ``errors`` (collective) and then ends with status 2 and its message in one line."""
    from mpi4py import MPI

    value, problem = None, None
    if MPI.COMM_WORLD.rank == 0:
        try:
            value = check()
        except errors as error:
            problem = str(error)
    value, problem = MPI.COMM_WORLD.bcast((value, problem), 0)
    if problem is not None:
        refuse(problem)
    return value


def check_directory(key: str, directory: str, taken: dict[str, str]) -> None:
    """Create ``directory`` and write a byte there; FileExistsError if a file there matches a
    glob pattern of ``taken`` (the message says its value: what the file is), OSError if the
    write fails, each naming ``key``."""
    found = [what for pattern, what in taken.items() if next(Path(directory).glob(pattern), 0)]
    if found:
        raise FileExistsError(f"{key}={directory}: it holds {found[0]}")
    probe = Path(directory) / ".physicsrl-write-test"
    try:
        probe.parent.mkdir(parents=True, exist_ok=True)
        with open(probe, "wb") as stream:
            stream.write(b"x")
            stream.flush()
            os.fsync(stream.fileno())  # a full disk fails here, not at close
        probe.unlink()
    except OSError as error:
        reason = error.strerror or str(error)
        cannot = f"{key}={directory}: cannot write the run directory there ({reason})"
        raise OSError(cannot) from None


def latest_checkpoint(run: Path) -> Path | None:
    """The newest checkpoint file of the run directory ``run`` (by name: its iteration)."""
    return max(run.glob(RUN), default=None)


def checkpoint_path(run: str) -> Path:
    """The checkpoint file that ``run`` names: ``run`` itself if it is a file, else the newest
    checkpoint of the run directory ``run``; ValueError naming ``run`` if it has none, or if the
    file is not a TorchRL checkpoint archive (:func:`is_checkpoint`)."""
    path = Path(run).expanduser()
    if path.is_file():
        if not is_checkpoint(path):
            raise ValueError(f"run={run} is not a checkpoint file (a TorchRL .torchrl archive)")
        return path
    latest = latest_checkpoint(path)
    if latest is None:
        elsewhere = checkpoints_elsewhere(path)
        raise ValueError(
            f"run={run}: no checkpoint file there or under its checkpoints/{elsewhere}"
        )
    return latest


def checkpoints_elsewhere(path: Path) -> str:
    """Where the checkpoints are that the directory ``path``, which has none of its own, points
    to, as the end of a one-line message: the run it resumed (its :data:`RESUMED`), or its jobs
    if it holds a sweep's runs (``"; a sweep: name one of its jobs (0, 1)"``); else ``""``."""
    resumed = path / RESUMED
    if resumed.is_file():
        return f"; {' '.join(resumed.read_text().split())}"
    names = sorted(
        {p.relative_to(path).parts[0] for p in path.glob(JOBS)}, key=lambda n: (len(n), n)
    )
    if len(names) > 4:  # a sweep's jobs are 0, 1, 2, ...
        names = [*names[:3], "...", names[-1]]
    return f"; a sweep: name one of its jobs ({', '.join(names)})" if names else ""


def is_checkpoint(path: Path) -> bool:
    """Whether the file ``path`` is a TorchRL checkpoint archive: a ZIP file whose
    ``manifest.json`` names the format ``torchrl.checkpoint`` (TorchRL's
    ``Checkpoint.is_checkpoint`` for archives, without importing torch)."""
    try:
        with zipfile.ZipFile(path) as archive, archive.open("manifest.json") as manifest:
            return json.load(manifest).get("format") == "torchrl.checkpoint"
    except (OSError, KeyError, ValueError, AttributeError, zipfile.BadZipFile):
        return False


def find_run(resume: str, runs: Path) -> Path:
    """The run directory to resume: ``resume`` itself (a run directory or a checkpoint file),
    or with ``resume == "true"`` the directory under ``runs`` whose newest checkpoint is the
    newest; FileNotFoundError naming ``resume`` if it has no checkpoint."""
    if resume.lower() != "true":
        path = Path(resume).expanduser()
        if path.is_file():
            path = path.parent.parent
        if latest_checkpoint(path) is None:
            elsewhere = checkpoints_elsewhere(path)
            raise FileNotFoundError(
                f"resume={resume}: no checkpoint under {path}/checkpoints{elsewhere}"
            )
        return path
    candidates = [d for d in (runs.iterdir() if runs.is_dir() else []) if latest_checkpoint(d)]
    if not candidates:
        raise FileNotFoundError(f"resume=true: no run with a checkpoint under {runs}")
    return max(candidates, key=lambda d: latest_checkpoint(d).stat().st_mtime)
