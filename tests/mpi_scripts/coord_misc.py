"""Side-by-side coordinators (and their time sending calls), sequence checking, idle CPU and
many coordinators in one process (argv[1] picks the case)."""

import sys
import time

from mpi4py import MPI

from physicsrl.coordinated import Coordinated, Coordinator, SequenceDivergence, parallel
from physicsrl.envs.layout import environments

comm = MPI.COMM_WORLD
case = sys.argv[1]


class Node(Coordinated):
    def __init__(self, coordinator):
        self.register_coordinator(coordinator)
        self.seen = []

    @parallel
    def record(self, value):
        self.seen.append(value)

    @parallel
    def diverge(self):
        if comm.rank == 1:
            self.record("only on rank 1")


if case == "side-by-side":
    # two groups, each with its own leader, driving their objects independently
    group = comm.Split(comm.rank % 2, comm.rank)
    coordinator = Coordinator(group)
    node = Node(coordinator)
    elapsed = 0.0
    with coordinator:
        if coordinator.is_leader():
            started = time.perf_counter()
            for i in range(50):
                node.record((comm.rank % 2, i))
            elapsed = time.perf_counter() - started
    seen = comm.gather(node.seen, root=0)
    timings = comm.gather((coordinator.is_leader(), coordinator.broadcast_s, elapsed), root=0)
    if comm.rank == 0:
        for rank, values in enumerate(seen):
            assert values == [(rank % 2, i) for i in range(50)], (rank, values)
        for leader, sending, total in timings:  # only a leader sends, within its calls' time
            assert (0 < sending <= total) if leader else sending == 0, (leader, sending, total)
        print("ok", file=sys.stderr)

elif case == "divergence":
    coordinator = Coordinator(check=True)
    node = Node(coordinator)
    with coordinator:
        if coordinator.is_leader():
            node.record(1)
            try:
                node.diverge()
            except SequenceDivergence as error:
                print(f"reported: {error}", file=sys.stderr)
                raise SystemExit(3) from None

elif case == "idle":
    coordinator = Coordinator()
    node = Node(coordinator)
    cpu, wall = time.process_time(), time.perf_counter()
    with coordinator:
        if coordinator.is_leader():
            node.record(1)
            time.sleep(2.0)  # the leader "trains"
            node.record(2)  # and the follower still answers
    share = (time.process_time() - cpu) / (time.perf_counter() - wall)
    shares = comm.gather(share, root=0)
    if comm.rank == 0:
        print(f"follower cpu {max(shares[1:]):.4f}", file=sys.stderr)

elif case == "many":
    # more coordinators, one after the other, than MPICH has communicators (~2040 per process):
    # each frees its own at the end of its with-block; a coordinator is used twice
    for i in range(3000):
        coordinator = Coordinator()
        node = Node(coordinator)
        for _ in range(1 if i else 2):
            with coordinator:
                if coordinator.is_leader():
                    node.record(i)
    assert node.seen == [2999], node.seen
    for i in range(3000):  # and as many one-group layouts, each with its communicators
        with environments(lambda coordinator: Node(coordinator), comm.size) as env:
            if env is not None:
                env.record(i)
    print("ok", file=sys.stderr)
