"""The resolution guard: h against the front width, the expected CV error, the warning."""

from __future__ import annotations

import physicsrl.fem  # noqa: F401  (first: loads the MPI library that dolfinx links to)

# isort: split

import math
import warnings

import numpy as np
import pytest

from physicsrl.coordinated import Coordinator
from physicsrl.envs import load_config, make_env
from physicsrl.fem import resolution as guard
from physicsrl.fem.resolution import ResolutionWarning, cv_table


@pytest.mark.parametrize("scheme", ["implicit", "explicit"])
def test_the_report_grid_reads_its_row_of_the_table(scheme):
    """60 x 60 cells of side 100/60: h is the cell diagonal, the width sqrt(0.013 * 0.3), and
    the expected CV error is the table's entry for that ratio (a row of the table)."""
    mesh = physicsrl.fem.default_ms_mesh(n=60)
    r = guard.resolution(mesh, 0.013, 0.3, scheme)
    assert r.h == pytest.approx(math.sqrt(2) * 100 / 60, rel=1e-12)
    assert r.front_width == pytest.approx(math.sqrt(0.0039), rel=1e-12)
    ratios, errors = cv_table(scheme)
    row = np.argmin(abs(np.log(ratios / r.ratio)))
    assert ratios[row] == pytest.approx(r.ratio, rel=1e-4)
    assert r.cv_error == pytest.approx(errors[row], abs=1e-4)
    assert str(r).count("\n") == 0 and f"{r.cv_error:+.1%}" in str(r)


def build(capsys, *overrides):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        make_env(load_config("ms", "catheter", "atp", list(overrides)), Coordinator())
    return [w for w in caught if issubclass(w.category, ResolutionWarning)], capsys.readouterr()


def test_the_report_preset_warns_once_and_a_resolved_mesh_not(capsys, monkeypatch):
    """Building the report's 60 x 60 ATP env prints its resolution and warns once (one line),
    not again for a second env; a resolved mesh (h = 0.1, explicit: -2 % expected) prints
    and does not warn, nor does the 60 x 60 env with env.model.warn_resolution=false."""
    monkeypatch.setattr(guard, "_warned", False)
    quiet = ["env.model.warn_resolution=false"]
    resolved = [
        "env.mesh.cells=20",
        "env.mesh.extent=1.0",
        "env.model.scheme=explicit",
        "observation.distances=[0.75,0.65,0.35,0.25]",
    ]
    caught, out = build(capsys, *resolved)
    assert not caught and "expected planar CV error -2.2%" in out.out
    caught, _ = build(capsys, *quiet)
    assert not caught
    caught, out = build(capsys)
    assert len(caught) == 1 and "\n" not in str(caught[0].message)
    assert "resolution: h = 2.36" in out.out
    caught, _ = build(capsys)
    assert not caught
