"""Leader-driven replication of method calls across MPI ranks.

Reinforcement-learning code runs on the leader rank only; simulator objects live on every rank.
A method marked ``@parallel`` on a :class:`Coordinated` object, called on the leader, is sent to
every follower rank and run there on the object registered under the same namespace, so the
distributed (FEniCSx) work happens everywhere while the leader sees an ordinary Python object::

    class Ping(Coordinated):
        def __init__(self, coordinator):
            self.register_coordinator(coordinator)

        @parallel
        def ping(self, value=None):
            return value

    coordinator = Coordinator()
    ping = Ping(coordinator)             # construct on every rank, in the same order
    with coordinator:                    # followers serve calls here until the leader leaves
        if coordinator.is_leader():
            ping.ping(3.0)               # runs on every rank; the leader gets the result

Wire format: one fixed-size message per call (16-byte header and up to ``INLINE_BYTES`` of
arguments inline), sent down a binomial tree of point-to-point messages on a private duplicate
of the communicator (log2(ranks) hops; measured faster than ``MPI_Bcast`` and, unlike it,
pollable); larger arguments follow in a ``Bcast``. A call
is addressed by a *route*, a small integer naming (namespace, method); the first call of a
route carries its definition, later calls only its number. Arguments are pickled (protocol 5),
with cloudpickle as the fallback for lambdas and closures; no-argument calls pickle nothing.

Failures never hang the job: an exception in a parallel method ends every rank with
``MPI.Abort`` after printing the traceback once, and an exception in leader-only code inside
the ``with`` block releases the followers, which exit with status 1. ``sys.exit(k)`` on the
leader inside the block is not a fault: every rank exits with status k, silently; a
``KeyboardInterrupt`` there ends every rank with status 130 and one line. A call that never
finishes on some ranks (a collective entered by some ranks only) is caught by the opt-in
watchdog (``timeout`` seconds, or the ``PHYSICSRL_TIMEOUT`` environment variable), which aborts
every rank with one line naming the call and the ranks that had not finished it.

Idle followers poll a non-blocking receive: they spin for ``spin_s`` seconds after the last
call, then sleep with a growing interval of at most ``max_sleep_s``, so a follower waiting
while the leader trains uses a small fraction of a core.
"""

from __future__ import annotations

import collections
import functools
import hashlib
import inspect
import math
import operator
import os
import pickle
import reprlib
import signal
import struct
import sys
import threading
import time
import traceback
from collections.abc import Callable, Hashable
from typing import Any, NoReturn

import numpy as np
from mpi4py import MPI

from physicsrl.guard import ended
from physicsrl.launch import check_sequence_from_environment, timeout_from_environment

__all__ = [
    "Coordinator",
    "wait_for",
    "Coordinated",
    "CoordinationError",
    "CollectiveError",
    "SequenceDivergence",
    "parallel",
    "random",
    "randint",
    "abort_on_error",
]

INLINE_BYTES = 240
_HEADER = struct.Struct("<4i")  # route, flags, payload length, sequence number
_STOP, _FAIL, _EXIT = -1, -2, -3  # _EXIT carries the leader's exit status in the flags
_PICKLE, _CLOUDPICKLE, _DEFINE = 1, 2, 4
_SERIALISED = _PICKLE | _CLOUDPICKLE
_TAG, _DONE_TAG, _FAILED_TAG = 17, 18, 19
# A failing follower waits this long for word that the leader failed in the same call, or,
# under abort_on_error, for the leader's abort, before it reports its own failure.
LEADER_FAILED_GRACE_S = 2.0
REPORT_S = 0.01  # a follower under the watchdog reports finished calls at most this often
INTERRUPTED = 130  # the shell's status for a process ended by SIGINT


class CoordinationError(RuntimeError):
    """Misuse of the coordination layer, or ranks that executed different commands."""


class CollectiveError(Exception):
    """An error that every rank raises at the same point of the same parallel call.

    Subclasses (a diverged simulation, say) do not abort the job: followers drop them and go on
    serving, and the leader's caller may handle them. Raise one only where the condition is
    known on every rank, e.g. after a reduction.
    """


class SequenceDivergence(CoordinationError, CollectiveError):
    """Ranks executed different parallel methods (found by the ``check`` option)."""


