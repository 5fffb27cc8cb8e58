"""A guard process per MPI rank, so that a rank that vanishes is named and ends the job non-zero.

A rank that ends without a word (``os._exit(0)``, the kernel's OOM killer) runs no handler,
and MPICH's ``mpiexec`` then kills every other rank at once and returns the status of the first
process it sees end: 0 for ``os._exit(0)`` (under load it once left the others waiting
instead). So the rank is watched from outside. :func:`guard`,
called before MPI starts, forks the process the launcher started: the child returns and runs
the job; the parent, the guard, keeps the launcher's connection open and waits for it. The job
marks its end when the interpreter exits (the script's end, ``sys.exit(k)``) and when physicsrl
aborts the job after reporting why (:func:`ended`). A job that ends unmarked gets one line,

    error: rank 1 ended before its job did (exited with status 0); the launcher ends every rank

and the guard asks the launcher to end every rank with the job's status (1 for 0, 128 + N for
signal N) as ``MPI_Abort`` does, by the PMI command ``abort`` on the launcher's connection, then
exits with it (a launcher without that connection ends the job when it sees the guard exit
non-zero). A marked end exits with the job's own status, silently.

Every ``physicsrl-*`` command guards its ranks under a launcher (``mpi.ranks=N`` launches
included); a script is guarded with ``mpiexec -n 4 python -m physicsrl.guard script.py [args]``
(or ``-m module [args]``), and an exception in its own code then ends every rank with the
traceback once (:func:`run`). The job stays in the rank's process group, where MPICH's
``mpiexec`` sends its signals, so SIGINT and SIGTERM reach it once, directly; the guard ignores
them and ends with the job (a launcher that signals only the process it started would not reach
the job: ``PHYSICSRL_GUARD=0`` there). The job is killed if its guard dies (the launcher's
SIGKILL). Linux only (``PR_SET_PDEATHSIG``); no guard elsewhere, nor with ``PHYSICSRL_GUARD=0``.
"""

from __future__ import annotations

import atexit
import ctypes
import importlib.util
import os
import runpy
import signal
import sys
import time
from typing import NoReturn

from physicsrl.launch import launched_rank, launched_size, refuse

__all__ = ["guard", "ended"]

PR_SET_PDEATHSIG = 1  # prctl option: a signal for this process when its parent dies
TEARDOWN_S = 1.0  # how long a launcher may take to kill the guards after another rank's abort
# how long the launcher is given to forward the guard's line before the abort ends it: without
# it MPICH's mpiexec lost the line, written and flushed, in 8 of 280 jobs run two at a time
# (tests/mpi_scripts/coord_exit.py vanish-SIGKILL); in none of 160 with it
FORWARD_S = 0.5
IGNORED = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGUSR1, signal.SIGUSR2)

_marker: tuple[int, int] | None = None  # in the job: (the pipe to its guard, the job's pid)


def guard() -> None:
    """Split this rank into its guard and its job (module docstring); returns in the job only.

    Does nothing without an MPI launcher, once MPI has started (forking it is unsafe), in a
    job already guarded, with ``PHYSICSRL_GUARD=0`` and off Linux.
    """
    global _marker
    if (
        launched_size() is None
        or "mpi4py.MPI" in sys.modules
        or _marker is not None
        or os.environ.get("PHYSICSRL_GUARD") == "0"
        or not sys.platform.startswith("linux")
    ):
        return
    sys.stdout.flush()
    sys.stderr.flush()
    read, write = os.pipe()
    job = os.fork()
    if job == 0:
        os.close(read)
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
        _marker = (write, os.getpid())  # not a forked child's exit
        atexit.register(ended)  # registered first, so it runs last
        return
    os.close(write)
    _watch(job, read)


def ended() -> None:
    """Tell this rank's guard that its job ends as meant: a normal exit, or an abort that
    physicsrl has reported (:mod:`physicsrl.coordinated`). Nothing without a guard."""
    global _marker
    if _marker is not None and _marker[1] == os.getpid():
        os.write(_marker[0], b"1")
        os.close(_marker[0])
        _marker = None


