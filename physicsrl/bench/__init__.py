"""Benchmarks behind `physicsrl-bench`: each module has `run(cfg) -> list[dict]` (table rows)."""