def wait_for(
    ready: Callable[[], bool],
    spin_s: float,
    max_sleep_s: float,
    oversubscribed: bool,
    idle: Callable[[], None] | None = None,
) -> None:
    """Return once ``ready()`` is true (a message has arrived). Polls busily for ``spin_s``
    seconds, yielding the core at each poll when ranks outnumber cores (the rank we wait for
    may need it), then sleeps between polls, 10 us doubling up to ``max_sleep_s`` (the worst
    extra latency of an idle rank), calling ``idle()`` after each sleep."""
    spin_until = time.perf_counter() + spin_s
    while not ready():
        if oversubscribed:
            os.sched_yield()
        if time.perf_counter() > spin_until:
            sleep = 1e-5
            while not ready():
                time.sleep(sleep)
                sleep = min(2 * sleep, max_sleep_s)
                if idle is not None:
                    idle()
            return


def _fail(
    comm: MPI.Comm, where: str | None, interrupted: str = "interrupted in a parallel call"
) -> None:
    """Print the current exception's traceback (unless ``where`` is None) and end every rank
    of ``comm``; a KeyboardInterrupt (Ctrl-C) is the one line ``interrupted`` instead, and
    status :data:`INTERRUPTED`."""
    if isinstance(sys.exc_info()[1], KeyboardInterrupt):
        _interrupt(comm, interrupted if where else None)
    if where is not None:
        sys.stderr.write(f"[rank {comm.rank}] {where}:\n{traceback.format_exc()}")
        sys.stderr.flush()
    _abort(comm)


def _interrupt(comm: MPI.Comm, why: str | None) -> NoReturn:
    """End every rank of ``comm`` with status :data:`INTERRUPTED`, saying ``why`` (unless
    None) in one line."""
    if why is not None:
        sys.stderr.write(f"[rank {comm.rank}] {why}: every rank exits with status {INTERRUPTED}\n")
        sys.stderr.flush()
    _abort(comm, INTERRUPTED)


def _abort(comm: MPI.Comm, status: int = 1) -> NoReturn:
    """End every rank of ``comm`` with ``status``, after what this rank printed about why; its
    guard (:mod:`physicsrl.guard`) is told that the end is meant."""
    ended()
    time.sleep(0.2)  # let the launcher forward the report before Abort tears the job down
    comm.Abort(status)
    os._exit(status)  # MPICH's Abort can return once it has told the process manager


class abort_on_error:  # noqa: N801 (used as a context manager, like contextlib helpers)
    """End all ranks with exit status 1 when the block raises on any rank.

    Without it, an exception on one rank leaves the others waiting in their next collective.
    The traceback is printed once when every rank fails alike: a failing follower reports
    only if the leader's abort has not ended it within :data:`LEADER_FAILED_GRACE_S`. A Ctrl-C
    (KeyboardInterrupt) is one line and status :data:`INTERRUPTED` instead. On one rank the
    exception propagates unchanged.
    """

    def __init__(self, comm: MPI.Comm = MPI.COMM_WORLD):
        self.comm = comm

    def __enter__(self):
        return self

    def __exit__(self, kind, value, tb):
        if kind is None or self.comm.size == 1 or issubclass(kind, SystemExit):
            return False
        if self.comm.rank != 0:
            time.sleep(LEADER_FAILED_GRACE_S)
        _fail(self.comm, "uncaught exception, aborting all ranks", "interrupted")
        return False


def _seconds(value: Any) -> bool:
    """Whether ``value`` is a finite real number (not a bool)."""
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _identity(obj: Any, function: Callable) -> str | Callable:
    """What names ``function`` to the followers: its name where ``obj``'s class resolves it to
    ``function``, else the parallel method of a base class that wraps it (sent by reference),
    else ``function`` itself (a free function, a lambda)."""
    name = function.__name__
    named = getattr(type(obj), name, None)
    if getattr(named, "__wrapped__", named) is function:
        return name
    for owner in type(obj).__mro__:
        attribute = vars(owner).get(name)
        if getattr(attribute, "__wrapped__", None) is function:
            return attribute
    return function


