"""Plot a training run's learning curve with baseline returns from a CSV as horizontal lines.

python experiments/learning_curve.py RUN_DIR OUT.png [--baselines BASELINES.csv]
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

from physicsrl.cli.eval import learning_curve


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a physicsrl-train run directory")
    parser.add_argument("out", type=Path, help="the PNG to write")
    parser.add_argument("--baselines", type=Path, help="a CSV with policy and return columns")
    args = parser.parse_args()
    rows = []
    if args.baselines:
        with open(args.baselines) as stream:
            rows = [
                {"policy": r["policy"], "return": float(r["return"])}
                for r in csv.DictReader(stream)
            ]
    if learning_curve(args.run, args.out, rows) is None:
        raise SystemExit(f"{args.run}: no eval/return in its TensorBoard events")
    print(args.out)


if __name__ == "__main__":
    main()
