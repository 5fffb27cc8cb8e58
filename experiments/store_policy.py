"""Store a trained policy: a training checkpoint without its replay buffer, optimizer, loss and
generator states (~90 kB instead of ~12 MB), which ``physicsrl-eval run=<file>`` loads.

    python experiments/store_policy.py <checkpoint or run directory> <out.torchrl>
"""

from __future__ import annotations

import argparse
from pathlib import Path

from torchrl.checkpoint import Checkpoint, JSONCheckpointAdapter, StateDictCheckpointAdapter

from physicsrl.checkpoint import State, read
from physicsrl.run_directory import checkpoint_path

KEPT = {"counters": True, "extra": False, "history": False, "q_network": True}
"""The components physicsrl-eval reads; True: a state dict, False: a JSON value."""


def main() -> None:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument("run", help="a checkpoint file, or a run directory (its newest)")
    parser.add_argument("out", type=Path, help="a new file (TorchRL would replace a directory)")
    args = parser.parse_args()
    if args.out.exists():
        parser.error(f"{args.out} exists: name a new file")
    try:
        source = checkpoint_path(args.run)
    except ValueError as error:
        parser.error(str(error))
    write_policy(args.out, read(source, KEPT))
    print(f"{args.out}: the policy of {source}")


def write_policy(out: Path, states: dict) -> None:
    """Write the components ``KEPT`` of ``states`` (by name, as :func:`read` gives them) as the
    policy file ``out``."""
    checkpoint = Checkpoint()
    for name, is_state in KEPT.items():
        if is_state:
            state = State(lambda value=states[name]: value, None)
            checkpoint.register(name, state, adapter=StateDictCheckpointAdapter())
        else:
            checkpoint.register(name, states[name], adapter=JSONCheckpointAdapter())
    checkpoint.save(out, format="archive")


if __name__ == "__main__":
    main()
