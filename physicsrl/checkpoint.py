"""Training checkpoints on TorchRL's ``torchrl.checkpoint``, and the run directory to resume.

A run's checkpoints are TorchRL archives ``checkpoints/ckpt-<iteration, 12 digits>.torchrl``
(one ZIP file each: a JSON manifest and one payload per component), written by a
:class:`~torchrl.checkpoint.Checkpoint` and rotated by a
:class:`~torchrl.checkpoint.CheckpointRotation` that keeps the newest ``keep``. TorchRL stages
every save under a temporary name, publishes it with ``os.replace`` and removes its temporary
files when a save fails, so a kill at any moment leaves complete checkpoints only. Added here,
what TorchRL does not do:

- :meth:`Checkpoints.save` syncs the published archive and its directory to disk;
- :meth:`Checkpoints.check_writable` finds a directory that cannot be written when the run
  starts, not at its first save;
- :meth:`Checkpoints.newest_readable` skips damaged checkpoints (the newest one truncated by a
  full disk or a crash while copying), with one warning naming each;
- :func:`read`: a checkpoint's stored states without the objects they came from.

The run directory that ``resume=`` names is found by
:func:`physicsrl.run_directory.find_run`, before torch loads.
"""

from __future__ import annotations

import logging
import os
import tempfile
import zipfile
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from torchrl.checkpoint import (
    Checkpoint,
    CheckpointError,
    CheckpointRotation,
    JSONCheckpointAdapter,
    StateDictCheckpointAdapter,
)

__all__ = ["Checkpoints", "State", "read", "CheckpointsError"]

log = logging.getLogger("physicsrl.checkpoint")

PREFIX = "ckpt"  # checkpoints/ckpt-000000000010.torchrl
SUFFIX = ".torchrl"  # TorchRL's name for its archive format


class CheckpointsError(OSError):
    """A checkpoint directory that cannot be written, or holds no readable checkpoint."""


class State:
    """A checkpoint component made of a getter and a setter, for state that is not an object
    with ``state_dict``/``load_state_dict`` of its own (counters, generator states)."""

    def __init__(self, get: Callable[[], Any] | None, set: Callable[[Any], None]):
        self.get, self.set = get, set

    def state_dict(self) -> Any:
        return self.get()

    def load_state_dict(self, state: Any) -> None:
        self.set(state)


class Checkpoints:
    """The checkpoints of one run directory's ``checkpoints/``, the newest ``keep`` kept."""

    def __init__(self, directory: str | Path, keep: int):
        self.rotation = CheckpointRotation(directory, keep_last=int(keep), prefix=PREFIX)
        self.directory = self.rotation.directory

    def paths(self) -> list[Path]:
        """The checkpoint files, readable or not, oldest first."""
        if not self.directory.is_dir():
            return []
        return sorted(self.directory.glob(f"{PREFIX}-{'[0-9]' * 12}{SUFFIX}"))

    def latest(self) -> Path | None:
        paths = self.paths()
        return paths[-1] if paths else None

    def check_writable(self) -> None:
        """Create the directory and a file in it, or raise :class:`CheckpointsError`."""
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            with tempfile.NamedTemporaryFile(dir=self.directory, prefix=".probe-"):
                pass
        except OSError as error:
            raise self._unwritable(error) from error

    def _unwritable(self, error: OSError) -> CheckpointsError:
        return CheckpointsError(
            f"cannot write checkpoints to {self.directory}: {error.strerror or error}"
        )

    def save(self, checkpoint: Checkpoint, iteration: int) -> Path:
        """Write ``checkpoint`` as iteration ``iteration``'s, on disk when this returns (a failed
        save raises :class:`CheckpointsError` and leaves the older checkpoints as they were)."""
        try:
            path = self.rotation.save(checkpoint, step=int(iteration))
            for synced in (path, self.directory):  # TorchRL publishes without syncing
                descriptor = os.open(synced, os.O_RDONLY)
                try:
                    os.fsync(descriptor)
                finally:
                    os.close(descriptor)
        except OSError as error:
            raise self._unwritable(error) from error
        return path

    def newest_readable(self) -> Path:
        """The newest checkpoint whose archive is intact (manifest and checksums), after one
        warning per damaged newer one; none intact: :class:`CheckpointsError` naming them."""
        damaged: dict[Path, str] = {}
        for path in reversed(self.paths()):
            problem = damage(path)
            if problem is None:
                for bad, why in damaged.items():
                    log.warning("skipping unreadable checkpoint %s: %s", bad, why)
                return path
            damaged[path] = problem
        found = ", ".join(path.name for path in damaged) or "none there"
        raise CheckpointsError(f"no readable checkpoint in {self.directory}: {found}")


def damage(path: Path) -> str | None:
    """What is wrong with the checkpoint archive ``path`` (None: it is intact)."""
    try:
        Checkpoint.manifest(path)
        with zipfile.ZipFile(path) as archive:
            member = archive.testzip()  # reads every member, checking its CRC
    except (CheckpointError, OSError, EOFError, zipfile.BadZipFile) as error:
        return " ".join(str(error).split()) or type(error).__name__
    return None if member is None else f"{member} is corrupt"


def read(path: str | Path, names: Iterable[str] | None = None) -> dict:
    """The states stored in the checkpoint ``path`` (all components, or ``names``), by component
    name: state dicts and JSON values, without the objects they came from."""
    components = Checkpoint.manifest(path)["components"]
    names = list(components if names is None else names)
    states: dict[str, Any] = {}
    checkpoint = Checkpoint()
    for name in names:
        if components[name]["adapter"] == StateDictCheckpointAdapter.adapter_id:
            capture = State(None, lambda state, name=name: states.__setitem__(name, state))
            checkpoint.register(name, capture, adapter=StateDictCheckpointAdapter())
        else:
            checkpoint.register(name, None, adapter=JSONCheckpointAdapter())
    loaded = checkpoint.load(path, map_location="cpu")
    return {name: states[name] if name in states else loaded.values.get(name) for name in names}
