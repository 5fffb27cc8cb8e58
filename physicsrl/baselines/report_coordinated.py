"""The report's coordination design (section 3), minimal: the baseline of ``physicsrl-bench ping``.

Every call pickles a dict of namespace, method name, args and kwargs, sends it with the pickled
``comm.bcast``, and followers dispatch it with ``getattr``; nested calls are tracked per object.
"""

from __future__ import annotations

import functools

from mpi4py import MPI


class ReportCoordinator:
    def __init__(self, comm: MPI.Comm = MPI.COMM_WORLD):
        self.comm = comm
        self.objects: dict = {}
        self.inside = False

    def register(self, obj, namespace=None):
        namespace = len(self.objects) if namespace is None else namespace
        self.objects[namespace] = obj
        return namespace

    def is_leader(self) -> bool:
        return self.comm.rank == 0

    def broadcast(self, namespace, name, args, kwargs):
        self.comm.bcast(
            {"namespace": namespace, "method": name, "args": args, "kwargs": kwargs}, root=0
        )

    def __enter__(self):
        self.inside = True
        if not self.is_leader():
            while (command := self.comm.bcast(None, root=0)) is not None:
                obj = self.objects[command["namespace"]]
                getattr(obj, command["method"])(*command["args"], **command["kwargs"])
        return self

    def __exit__(self, *exc):
        if self.is_leader():
            self.comm.bcast(None, root=0)
        self.inside = False
        return False


class ReportCoordinated:
    def register_coordinator(self, coordinator: ReportCoordinator, namespace=None):
        self._coordinator = coordinator
        self._namespace = coordinator.register(self, namespace)
        self._inside_parallel = False

    def run_method_in_parallel(self, function, *args, **kwargs):
        if not self._coordinator.inside:
            raise RuntimeError("parallel method called outside 'with coordinator'")
        broadcast = self._coordinator.is_leader() and not self._inside_parallel
        self._inside_parallel = True
        try:
            if broadcast:
                self._coordinator.broadcast(self._namespace, function.__name__, args, kwargs)
            return function(self, *args, **kwargs)
        finally:
            self._inside_parallel = False


def report_parallel(method):
    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        return self.run_method_in_parallel(method, *args, **kwargs)

    return wrapper
