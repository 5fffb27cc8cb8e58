"""Atomic training checkpoints and random-number-generator states.

A checkpoint is one ``torch.save`` file ``checkpoints/ckpt_<iteration>.pt`` written to a
temporary name first and moved into place with ``os.replace``, so a kill at any moment leaves
either the previous complete checkpoint or the new one, never half a file. The last ``keep``
are kept.
"""

from __future__ import annotations

import os
import random
import re
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = ["CheckpointManager", "rng_state", "set_rng_state", "find_run"]

NAME = re.compile(r"^ckpt_(\d+)\.pt$")


class CheckpointManager:
    """Writes and finds the checkpoints of one run directory."""

    def __init__(self, directory: str | Path, keep: int = 3):
        self.directory = Path(directory)
        self.keep = max(1, int(keep))

    def paths(self) -> list[Path]:
        """Complete checkpoints, oldest first."""
        if not self.directory.is_dir():
            return []
        found = [
            (int(m.group(1)), p) for p in self.directory.iterdir() if (m := NAME.match(p.name))
        ]
        return [p for _, p in sorted(found)]

    def latest(self) -> Path | None:
        paths = self.paths()
        return paths[-1] if paths else None

    def save(self, state: dict, iteration: int) -> Path:
        self.directory.mkdir(parents=True, exist_ok=True)
        final = self.directory / f"ckpt_{iteration:08d}.pt"
        temporary = self.directory / f".ckpt_{iteration:08d}.pt.{os.getpid()}.tmp"
        with open(temporary, "wb") as stream:
            torch.save(state, stream)
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(temporary, final)
        for old in self.paths()[: -self.keep]:
            old.unlink(missing_ok=True)
        return final

    @staticmethod
    def load(path: str | Path) -> dict:
        return torch.load(path, map_location="cpu", weights_only=False)


def find_run(resume: str, runs: Path, exclude: Path | None = None) -> Path:
    """The run directory to resume: ``resume`` itself (a run directory or a checkpoint file),
    or with ``resume == "true"`` the newest directory under ``runs`` holding a checkpoint."""
    if resume.lower() != "true":
        path = Path(resume).expanduser()
        if path.is_file():
            path = path.parent.parent
        if not CheckpointManager(path / "checkpoints").latest():
            raise FileNotFoundError(f"resume={resume}: no checkpoint under {path / 'checkpoints'}")
        return path
    candidates = [
        d
        for d in (runs.iterdir() if runs.is_dir() else [])
        if d.is_dir()
        and (exclude is None or d.resolve() != exclude.resolve())
        and CheckpointManager(d / "checkpoints").latest()
    ]
    if not candidates:
        raise FileNotFoundError(f"resume=true: no run with a checkpoint under {runs}")
    return max(
        candidates, key=lambda d: CheckpointManager(d / "checkpoints").latest().stat().st_mtime
    )


# random number generators ---------------------------------------------------------------------
def rng_state(env: Any = None) -> dict:
    """The global torch, numpy and python generator states, and the env's own
    (``env.rng_state()``, for envs that hold a generator: :class:`~physicsrl.envs.PhysicsEnv`)."""
    state = {
        "torch": torch.get_rng_state(),
        "numpy": np.random.get_state(),
        "python": random.getstate(),
    }
    if hasattr(env, "rng_state"):
        state["env"] = env.rng_state()
    return state


def set_rng_state(state: dict, env: Any = None) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    if "env" in state and hasattr(env, "set_rng_state"):
        env.set_rng_state(state["env"])
