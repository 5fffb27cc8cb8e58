"""Wait for a Ctrl-C (the test sends SIGINT to the launcher's process group, as a terminal
does) where argv[1] says: ``idle``, the leader in its own code and the followers idle;
``call``, every rank inside a parallel call. Each rank says "ready" on stderr first."""

import os
import sys
import time

from mpi4py import MPI

from physicsrl.coordinated import Coordinated, Coordinator, parallel

comm = MPI.COMM_WORLD


class Job(Coordinated):
    def __init__(self, coordinator):
        self.register_coordinator(coordinator)

    @parallel
    def wait(self, seconds):
        comm.Barrier()
        print(f"rank {comm.rank} ready, pid {os.getpid()}", file=sys.stderr, flush=True)
        time.sleep(seconds)


coordinator = Coordinator()
job = Job(coordinator)
with coordinator:
    if coordinator.is_leader():
        if sys.argv[1] == "call":
            job.wait(60)
        else:
            job.wait(0)
            time.sleep(60)
print(f"rank {comm.rank} finished", file=sys.stderr)