def _serialise(args: tuple, kwargs: dict) -> tuple[bytes, int]:
    """Pickle call arguments, falling back to cloudpickle; raise TypeError if neither can."""
    try:
        return pickle.dumps((args, kwargs), protocol=5), _PICKLE
    except Exception:  # noqa: BLE001 - PicklingError, TypeError, ValueError (an MPI comm), ...
        pass
    import cloudpickle

    try:
        return cloudpickle.dumps((args, kwargs), protocol=5), _CLOUDPICKLE
    except Exception as error:
        shown = reprlib.repr((args, kwargs))  # bounded: arguments can be huge or deeply nested
        raise TypeError(f"arguments {shown} cannot be serialised: {error}") from None


class Coordinator:
    """Multiplexes the parallel calls of all registered objects over one communicator.

    Parameters
    ----------
    comm:
        The communicator whose rank 0 is the leader.
    spin_s:
        Seconds an idle follower busy-polls after the last call before it starts sleeping.
    max_sleep_s:
        Longest sleep between two polls of an idle follower (its worst-case extra latency).
    check:
        Verify after every call that all ranks executed the same sequence of parallel methods
        (costs one ``allgather`` per call). Defaults to the ``PHYSICSRL_CHECK_SEQUENCE``
        environment variable.
    timeout:
        Seconds after which a parallel call that some ranks have not finished aborts the job
        with one line naming the call and those ranks; None (the default, or the
        ``PHYSICSRL_TIMEOUT`` environment variable) turns the watchdog off at no cost. The
        leader's value is used on every rank. When on, every follower sends the leader one
        small message per call, and a thread on the leader checks them.
    """

    def __init__(
        self,
        comm: MPI.Comm = MPI.COMM_WORLD,
        spin_s: float = 0.05,
        max_sleep_s: float = 0.002,
        check: bool | None = None,
        timeout: float | None = None,
    ):
        if not isinstance(comm, MPI.Comm):
            raise CoordinationError(f"comm={comm!r}: must be an MPI communicator")
        for name, seconds in (("spin_s", spin_s), ("max_sleep_s", max_sleep_s)):
            if not _seconds(seconds) or seconds < 0:
                raise CoordinationError(f"{name}={seconds!r}: must be a number of seconds >= 0")
        if check is not None and not isinstance(check, bool):
            raise CoordinationError(f"check={check!r}: must be True, False or None")
        if timeout is not None and not (_seconds(timeout) and timeout > 0):
            raise CoordinationError(f"timeout={timeout!r}: must be a number of seconds > 0")
        self.comm = comm
        self.rank = comm.rank
        self.size = comm.size
        self._channel = comm  # a duplicate of comm inside the with-block (__enter__)
        self._oversubscribed = False  # more ranks on this node than cores: yield when polling
        if comm.size > 1:
            on_this_node = comm.Split_type(MPI.COMM_TYPE_SHARED)
            self._oversubscribed = on_this_node.size > len(os.sched_getaffinity(0))
            on_this_node.Free()
        # Binomial tree rooted at the leader: the parent clears r's highest bit; the children
        # add each higher power of two.
        high = 1 << (self.rank.bit_length() - 1) if self.rank else 0
        self._parent = self.rank - high
        step = 2 * high if self.rank else 1
        self._children = []
        while self.rank + step < self.size:
            self._children.append(self.rank + step)
            step *= 2
        self.spin_s = spin_s
        self.max_sleep_s = max_sleep_s
        try:
            self.check = check_sequence_from_environment() if check is None else check
            self.timeout = timeout_from_environment() if timeout is None else timeout
        except ValueError as error:
            raise CoordinationError(str(error)) from None
        self._watchdog: _Watchdog | None = None  # the leader's, while the watchdog is on
        self._done: MPI.Prequest | None = None  # a follower's report of a finished call
        self._done_sequence = np.zeros(1, dtype=np.int32)
        self._failed = np.zeros(1, dtype=np.int32)  # the leader's word that its call failed
        self._unreported = False  # a finished call waits for the previous report to go out
        self._next_report = 0.0  # time.monotonic() of the next report
        self.objects: dict[Hashable, Any] = {}
        self.depth = 0  # >0 while a parallel method runs: nested calls are not re-sent
        self.direct = False  # calls need no coordination: one rank, or nested (fast path)
        self._local = False  # inside the with-block on a single rank
        self._inside = False
        self._next_namespace = 0
        self._routes: dict[tuple[Hashable, str | Callable], int] = {}  # leader: -> route id
        self._handlers: list[tuple[Any, Callable]] = []  # follower: id -> (object, function)
        self._message = bytearray(_HEADER.size + INLINE_BYTES)
        self._view = memoryview(self._message)
        self._sequence = 0
        self.broadcast_s = 0.0  # the leader's seconds in broadcast(), in total: coordination
        self._sending: list[MPI.Prequest] = []
        self._receiving: MPI.Prequest | None = None
        self._trace: list[str] = []
        self._interrupted_at: float | None = None  # a follower's Ctrl-C (serve), when

    # registration -------------------------------------------------------------------------
    def register(self, obj: Any, namespace: Hashable | None = None) -> Hashable:
        """Register ``obj`` under ``namespace`` (default: the next integer) and return it.

        Register corresponding objects in the same order on every rank, or give each an
        explicit namespace.
        """
        if namespace is None:
            while self._next_namespace in self.objects:
                self._next_namespace += 1
            namespace = self._next_namespace
        if namespace in self.objects:
            raise CoordinationError(f"namespace {namespace!r} is already registered")
        self.objects[namespace] = obj
        return namespace

    def is_leader(self) -> bool:
        return self.rank == 0

    def is_ready_to_broadcast(self) -> bool:
        """True on the leader inside ``with coordinator``."""
        return self._inside and self.rank == 0

    # leader side ------------------------------------------------------------------------
    def call(self, obj: Coordinated, function: Callable, args: tuple, kwargs: dict) -> Any:
        """Run ``function(obj, *args, **kwargs)`` on every rank; return this rank's result."""
        if self.depth == 0:
            if not self._inside:
                raise CoordinationError(
                    f"{type(obj).__name__}.{function.__name__} is a parallel method: call it "
                    "inside 'with coordinator:', on the leader (if coordinator.is_leader():); "
                    "the followers serve there until the leader leaves the block"
                )
            if self.rank == 0 and self.size > 1:
                self.broadcast(obj._namespace, function, args, kwargs)
                if self._watchdog is not None:
                    self._watchdog.started(self._sequence, obj, function)
                    try:
                        return self.execute(obj, function, args, kwargs)
                    finally:
                        self._watchdog.finished(0, self._sequence)
        return self.execute(obj, function, args, kwargs)

    def broadcast(
        self,
        namespace: Hashable,
        method: str | Callable,
        args: tuple = (),
        kwargs: dict | None = None,
    ) -> None:
        """Send the call ``method(objects[namespace], *args, **kwargs)`` to every follower:
        ``method`` the name of a method of the object's class, or a function (named to the
        followers once, by :func:`_identity`).

        Leader only. Arguments are serialised before anything is sent, so an argument that
        cannot be serialised raises here and the followers stay in step.
        """
        if not (self._inside and self.rank == 0):
            raise CoordinationError("broadcast() is for the leader inside 'with coordinator'")
        started = time.perf_counter()
        flags = 0
        payload = b""
        if args or kwargs:
            payload, flags = _serialise(args, kwargs or {})
        route = self._routes.get((namespace, method))
        if route is None:
            route = len(self._routes)
            named = _identity(self.objects[namespace], method) if callable(method) else method
            definition, _ = _serialise((namespace, named), {})
            payload = len(definition).to_bytes(4, "little") + definition + payload
            flags |= _DEFINE
            self._routes[(namespace, method)] = route
        self._send(route, flags, payload)
        self.broadcast_s += time.perf_counter() - started

    def _send(self, route: int, flags: int, payload: bytes) -> None:
        n = len(payload)
        self._sequence += 1
        _HEADER.pack_into(self._message, 0, route, flags, n, self._sequence)
        if n:
            inline = min(n, INLINE_BYTES)
            self._message[_HEADER.size : _HEADER.size + inline] = payload[:inline]
        self._forward()
        if n > INLINE_BYTES:
            self._channel.Bcast(bytearray(payload[INLINE_BYTES:]), 0)

    def _forward(self) -> None:
        """Send the message buffer to this rank's children in the tree."""
        for request in self._sending:
            request.Start()
            request.Wait()

    # follower side ----------------------------------------------------------------------
    def _receive(self) -> tuple[int, int, bytes | memoryview]:
        """Wait for the leader's next message and pass it on; return (route, flags, payload)."""
        self._receiving.Start()
        if not self._receiving.Test():  # the hot path: the next call is already here
            wait_for(
                self._receiving.Test,
                self.spin_s,
                self.max_sleep_s,
                self._oversubscribed,
                idle=self._idle,
            )
        self._forward()
        route, flags, n, self._sequence = _HEADER.unpack_from(self._message)
        if n <= INLINE_BYTES:
            return route, flags, self._view[_HEADER.size : _HEADER.size + n]
        rest = bytearray(n - INLINE_BYTES)
        self._channel.Bcast(rest, 0)
        return route, flags, bytes(self._view[_HEADER.size :]) + rest

    def _idle(self) -> None:
        if self._unreported:
            self._report()
        self._check_interrupted()

    def _check_interrupted(self) -> None:
        """End every rank if this follower's Ctrl-C is older than :data:`LEADER_FAILED_GRACE_S`
        and the leader has not ended the block since (it was not interrupted)."""
        if self._interrupted_at is not None:
            if time.monotonic() - self._interrupted_at > LEADER_FAILED_GRACE_S:
                _interrupt(self.comm, "interrupted, and the leader was not")

    def serve(self) -> None:
        """Run the leader's calls until it leaves its ``with`` block (followers only).

        A Ctrl-C between calls is noted, not raised: the terminal interrupts the leader too,
        which then ends every rank with status :data:`INTERRUPTED` (``__exit__``); a follower
        interrupted alone ends every rank after :data:`LEADER_FAILED_GRACE_S`. Inside a call it
        raises KeyboardInterrupt, which ends every rank with that status (:func:`_fail`). A
        SIGINT handler of the program's own is kept (``physicsrl-train``'s followers ignore it:
        the leader checkpoints first)."""
        self._interrupted_at = None
        previous = None
        main = threading.current_thread() is threading.main_thread()
        if main and signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            previous = signal.signal(signal.SIGINT, self._note_interrupt)
        try:
            self._serve()
        except SystemExit as stop:
            if stop.code == INTERRUPTED:
                previous = signal.SIG_IGN  # a Ctrl-C still on its way would end us by SIGINT
            raise
        finally:
            if previous is not None:
                signal.signal(signal.SIGINT, previous)

    def _note_interrupt(self, signum, frame) -> None:
        if self.depth:
            raise KeyboardInterrupt
        if self._interrupted_at is None:
            self._interrupted_at = time.monotonic()

    def _serve(self) -> None:
        while True:
            route, flags, payload = self._receive()
            if route == _STOP:
                if self._done is not None:  # the leader waits for this last report
                    self._done.Wait()
                    self._done_sequence[0] = self._sequence
                    self._done.Start()
                    self._done.Wait()
                return
            if route == _FAIL:
                raise SystemExit(1)  # the leader failed and printed its traceback
            if route == _EXIT:
                raise SystemExit(flags)  # the leader exits with this status: so do we
            try:
                if flags & _DEFINE:
                    n = int.from_bytes(payload[:4], "little")
                    (namespace, method), _ = pickle.loads(payload[4 : 4 + n])
                    payload = payload[4 + n :]
                    obj = self.objects[namespace]
                    function = getattr(type(obj), method) if isinstance(method, str) else method
                    self._handlers.append((obj, getattr(function, "__wrapped__", function)))
                obj, function = self._handlers[route]
                # cloudpickle's payloads load with pickle too
                args, kwargs = pickle.loads(payload) if flags & _SERIALISED else ((), {})
                self.execute(obj, function, args, kwargs)
            except CollectiveError:
                pass  # the leader raises it too, and its caller decides
            except BaseException:
                # The same call often fails on several ranks: the traceback is printed once, by
                # the lowest rank that failed (each tells the ranks above it, and the leader's
                # watchdog, which then leaves the report to it).
                for rank in (0, *range(self.rank + 1, self.size)):
                    self._channel.Isend(self._failed, rank, _FAILED_TAG)
                if self._lower_rank_failed(LEADER_FAILED_GRACE_S):
                    time.sleep(LEADER_FAILED_GRACE_S)  # its abort normally ends us here
                    _fail(self.comm, None)
                _fail(self.comm, "exception in a parallel method on a follower")
            if self._done is not None:
                self._unreported = True
                if time.monotonic() >= self._next_report:
                    self._report()
            self._check_interrupted()

    def _lower_rank_failed(self, seconds: float) -> bool:
        """Whether a lower rank (the leader, or a follower) says, within ``seconds``, that its
        call failed as well."""
        deadline = time.monotonic() + seconds
        while not self._channel.Iprobe(MPI.ANY_SOURCE, _FAILED_TAG):
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.01)
        return True

    def _report(self) -> None:
        """Tell the leader's watchdog the last call this follower finished, unless the previous
        report is still on its way (then the idle loop sends it later). Reports go at most
        every ``REPORT_S``: testing the previous one costs more than a call."""
        self._next_report = time.monotonic() + REPORT_S
        if self._done.Test():
            self._done_sequence[0] = self._sequence
            self._done.Start()
            self._unreported = False

    # both sides ------------------------------------------------------------------------
    def execute(self, obj: Any, function: Callable, args: tuple, kwargs: dict) -> Any:
        """Run one parallel call on this rank, marking it so nested calls are not re-sent."""
        if self.check:
            self._trace.append(f"{type(obj).__qualname__}[{obj._namespace!r}].{function.__name__}")
        self.depth += 1
        self.direct = not self.check
        try:
            result = function(obj, *args, **kwargs)
        except CollectiveError:
            raise
        except BaseException:
            if self.depth == 1 and self.rank == 0 and self.size > 1:
                # The followers may be waiting in a collective of this call: end them all.
                for rank in range(1, self.size):  # those that fail too then keep quiet
                    self._channel.Isend(self._failed, rank, _FAILED_TAG)
                _fail(self.comm, "exception in a parallel method on the leader")
            raise
        finally:
            self.depth -= 1
            self.direct = self._local or (self.depth > 0 and not self.check)
        if self.check and self.depth == 0:
            self._check_sequence()
        return result

    def _update_direct(self) -> None:
        self._local = self._inside and self.size == 1
        self.direct = self._local or (self.depth > 0 and not self.check)

    def _check_sequence(self) -> None:
        """Compare this call's trace of parallel methods across ranks (collective)."""
        trace, self._trace = self._trace, []
        digest = hashlib.sha1("\n".join(trace).encode()).hexdigest()
        everyone = self.comm.allgather((digest, trace))
        leader_digest, leader_trace = everyone[0]
        for rank, (other_digest, other_trace) in enumerate(everyone):
            if other_digest == leader_digest:
                continue
            pairs = zip(leader_trace, other_trace, strict=False)
            step = next(
                (i for i, (a, b) in enumerate(pairs) if a != b),
                min(len(leader_trace), len(other_trace)),
            )
            ran = [t[step] if step < len(t) else "nothing" for t in (leader_trace, other_trace)]
            raise SequenceDivergence(
                f"ranks diverged in call {self._sequence}, step {step}: the leader ran "
                f"{ran[0]}, rank {rank} ran {ran[1]}"
            )

    # the with-block -------------------------------------------------------------------
    def __enter__(self) -> Coordinator:
        if self._inside:
            raise CoordinationError("this coordinator is already inside a 'with' block")
        self._inside = True
        self._update_direct()
        if self._local and not self.check:
            for obj in self.objects.values():
                _bind_directly(obj)
        # A communicator of its own, so that the calls' messages never match the user's; freed
        # when the block ends (MPI has a few thousand communicators per process).
        self._channel = self.comm.Dup() if self.size > 1 else self.comm
        # Persistent requests: a third of the cost of a fresh Send/Irecv per message.
        self._sending = [self._channel.Send_init(self._message, c, _TAG) for c in self._children]
        if self.size > 1:
            self.timeout, self.check = self._channel.bcast((self.timeout, self.check), 0)
            multiple = MPI.Query_thread() >= MPI.THREAD_MULTIPLE
            if self.timeout is not None and not self._channel.allreduce(multiple, op=MPI.LAND):
                self._close()
                raise CoordinationError(
                    "the watchdog (timeout, PHYSICSRL_TIMEOUT) needs MPI initialised with "
                    "THREAD_MULTIPLE on every rank"
                )
        if self.timeout is not None and self.size > 1:
            if self.rank == 0:
                self._watchdog = _Watchdog(self._channel, self.timeout)
            else:
                self._done = self._channel.Send_init(self._done_sequence, 0, _DONE_TAG)
        if self.rank != 0:
            self._receiving = self._channel.Recv_init(self._message, self._parent, _TAG)
            try:
                self.serve()
            finally:
                self._close()
        return self

    def _close(self) -> None:
        if self._watchdog is not None:
            self._watchdog.stop()
        for request in [*self._sending, self._receiving, self._done]:
            if request:
                request.Free()
        self._sending, self._receiving, self._done, self._watchdog = [], None, None, None
        if self._channel is not self.comm:
            self._channel.Free()
            self._channel = self.comm
        if self._local:
            for obj in self.objects.values():
                _unbind(obj)
        self._inside = False
        self._update_direct()

    def __exit__(self, kind, value, tb) -> bool:
        if self.rank != 0:
            return False
        interrupted = kind is not None and issubclass(kind, KeyboardInterrupt) and self.size > 1
        if interrupted and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, signal.SIG_IGN)  # the launcher may send it again
        try:
            if self.size == 1:
                pass
            elif kind is None:
                self._send(_STOP, 0, b"")
                if self._watchdog is not None:
                    self._watchdog.wait_for_everyone(self._sequence)
            elif issubclass(kind, SystemExit):
                self._send(_EXIT, _exit_status(value.code), b"")
            elif interrupted:
                self._send(_EXIT, INTERRUPTED, b"")
            else:
                self._send(_FAIL, 0, b"")
        finally:
            self._close()
        if interrupted:
            sys.stderr.write(f"interrupted: every rank exits with status {INTERRUPTED}\n")
            raise SystemExit(INTERRUPTED) from None
        return False


