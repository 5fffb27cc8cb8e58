"""The ms benchmark core runs both implementations, which compute the same field."""

from __future__ import annotations

import physicsrl.fem  # noqa: F401  (first: loads the MPI library that dolfinx links to)

# isort: split

from omegaconf import OmegaConf

from physicsrl.bench import ms


def test_ms_benchmark_core_on_a_tiny_grid():
    """20 x 20 cells (the stimulus covers the cells of midpoints x = +-2.5), 40 steps
    (stimulus in the first 30): one row per implementation with positive step times; the
    baseline's final u equals physicsrl's implicit one within 1e-8, the floor's equals the
    explicit one to round-off (the structured stencil is the assembled operator), and the
    explicit differs from the implicit (another scheme); the one goal of this grid is judged
    from the rows' own times, as is a row of another right-hand side."""
    cfg = {"grid": {"n": 20}, "steps": 40, "steps_per_call": 1, "baseline": True}
    rows = ms.run(OmegaConf.create({**cfg, "scheme": "both", "rhs": "compiled"}))
    names = ["physicsrl", "physicsrl explicit", "floor (structured C loop)", "report (baseline)"]
    assert [row["implementation"] for row in rows] == names
    for row in rows:
        assert row["dofs"] == 441 and row["step_ms"] > 0
    assert rows[0]["solve_ms"] > 0 and rows[1]["explicit_ms"] > 0
    assert rows[3]["max_abs_diff_u"] < 1e-8
    assert rows[2]["max_abs_diff_u"] < 1e-13
    assert rows[1]["max_abs_diff_u"] > 1e-3
    ratio = round(rows[3]["step_ms"] / rows[0]["step_ms"], 2)  # the goal's: baseline / implicit
    assert ms.goals(rows) == [(f"20x20, 1 ranks: {ratio}x the baseline >= 10x", ratio >= 10)]
    numpy = {**rows[0], "implementation": "physicsrl (rhs=numpy)", "step_ms": rows[3]["step_ms"]}
    assert ms.goals([numpy, rows[3]]) == [("20x20, 1 ranks: 1.0x the baseline >= 10x", False)]
