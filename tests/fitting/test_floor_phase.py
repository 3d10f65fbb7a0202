"""Where the fit grid's node rows lie against the floor (`FitSettings.floor_phase`, `--floor-phase`).

Contracts: the floor lies the asked fraction of a cell above a node row at any dx, with the grid spacing,
the floor and the domain's top those of the scene; by default the rows are the domain's (a floor at its
lower bound on a row); a phase outside [0, 1) is refused naming the field; and what the option changes:
at dx 5 mm foam landed on a Coulomb floor rests with its edge within a quarter cell of the floor at half
a cell, where with a row on the floor it rests more than a quarter cell above it.
"""
import dataclasses
import json

import h5py
import numpy as np
import pytest

from fitting import CalibrationError, FitSettings, build_problem, calibrate, synthesize
from fitting.driver import _same_fit
from helpers import edited, scene as zoo_scene

TRUTH = {"mu": 150.0, "sigma_y": 60.0, "eta": 5.0, "m": 0.6}
DROP = zoo_scene("drop")          # Coulomb floor (friction 0.5) at y = 0, the domain's lower bound


@pytest.fixture(scope="module")
def drop_data():
    return synthesize(DROP, TRUTH, dx=0.01, frames=4, duration=0.6, noise=0.0, seed=0)


@pytest.mark.parametrize("phase", [0.0, 0.25, 0.5, 0.75])
@pytest.mark.parametrize("dx", [0.01, 0.007])
def test_floor_lies_the_asked_fraction_of_a_cell_above_a_row(drop_data, phase, dx):
    problem = build_problem(drop_data, FitSettings(dx=dx, floor_phase=phase, dx_check=False))
    grid = problem.sim.model.grid
    cells = (problem.scene.floor_y - grid.origin[1]) / grid.dx
    assert problem.floor_phase == pytest.approx(phase, abs=1e-9)
    assert (cells - np.floor(cells + 1e-9)) % 1.0 == pytest.approx(phase, abs=1e-9)
    assert grid.dx == dx
    assert problem.scene.floor_y == 0.0 and problem.scene.domain_max == tuple(DROP["domain"]["max"])


def test_default_keeps_the_domains_rows(drop_data):
    """By default the rows lie at the domain's lower bound + k dx, as in `jaxfoam simulate` and
    `synthesize`: a floor at that bound lies on a row, one above it where the spacing puts it; an
    explicit phase moves the rows for a sticky floor as for a Coulomb one."""
    assert FitSettings().floor_phase is None
    assert build_problem(drop_data, FitSettings(dx=0.007, dx_check=False)).floor_phase == 0.0
    raised = edited(edited(DROP, ("floor", "y"), 0.0125), ("initial_shape", "min", 1), 0.1125)
    data = synthesize(raised, TRUTH, dx=0.02, frames=2, duration=0.1, seed=0)
    problem = build_problem(data, FitSettings(dx=0.01, dx_check=False))
    assert problem.floor_phase == pytest.approx(0.25) and problem.scene.domain_min == (0.0, 0.0)
    data = synthesize(edited(DROP, ("floor",), {"y": 0.0, "friction": "sticky"}), TRUTH, dx=0.02, frames=2,
                      duration=0.1, seed=0)
    assert build_problem(data, FitSettings(dx=0.02, floor_phase=0.5, dx_check=False)).floor_phase == 0.5


@pytest.mark.parametrize("bad", [1.0, -0.1, float("nan"), "half", True])
def test_floor_phase_outside_a_cell_is_refused(bad):
    with pytest.raises(CalibrationError, match=r"floor_phase must be None or a fraction of a cell in \[0, 1\)"):
        FitSettings(floor_phase=bad).validate()


@pytest.mark.slow
def test_landed_foam_rests_on_a_coulomb_floor_at_half_a_cell(drop_data):
    """The lowest particle's extent (a quarter cell at 4 ppc) ends within a quarter cell of the floor at
    floor_phase 0.5 (dx 5 mm: measured 0.06 cells below it) and more than a quarter above it with a
    row on the floor (0.40 cells above)."""
    dx = 0.005
    edge = {}
    for phase in (0.0, 0.5):
        problem = build_problem(drop_data, FitSettings(dx=dx, floor_phase=phase, dx_check=False))
        x, active = problem.simulate(TRUTH)
        edge[phase] = (np.min(x[-1][active[-1].astype(bool), 1]) - problem.scene.floor_y) / dx - 0.25
    assert abs(edge[0.5]) < 0.25
    assert edge[0.0] > 0.25


def test_a_log_of_another_floor_phase_is_not_resumed(tmp_path):
    """The grid's phase is part of what a fit log must match: the same data and settings on rows moved by
    half a cell are another fit; a log written before the option existed matches the default only."""
    data = synthesize(DROP, TRUTH, dx=0.02, frames=3, duration=0.2, seed=0)
    settings = FitSettings(dx=0.02, fixed={"mu": 150.0, "eta": 5.0, "m": 0.6}, starts=1, max_iter=1, dx_check=False)
    log = tmp_path / "fit.fitlog.h5"
    calibrate(data, settings, log=log)
    with pytest.raises(CalibrationError, match="cannot resume: the log was written for other data or settings"):
        calibrate(data, dataclasses.replace(settings, floor_phase=0.5), log=log, resume=True)
    with h5py.File(log, "r") as f:
        logged = json.loads(f.attrs["calibration"])
    assert logged["floor_phase"] == 0.0 and logged["settings"]["floor_phase"] is None
    old = {k: v for k, v in logged.items() if k != "floor_phase"}
    old["settings"] = {k: v for k, v in old["settings"].items() if k != "floor_phase"}
    assert _same_fit(old, logged)
    moved = dict(logged, floor_phase=0.5, settings=dict(logged["settings"], floor_phase=0.5))
    assert not _same_fit(old, moved)


@pytest.mark.parametrize("command", [["fit", "data.h5", "--out", "fit.json"], ["design", "scene.json"]])
def test_command_line_refuses_a_floor_phase_outside_a_cell(command, capsys):
    """`jaxfoam fit` and `jaxfoam design` refuse --floor-phase 1.5 before reading any file (exit 2)."""
    from jaxfoam.cli import main
    with pytest.raises(SystemExit) as exc:
        main(command + ["--floor-phase", "1.5"])
    assert exc.value.code == 2
    assert "argument --floor-phase: must be a finite number in [0, 1) cells, got '1.5'" in capsys.readouterr().err
