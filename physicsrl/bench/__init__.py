"""Benchmarks behind ``physicsrl-bench``: each module has ``run(cfg) -> list[dict]`` (table rows)
and optionally ``goals(rows)``.

:data:`SETTINGS` holds, per benchmark, the type and least value of each of its settings, or
the tuple of its choices (``conf/bench_<name>.yaml``), checked before the benchmark's module is
imported (it imports torch or DOLFINx, seconds): a bad value is a one-line error at once.
"""

SETTINGS: dict[str, dict[str, tuple[type | tuple[str, ...], float | None]]] = {
    "ping": {"calls": (int, 1), "repeats": (int, 1), "idle_seconds": (float, 0.0)},
    "ms": {
        "grid.n": (int, 2),
        "steps": (int, 1),
        "steps_per_call": (int, 1),
        "scheme": (("implicit", "explicit", "both"), None),
        "rhs": (("compiled", "numpy", "form"), None),
        "baseline": (bool, None),
        "max_memory_gb": (float, 0.0),
    },
    "env": {
        "seed": (int, 0),
        "decisions": (int, 1),
        "shock_every": (int, 1),
        "baseline": (bool, None),
        "baseline_decisions": (int, 1),
        "max_memory_gb": (float, 0.0),
    },
    "groups": {
        "atp": (bool, None),
        "seed": (int, 0),
        "decisions": (int, 1),
        "shock_every": (int, 1),
        "noop_steps": (int, 1),
        "max_memory_gb": (float, 0.0),
    },
}
