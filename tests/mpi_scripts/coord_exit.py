"""End the job in the way argv[1] names; the test checks every rank's exit and the output.

``exit-K``: the leader calls ``sys.exit(K)`` inside the with block; ``interrupt``: leader-only
code raises KeyboardInterrupt; ``vanish-K``: the last rank calls ``os._exit(K)`` inside a
parallel call (a follower that disappears without a word), ``vanish-SIGKILL``: it kills itself
(as the OOM killer would); ``followers-collective``: a parallel call enters a barrier on the
followers only (a hang that the watchdog ends); ``watched``: ordinary calls under the watchdog;
``ctrl-c-idle``, ``ctrl-c-call`` and ``ctrl-c-plain``: wait for a Ctrl-C (the test sends SIGINT),
the leader in its own code and the followers idle, every rank inside a parallel call, or every
rank in its own code under ``abort_on_error``, after each rank has said "ready" and its pid on
stderr; ``raise-everywhere`` and ``raise-last``: every rank, or the last one while the others
wait in a barrier, raises in the script's own code before any coordinator.
"""

import os
import signal
import sys
import time

from mpi4py import MPI

from physicsrl.coordinated import Coordinated, Coordinator, abort_on_error, parallel

how = sys.argv[1]
comm = MPI.COMM_WORLD


class Job(Coordinated):
    def __init__(self, coordinator):
        self.register_coordinator(coordinator)

    @parallel
    def step(self, followers_only_barrier=False, vanish=None, seconds=None):
        if seconds is not None:
            comm.Barrier()
            ready(seconds)
        if vanish is not None and comm.rank == comm.size - 1:
            if vanish == "SIGKILL":
                os.kill(os.getpid(), signal.SIGKILL)
            os._exit(int(vanish))
        if not followers_only_barrier or comm.rank != 0:
            comm.Barrier()
        return comm.rank


def ready(seconds):
    print(f"rank {comm.rank} ready, pid {os.getpid()}", file=sys.stderr, flush=True)
    time.sleep(seconds)


if how == "ctrl-c-plain":
    with abort_on_error():
        ready(60)

if how.startswith("raise-"):  # the script's own code, outside a with block
    if how == "raise-everywhere" or comm.rank == comm.size - 1:
        raise ValueError(f"a bad setting, read on rank {comm.rank}")
    comm.Barrier()  # the others wait for the last rank here

coordinator = Coordinator()
job = Job(coordinator)
with coordinator:
    if coordinator.is_leader():
        job.step()
        if how.startswith("exit-"):
            sys.exit(int(how.removeprefix("exit-")))
        if how == "interrupt":
            raise KeyboardInterrupt
        if how.startswith("ctrl-c-"):
            job.step(seconds=60 if how == "ctrl-c-call" else 0)
            time.sleep(60)
        if how == "followers-collective":
            job.step(followers_only_barrier=True)
        elif how.startswith("vanish-"):
            job.step(vanish=how.removeprefix("vanish-"))
            for _ in range(100):
                job.step()
        else:
            for _ in range(100):
                job.step()
print(f"rank {comm.rank} finished", file=sys.stderr)