def _exit_status(code: Any) -> int:
    """The process exit status of ``SystemExit(code)``, as Python computes it."""
    if code is None:
        return 0
    return code & 0xFF if isinstance(code, int) else 1  # the OS keeps the low 8 bits


class _Watchdog:
    """The leader's thread that aborts every rank when a parallel call overstays ``timeout``.

    The leader notes when each call started and that it finished it itself; each follower
    reports the last call it finished in a small message on ``channel``. Every ``timeout / 4``
    seconds (at most 0.25 s) the thread reads the reports and forgets the calls every rank has
    finished; if the oldest call left started more than ``timeout`` seconds ago, the ranks that
    have not finished it end the job. A follower whose call failed says so at once and reports
    after its grace (:data:`LEADER_FAILED_GRACE_S`): the watchdog leaves the end to it for
    that long, so that a timeout shorter than the grace does not hide the traceback.
    """

    def __init__(self, channel: MPI.Comm, timeout: float):
        self.channel = channel
        self.timeout = timeout
        self.interval = min(timeout / 4, 0.25)
        self._finished = [0] * channel.size  # rank -> the last call it finished
        self._calls: collections.deque[tuple[int, Any, Callable, float]] = collections.deque()
        self._wake = threading.Event()
        self._stopping = False
        self._thread = threading.Thread(target=self._watch, name="physicsrl-watchdog", daemon=True)
        self._thread.start()

    def started(self, sequence: int, obj: Any, function: Callable) -> None:
        self._calls.append((sequence, obj, function, time.monotonic()))

    def finished(self, rank: int, sequence: int) -> None:
        self._finished[rank] = sequence

    def wait_for_everyone(self, sequence: int) -> None:
        """Block until every rank has reported call ``sequence`` (or the watchdog aborts)."""
        self._finished[0] = sequence
        self.interval = 1e-3
        while min(self._finished) < sequence:
            self._wake.set()
            time.sleep(1e-3)

    def stop(self) -> None:
        self._stopping = True
        self._wake.set()
        self._thread.join()

    def _watch(self) -> None:
        report = np.zeros(1, dtype=np.int32)
        status = MPI.Status()
        while not self._stopping:
            self._wake.wait(self.interval)
            self._wake.clear()
            while self.channel.Iprobe(MPI.ANY_SOURCE, _DONE_TAG, status):
                self.channel.Recv(report, status.Get_source(), _DONE_TAG)
                self._finished[status.Get_source()] = int(report[0])
            everyone = min(self._finished)
            while self._calls and self._calls[0][0] <= everyone:
                self._calls.popleft()
            if not self._calls or time.monotonic() - self._calls[0][3] < self.timeout:
                continue
            overdue = time.monotonic() - self._calls[0][3] - self.timeout
            if overdue < 2 * LEADER_FAILED_GRACE_S and self.channel.Iprobe(
                MPI.ANY_SOURCE, _FAILED_TAG
            ):
                continue  # a follower failed: it reports and ends the job after its grace
            sequence, obj, function, _ = self._calls[0]
            late = [rank for rank, done in enumerate(self._finished) if done < sequence]
            name = f"{type(obj).__name__}.{function.__name__}"
            sys.stderr.write(
                f"watchdog: parallel call {name} (call {sequence}) has not finished after "
                f"{self.timeout:g} s on ranks {late}; aborting every rank\n"
            )
            sys.stderr.flush()
            _abort(self.channel)


