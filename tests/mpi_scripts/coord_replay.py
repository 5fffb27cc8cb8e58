"""Replay of parallel calls on every rank; prints 'ok' on the leader when every check holds.

Routing: a plain override that delegates to its parallel base method, a free function named
like a method, and a lambda run the function the leader ran (the followers looked the name up
on their object's class: the override ran twice, the class's method instead of the free one).
"""

import sys
import threading

import numpy as np
from mpi4py import MPI

from physicsrl.coordinated import Coordinated, Coordinator, parallel


class Counter(Coordinated):
    def __init__(self, coordinator, namespace=None):
        self.register_coordinator(coordinator, namespace)
        self.log = []

    @parallel
    def add(self, value, scale=1):
        self.log.append(value * scale)
        return len(self.log)

    @parallel
    def apply(self, function, value):
        self.log.append(function(value))

    @parallel
    def twice(self, value):
        self.add(value)  # nested: the followers make this call themselves
        self.add(value)

    @parallel
    def total(self):
        return MPI.COMM_WORLD.allreduce(sum(self.log))  # a collective inside a parallel call


class Doubling(Counter):
    def add(self, value, scale=1):  # a plain override delegating to the parallel base method
        return super().add(2 * value, scale)


def total(self):  # a free function named like a parallel method of Counter
    self.log.append("free")


comm = MPI.COMM_WORLD
coordinator = Coordinator()
# explicit namespaces: registered in a different order on the leader and the followers
named = [Counter(coordinator, "a"), Counter(coordinator, "b")]
if comm.rank == 0:
    named.reverse()
first, second = sorted(named, key=lambda c: c._namespace)
counter = Counter(coordinator)
doubling = Doubling(coordinator)
offset = 10
duplicate = comm.Dup()  # collective; pickle refuses a communicator that is not predefined

with coordinator:
    if coordinator.is_leader():
        assert counter.add(1) == 1  # the leader gets the return value
        counter.add(2, scale=3)
        counter.apply(lambda x: x + offset, 5)  # a closure goes by cloudpickle
        counter.twice(4)
        big = np.arange(1000.0)  # larger than one message: a second broadcast
        counter.apply(np.sum, big)
        # neither pickler serialises these (pickle raises TypeError and ValueError for them)
        for unserialisable in (threading.Lock(), duplicate, [threading.Lock(), *range(10**6)]):
            try:
                counter.add(unserialisable)
            except TypeError as error:
                assert "cannot be serialised" in str(error) and len(str(error)) < 1000, error
            else:
                raise AssertionError("an unserialisable argument must raise TypeError")
        counter.add(7)  # the followers are still in step
        first.add(100)
        second.add(200)
        assert counter.total() == comm.size * (1 + 6 + 15 + 8 + big.sum() + 7)
        doubling.add(1)
        doubling.run_method_in_parallel(total)
        doubling.run_method_in_parallel(lambda self, value: self.log.append(value), 3)

logs = comm.gather((counter.log, first.log, second.log, doubling.log), root=0)
if comm.rank == 0:
    assert all(log == logs[0] for log in logs), logs
    assert logs[0][3] == [2, "free", 3], logs[0][3]
    assert logs[0][0] == [1, 6, 15, 4, 4, 499500.0, 7], logs[0][0]
    assert logs[0][1:3] == ([100], [200]), logs[0]
    print("ok", file=sys.stderr)
