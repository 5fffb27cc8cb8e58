"""Name -> class registries, so that a config's ``name`` field selects an implementation.

Adding an observation, a reward or a task is one class decorated with
``@REGISTRY.register("name")`` plus one YAML file whose ``name`` is that name; the other keys of
the YAML are the class's config fields (see :func:`physicsrl.checks.build`). A class
outside the package is found through the YAML's ``module`` key: a module name
(``mylab.tasks``) or a ``.py`` file (relative to the working directory) imported, once, before
the name is looked up (``examples/thermostat.py`` and its YAML in ``examples/conf/``).

:func:`shipped` finds the shipped YAML files, :func:`shipped_option` reads one onto its base
(``ms_resolved`` onto ``ms``) and :func:`load_config` composes them without Hydra (torch-free,
like the registries: the commands check settings before importing torch).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from physicsrl.checks import plain


class Registry:
    """Classes registered under names, for one config group (``observation``, ...)."""

    def __init__(self, group: str):
        self.group = group
        self.classes: dict[str, type] = {}

    def register(self, name: str) -> Callable[[type], type]:
        def decorate(cls: type) -> type:
            if name in self.classes:
                raise ValueError(f"{self.group} {name!r} is already registered")
            self.classes[name] = cls
            cls.name = name
            return cls

        return decorate

    def lookup(self, cfg: Mapping | Any) -> tuple[type, dict]:
        """The class named by ``cfg.name`` and the remaining settings, as a plain dict."""
        settings = plain(cfg)
        if not isinstance(settings, Mapping) or "name" not in settings:
            raise ValueError(f"{self.group} must be a mapping with a 'name', got {settings!r}")
        settings = dict(settings)
        name = settings.pop("name")
        import_module_of(self.group, settings)
        settings.pop("module", None)
        if name not in self.classes:
            known = ", ".join(sorted(self.classes))
            raise ValueError(f"{self.group}.name {name!r} is unknown; registered: {known}")
        return self.classes[name], settings


def import_module_of(group: str, settings: Mapping) -> None:
    """Import the ``module`` a config group's settings name, if any (ValueError naming
    ``group.module`` if it cannot be imported)."""
    module = settings.get("module")
    if module is None:
        return
    from physicsrl.imports import import_source

    try:
        import_source(str(module))
    except (ImportError, OSError) as error:
        raise ValueError(f"{group}.module {module!r} cannot be imported: {error}") from error


def shipped(group: str, option: str) -> str:
    """The path of the shipped YAML ``conf/<group>/<option>.yaml``: in the package
    ``physicsrl.conf`` when installed, the repository's ``conf/`` in a checkout (where a stray
    ``physicsrl/conf`` folder may shadow the editable mapping); ValueError naming the group's
    options if absent."""
    from importlib.resources import files
    from pathlib import Path

    candidates = [files("physicsrl.conf"), Path(__file__).resolve().parents[2] / "conf"]
    for root in candidates:
        if (root / "env" / "heat.yaml").is_file():
            path = root / group / f"{option}.yaml"
            if not path.is_file():
                yamls = (p.name for p in (root / group).iterdir() if p.name.endswith(".yaml"))
                options = ", ".join(sorted(name.removesuffix(".yaml") for name in yamls))
                raise ValueError(f"{group}={option}: no such option (choose one of {options})")
            return str(path)
    raise FileNotFoundError("the physicsrl configs (conf/env/heat.yaml) are not installed")


def load_config(
    env: str = "heat",
    observation: str | None = None,
    reward: str | None = None,
    overrides: tuple[str, ...] | list[str] = (),
    seed: int | None = None,
):
    """The config of ``make_env`` from the shipped YAML files (``physicsrl.conf``), without
    Hydra: the task ``env``, the ``observation`` and ``reward`` options (None: those the task's
    YAML chooses, as on the command line: ``catheter`` and ``atp`` for ``ms``), the seed and
    ``physicsrl-train``'s cap on a simulator's memory per rank (``max_memory_gb``), and
    ``overrides``, dotted ``key=value`` strings, e.g. ``"env.mesh.cells=20"``.

    For scripts, tests and examples; Hydra commands compose the same groups themselves.
    """
    from omegaconf import OmegaConf

    from physicsrl.config import parse_overrides, train_default

    groups = {"env": env, **chosen_options(env)}
    groups |= {g: o for g, o in (("observation", observation), ("reward", reward)) if o}
    cfg = OmegaConf.create({g: shipped_option(g, n) for g, n in groups.items()})
    cfg.seed, cfg.max_memory_gb = seed, train_default("max_memory_gb")
    changes = parse_overrides(overrides)
    unknown = sorted(set(changes) - set(cfg))
    if unknown:
        raise ValueError(f"overrides: {unknown[0]!r} is not one of {', '.join(cfg)}")
    return OmegaConf.merge(cfg, changes)


def chosen_options(env: str) -> dict[str, str]:
    """The options of other groups that the shipped task ``env``'s defaults list chooses
    (``override /observation@_global_.observation: catheter``), those of the task it extends
    (``ms_resolved``: ``ms``) first."""
    from omegaconf import OmegaConf

    chosen: dict[str, str] = {}
    for entry in OmegaConf.load(shipped("env", env)).get("defaults", []):
        if isinstance(entry, str):
            chosen |= {} if entry == "_self_" else chosen_options(entry)
        else:
            chosen |= {key.split("@")[0].split("/")[-1]: value for key, value in entry.items()}
    return chosen


def shipped_option(group: str, option: str):
    """The shipped ``conf/<group>/<option>.yaml`` merged onto the options of the same group that
    its defaults list names, in that list's order (``_self_`` last unless placed), as Hydra
    composes it: ``ms_resolved`` is ``ms`` changed. The entries that choose other groups (an
    env's observation and reward) are left out."""
    from omegaconf import OmegaConf

    node = OmegaConf.load(shipped(group, option))
    defaults = list(node.pop("defaults", []))
    if "_self_" not in defaults:
        defaults.append("_self_")
    parts = [
        node if d == "_self_" else shipped_option(group, d) for d in defaults if isinstance(d, str)
    ]
    return OmegaConf.merge(*parts)
