"""The Hydra callback that checks the run directory can be written before Hydra writes there.

Named in ``conf/common.yaml`` (``hydra.callbacks``); a module of its own so that importing
:mod:`physicsrl.launch` (before an MPI re-launch) does not import Hydra.
"""

from __future__ import annotations

import os
from pathlib import Path

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
    of the leader failing in Hydra's log setup while the followers wait for it."""

    def on_run_start(self, config, **kwargs) -> None:
        evaluation = "run" in config
        taken = {}
        if evaluation or ("resume" in config and not config.resume):
            taken[RUN] = CHECKPOINTS
        if evaluation:
            taken["eval_summary.csv"] = "an earlier evaluation's results; name a new directory"
        agree_directory_is_writable("hydra.run.dir", config.hydra.run.dir, taken)

    def on_multirun_start(self, config, **kwargs) -> None:
        new_runs = "resume" in config and not config.resume
        taken = {JOBS: SWEEP_CHECKPOINTS} if new_runs else {}
        agree_directory_is_writable("hydra.sweep.dir", config.hydra.sweep.dir, taken)


RUN, JOBS = "checkpoints/ckpt-*", "*/checkpoints/ckpt-*"  # a run's, a sweep's checkpoints
CHECKPOINTS = (
    "a training run's checkpoints; resume=true continues it, a new run or an evaluation needs "
    "another directory"
)
SWEEP_CHECKPOINTS = (
    "training runs' checkpoints in its subdirectories; resume=true continues a sweep there, a "
    "new sweep needs another directory"
)


def agree_directory_is_writable(key: str, directory: str, taken: dict[str, str]) -> None:
    """The leader creates ``directory`` and writes a byte there, and looks for files matching
    the glob patterns of ``taken`` in it; every rank learns the outcome (collective) and
    refuses to go on if the write failed or such a file is there (the line says ``taken``'s
    value: what the file is)."""
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    problem = None
    found = [] if comm.rank else [w for p, w in taken.items() if next(Path(directory).glob(p), 0)]
    if found:
        problem = f"{key}={directory}: it holds {found[0]}"
    elif comm.rank == 0:
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
            problem = f"{key}={directory}: cannot write the run directory there ({reason})"
    problem = comm.bcast(problem, 0)
    if problem is not None:
        refuse(problem)