def _watch(job: int, marker: int) -> NoReturn:
    """The guard: wait for ``job``, exit with its status (module docstring), naming this rank
    if it ended without marking it."""
    for signum in IGNORED:  # the launcher signals the rank's process group: the job too
        signal.signal(signum, signal.SIG_IGN)
    _, status = os.waitpid(job, 0)
    code = os.waitstatus_to_exitcode(status)  # -N: killed by signal N
    exit_status = 128 - code if code < 0 else code
    # blocks while a process the job forked still holds the pipe: the launcher's connection
    # is held open by that process too, and the job ends when it does (measured: with a
    # non-blocking read the job hangs, as it does unguarded)
    if os.read(marker, 1) != b"1":
        # a job ended by the launcher's teardown of an abort elsewhere (reported there) is
        # followed by the guard's own SIGKILL: only a rank that ended first gets this far
        time.sleep(TEARDOWN_S)
        how = (
            f"killed by {signal.Signals(-code).name}" if code < 0 else f"exited with status {code}"
        )
        sys.stderr.write(
            f"error: rank {launched_rank()} ended before its job did ({how}); "
            "the launcher ends every rank\n"
        )
        sys.stderr.flush()
        time.sleep(FORWARD_S)
        exit_status = exit_status or 1
        _abort(exit_status)
    os._exit(exit_status)  # not the job's atexit handlers a second time


def _abort(code: int) -> None:
    """Ask the launcher to end every rank with status ``code``, as ``MPI_Abort`` does: the PMI
    command ``abort`` on the process manager's connection ``PMI_FD`` (MPICH's), which the job
    inherited from the guard and spoke through. Only the guard's exit would tell it otherwise:
    MPICH's launcher then returns whichever status it sees first (1, or 9 for a rank it
    killed), and about once in 1,000 jobs it missed that exit and left the others waiting."""
    connection = os.environ.get("PMI_FD", "")
    if connection.isdigit():
        try:
            os.write(int(connection), f"cmd=abort exitcode={code}\n".encode())
        except OSError:  # not a PMI connection (any more): the guard's exit ends the job
            pass


def run(arguments: list[str]) -> NoReturn:
    """``python -m physicsrl.guard script.py [args]`` or ``... -m module [args]``: guard this
    rank, then run the script or module as ``__main__`` with those arguments."""
    usage = "usage: mpiexec -n N python -m physicsrl.guard (script.py | -m module) [args]"
    if arguments[:1] in (["-h"], ["--help"]):
        if launched_rank() == 0:
            print(usage)
        raise SystemExit(0)
    if not arguments or arguments == ["-m"]:
        refuse(usage)
    if arguments[0] != "-m" and not os.path.isfile(arguments[0]):
        refuse(f"no script {arguments[0]}")
    if arguments[0] == "-m" and not _module_exists(arguments[1]):
        refuse(f"no module {arguments[1]}")
    guard()
    try:
        if arguments[0] == "-m":
            sys.argv = arguments[1:]
            runpy.run_module(arguments[1], run_name="__main__", alter_sys=True)
        else:
            sys.argv = arguments
            sys.path.insert(0, os.path.dirname(os.path.abspath(arguments[0])))
            runpy.run_path(arguments[0], run_name="__main__")
    except Exception:
        _end_every_rank()
        raise
    raise SystemExit(0)


def _end_every_rank() -> None:
    """In the handling of an exception from the script's own code (outside the parallel calls,
    which end every rank themselves): once MPI has started on several ranks, end every rank
    as :class:`~physicsrl.coordinated.abort_on_error` does, with the traceback printed once
    when every rank fails alike and without the others waiting when one fails alone."""
    if "mpi4py.MPI" not in sys.modules:
        return
    from mpi4py import MPI

    from physicsrl.coordinated import abort_on_error

    if MPI.Is_initialized() and not MPI.Is_finalized():
        with abort_on_error(MPI.COMM_WORLD):
            raise


def _module_exists(name: str) -> bool:
    """Whether ``name`` can be imported (its parent packages are imported to look)."""
    try:
        return importlib.util.find_spec(name) is not None
    except ImportError:  # a parent package is missing
        return False


if __name__ == "__main__":
    import physicsrl.guard  # this file runs as __main__: the job's marker lives in the module

    physicsrl.guard.run(sys.argv[1:])
