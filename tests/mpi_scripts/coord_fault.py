"""Raise in one place (argv[1]) and expect every rank to end with a non-zero exit."""

import sys
import time

from mpi4py import MPI

from physicsrl.coordinated import Coordinated, Coordinator, parallel

where = sys.argv[1]
rank = MPI.COMM_WORLD.rank


class Faulty(Coordinated):
    def __init__(self, coordinator):
        self.register_coordinator(coordinator)

    @parallel
    def step(self):
        fails = {"leader": rank == 0, "follower": rank == 1, "followers": rank > 0, "all": True}
        if fails.get(where, False):
            raise RuntimeError(f"injected fault {where}")
        MPI.COMM_WORLD.Barrier()  # the ranks that did not fail wait here for the others


coordinator = Coordinator()
faulty = Faulty(coordinator)
with coordinator:
    if coordinator.is_leader():
        faulty.step()
        if where == "leader-code":
            time.sleep(0.2)
            raise RuntimeError("injected fault leader-code")
print("unreachable for a fault", file=sys.stderr)
