"""The ms benchmark core runs both implementations, which compute the same field."""

from __future__ import annotations

import physicsrl.fem  # noqa: F401  (first: loads the MPI library that dolfinx links to)

# isort: split

from omegaconf import OmegaConf

from physicsrl.bench import ms


def test_ms_benchmark_core_on_a_tiny_grid():
    """8 x 8 cells, 40 steps (stimulus in the first 30): one row per implementation with
    positive step times, and the baseline's final u equals physicsrl's within 1e-8."""
    rows = ms.run(OmegaConf.create({"grid": {"n": 8}, "steps": 40, "baseline": True}))
    assert [row["implementation"] for row in rows] == ["physicsrl", "report (baseline)"]
    for row in rows:
        assert row["dofs"] == 81 and row["step_ms"] > 0 and row["solve_ms"] > 0
    assert rows[1]["max_abs_diff_u"] < 1e-8
    assert ms.goals(rows)