class _Unregistered:
    """The coordinator of a Coordinated object before ``register_coordinator``."""

    direct = False

    def call(self, obj: Any, function: Callable, args: tuple, kwargs: dict) -> Any:
        raise CoordinationError(
            f"{type(obj).__name__}.{function.__name__}: call register_coordinator() before "
            "parallel methods"
        )


class Coordinated:
    """Base class of objects whose ``@parallel`` methods run on every rank.

    Call :meth:`register_coordinator` in the constructor (on every rank, in the same order, or
    with explicit namespaces). It is a method rather than a constructor argument so that
    subclasses can also derive from other bases (a TorchRL ``EnvBase``, say).
    """

    _coordinator: Coordinator | _Unregistered = _Unregistered()
    _namespace: Hashable | None = None

    def register_coordinator(self, coordinator: Coordinator, namespace: Hashable | None = None):
        self._coordinator = coordinator
        self._namespace = coordinator.register(self, namespace)

    @property
    def coordinator(self) -> Coordinator:
        if isinstance(self._coordinator, _Unregistered):
            raise CoordinationError(f"{type(self).__name__}: call register_coordinator() first")
        return self._coordinator

    def run_method_in_parallel(self, function: Callable, *args, **kwargs) -> Any:
        """Run ``function(self, *args, **kwargs)`` on every rank; return the leader's result."""
        return self._coordinator.call(self, function, args, kwargs)


