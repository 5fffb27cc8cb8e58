"""``physicsrl-bench ping``: the cost of one parallel call (report section 3.5, Table 1).

Measured side by side, interleaved, on the same ranks: physicsrl's ``@parallel``; a minimal
re-implementation of the report's design (pickled dict sent with ``comm.bcast``, dispatched with
``getattr``) as the baseline; and the floor, a 16-byte buffer ``Bcast`` per call. Each method
makes ``calls`` no-op calls (and a variant with a float and a short tuple as arguments); the
time per call is the leader's wall time from a barrier before the first call to a barrier after
the followers have run the last one. Also measured: physicsrl with its watchdog on (the
``timeout`` option: one report message per call and follower), and the CPU use of a follower
while the leader is idle (training, say) for ``idle_seconds``.
"""

from __future__ import annotations

import statistics
import time

from mpi4py import MPI

from physicsrl.baselines.report_coordinated import (
    ReportCoordinated,
    ReportCoordinator,
    report_parallel,
)
from physicsrl.coordinated import Coordinated, Coordinator, parallel

SMALL_ARGUMENT = (1.5, (1, 2))
IDLE = "idle follower CPU (fraction of a core)"
WATCHDOG_S = 600.0  # long enough never to fire: only its cost is measured


class PingEnvironment(Coordinated):
    """The report's benchmark object: one parallel no-op."""

    def __init__(self, coordinator: Coordinator):
        self.register_coordinator(coordinator)

    @parallel
    def ping(self, *args):
        pass


class ReportPingEnvironment(ReportCoordinated):
    def __init__(self, coordinator: ReportCoordinator):
        self.register_coordinator(coordinator)

    @report_parallel
    def ping(self, *args):
        pass


def time_calls(comm: MPI.Comm, coordinator, target, args: tuple, calls: int) -> float:
    """Microseconds per ``target.ping(*args)`` call, all ranks included."""
    comm.Barrier()
    start = time.perf_counter()
    with coordinator:
        if coordinator.is_leader():
            for _ in range(calls):
                target.ping(*args)
    comm.Barrier()
    return (time.perf_counter() - start) / calls * 1e6


def time_floor(comm: MPI.Comm, calls: int) -> float:
    """Microseconds per 16-byte buffer ``Bcast``: what no implementation can beat."""
    buffer = bytearray(16)
    comm.Barrier()
    start = time.perf_counter()
    for _ in range(calls):
        comm.Bcast(buffer, 0)
    comm.Barrier()
    return (time.perf_counter() - start) / calls * 1e6


def idle_follower_cpu(comm: MPI.Comm, coordinator: Coordinator, seconds: float) -> float:
    """The largest fraction of a core a follower uses while the leader idles ``seconds``."""
    cpu, wall = time.process_time(), time.perf_counter()
    with coordinator:
        if coordinator.is_leader():
            time.sleep(seconds)
    fraction = (time.process_time() - cpu) / (time.perf_counter() - wall)
    return max(comm.allgather(fraction if comm.rank else 0.0))


def run(cfg) -> list[dict]:
    comm = MPI.COMM_WORLD
    coordinator, report = Coordinator(comm), ReportCoordinator(comm)
    ours, theirs = PingEnvironment(coordinator), ReportPingEnvironment(report)
    watched = Coordinator(comm, timeout=WATCHDOG_S)
    ours_watched = PingEnvironment(watched)
    methods = {
        "physicsrl": lambda: time_calls(comm, coordinator, ours, (), cfg.calls),
        "physicsrl, watchdog on": lambda: time_calls(comm, watched, ours_watched, (), cfg.calls),
        "report design": lambda: time_calls(comm, report, theirs, (), cfg.calls),
        "floor (Bcast 16 B)": lambda: time_floor(comm, cfg.calls),
        "physicsrl, small argument": lambda: time_calls(
            comm, coordinator, ours, SMALL_ARGUMENT, cfg.calls
        ),
        "report design, small argument": lambda: time_calls(
            comm, report, theirs, SMALL_ARGUMENT, cfg.calls
        ),
    }
    samples: dict[str, list[float]] = {name: [] for name in methods}
    for _ in range(cfg.repeats):
        for name, measure in methods.items():
            samples[name].append(measure())
    idle = idle_follower_cpu(comm, coordinator, cfg.idle_seconds) if comm.size > 1 else 0.0

    median = {name: statistics.median(values) for name, values in samples.items()}
    floor = median["floor (Bcast 16 B)"]
    rows = []
    for name, values in samples.items():
        baseline = median[f"report design{', small argument' if 'argument' in name else ''}"]
        rows.append(
            {
                "ranks": comm.size,
                "method": name,
                "us_per_call": round(median[name], 3),
                "min_us": round(min(values), 3),
                "vs_report": round(median[name] / baseline, 3),
                "vs_floor": round(median[name] / floor, 3),
            }
        )
    rows.append({"ranks": comm.size, "method": IDLE, "us_per_call": round(idle, 4)})
    return rows


def goals(rows: list[dict]) -> list[tuple[str, bool]]:
    """The issue's goals, each with whether this run met it."""
    by_method = {row["method"]: row for row in rows}
    ours, ranks = by_method["physicsrl"], rows[0]["ranks"]
    if ranks == 1:
        return [(f"1 rank: {ours['us_per_call']} us <= 0.5 us", ours["us_per_call"] <= 0.5)]
    idle = by_method[IDLE]["us_per_call"]
    return [
        (f"physicsrl {ours['vs_report']}x the report design <= 0.5x", ours["vs_report"] <= 0.5),
        (f"physicsrl {ours['vs_floor']}x the floor <= 1.5x", ours["vs_floor"] <= 1.5),
        (f"idle follower uses {idle:.1%} of a core < 10%", idle < 0.10),
    ]
