"""Tables of results: rows (dicts with the same keys), their means, as aligned text and as CSV.

Plain Python, no torch or MPI: the command line prints and writes tables on the leader only,
after or without the simulation.
"""

from __future__ import annotations

import csv
import subprocess
from collections.abc import Iterable, Mapping
from pathlib import Path


def format_table(rows: list[dict]) -> str:
    """``rows`` as text: a header of the columns in order of first appearance, then one line
    per row, each column left-aligned to its widest cell."""
    columns = list(dict.fromkeys(key for row in rows for key in row))
    cells = [columns] + [[str(row.get(column, "")) for column in columns] for row in rows]
    widths = [max(len(line[i]) for line in cells) for i in range(len(columns))]
    lines = ("  ".join(c.ljust(w) for c, w in zip(line, widths, strict=True)) for line in cells)
    return "\n".join(lines)


def rounded(rows: list[dict]) -> list[dict]:
    """``rows`` with floats to 3 decimals, for :func:`format_table`."""
    return [{k: f"{v:.3f}" if isinstance(v, float) else v for k, v in row.items()} for row in rows]


def write_csv(path: str | Path, rows: list[dict]) -> None:
    """``rows`` as CSV, the columns in order of first appearance."""
    with open(path, "w", newline="") as stream:
        writer = csv.DictWriter(stream, fieldnames=list(dict.fromkeys(k for r in rows for k in r)))
        writer.writeheader()
        writer.writerows(rows)


def mean_metrics(rows: Iterable[Mapping]) -> dict:
    """The mean of each metric over ``rows`` (a metric missing from a row counts as 0; the
    ``seed`` and ``policy`` columns are not metrics)."""
    rows = [{k: v for k, v in row.items() if k not in ("seed", "policy")} for row in rows]
    keys = dict.fromkeys(k for row in rows for k in row)
    return {k: sum(float(r.get(k, 0.0)) for r in rows) / max(len(rows), 1) for k in keys}


def number(text: str) -> int | float:
    """A CSV cell as the number it was written from."""
    try:
        return int(text)
    except ValueError:
        return float(text)


def read_per_policy(path: str | Path) -> dict[str, list[dict]]:
    """A CSV with a ``policy`` column (e.g. one row per policy and seed) as policy -> its rows,
    in the order of first appearance, every other cell a number."""
    rows: dict[str, list[dict]] = {}
    with open(path, newline="") as stream:
        for row in csv.DictReader(stream):
            policy = row.pop("policy")
            rows.setdefault(policy, []).append({k: number(v) for k, v in row.items()})
    return rows


def provenance() -> str:
    """``commit <hash> (CPU: <vector instructions>)`` for the record beside a results file: the
    git commit of this source tree ("unknown" outside a git checkout), and torch's CPU
    capability (e.g. AVX2, AVX512), since float32 results round as those instructions do."""
    import torch  # here, not above: a command line's bad input is refused before torch loads

    git = ["git", "rev-parse", "HEAD"]
    result = subprocess.run(git, capture_output=True, text=True, cwd=Path(__file__).parent)
    commit = result.stdout.strip() or "unknown"
    return f"commit {commit} (CPU: {torch.backends.cpu.get_cpu_capability()})"