def parallel(method: Callable) -> Callable:
    """Mark a method of a :class:`Coordinated` subclass to run on every rank.

    The leader's call is replayed on every follower's object of the same namespace; calls
    made from inside another parallel method are not sent again (the followers make them
    themselves); the leader gets the return value.
    """

    if inspect.isgeneratorfunction(method) or inspect.iscoroutinefunction(method):
        raise TypeError(
            f"@parallel {method.__qualname__}: a generator or coroutine runs only where it is "
            "iterated; return a list instead"
        )

    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        coordinator = self._coordinator
        if coordinator.direct:  # one rank, or nested in another parallel call
            return method(self, *args, **kwargs)
        return coordinator.call(self, method, args, kwargs)

    wrapper.parallel = True
    return wrapper


def _bind_directly(obj: Any) -> None:
    """Shadow the parallel methods of ``obj`` with its plain bound methods.

    On one rank nothing needs coordinating, and a plain bound method costs a quarter of the
    wrapper's ``*args, **kwargs`` forwarding.
    """
    attributes = getattr(obj, "__dict__", None)
    if attributes is None:
        return
    for name in dir(type(obj)):
        wrapper = getattr(type(obj), name, None)
        if getattr(wrapper, "parallel", False) is True:
            attributes[name] = wrapper.__wrapped__.__get__(obj)


def _unbind(obj: Any) -> None:
    attributes = getattr(obj, "__dict__", None)
    for name in list(attributes or ()):
        if getattr(getattr(type(obj), name, None), "parallel", False) is True:
            del attributes[name]


def random(comm: MPI.Comm = MPI.COMM_WORLD, rng: np.random.Generator | None = None) -> float:
    """A uniform float in [0, 1) drawn on the leader and shared with every rank (collective)."""
    value = (rng or np.random.default_rng()).random() if comm.rank == 0 else None
    return comm.bcast(value, 0)


def randint(comm: MPI.Comm, a: int, b: int, rng: np.random.Generator | None = None) -> int:
    """An integer uniform in [a, b] (both included) drawn on the leader, shared (collective).
    ``a`` and ``b`` are integers with a <= b (checked on every rank: call it alike everywhere)."""
    a, b = operator.index(a), operator.index(b)
    if a > b:
        raise ValueError(f"randint: a = {a} must be <= b = {b}")
    value = int((rng or np.random.default_rng()).integers(a, b + 1)) if comm.rank == 0 else None
    return comm.bcast(value, 0)
