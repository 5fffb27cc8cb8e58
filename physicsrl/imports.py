"""The code a config names: an object by ``"module:name"`` or ``"file.py:name"``
(``env.factory``, a command's job) and a module by name or file (``env.module``, a task's
registration). No torch: every rank of a command loads its job through it.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from pathlib import Path
from typing import Any


def load_object(spec: str) -> Any:
    """``"package.module:name"`` or ``"/path/to/file.py:name"`` -> the named object."""
    where, _, name = spec.rpartition(":")
    if not where or not name:
        raise ValueError(f"{spec!r}: expected 'module:name' or 'file.py:name'")
    return getattr(import_source(where), name)


def import_source(where: str) -> Any:
    """The module ``where`` names: ``"package.module"``, or a ``.py`` file executed once per
    process (as the module ``_physicsrl_<stem>``; a second call returns the same module)."""
    if not where.endswith(".py"):
        return importlib.import_module(where)
    path = Path(where).expanduser().resolve()
    name = f"_physicsrl_{path.stem}"
    loaded = sys.modules.get(name)
    if loaded is not None and Path(loaded.__file__) == path:
        return loaded
    if not path.is_file():
        raise ImportError(f"no file {path}")
    module_spec = importlib.util.spec_from_file_location(name, path)
    if module_spec is None or module_spec.loader is None:
        raise ImportError(f"cannot import {path}")
    module = importlib.util.module_from_spec(module_spec)
    sys.modules[name] = module  # before running it: its classes register once
    try:
        module_spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise
    return module
