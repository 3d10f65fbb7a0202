"""The fitter's defaults are the ones experiments/MODEL_CHOICE.md recommends from the measured studies.

Contract checked: the machine-readable `defaults` block of MODEL_CHOICE.md and the named constants of
jaxfoam/calibrate/settings.py state the same grid (cells across the largest domain extent), particles per cell,
CFL number and precision, and the fitter (FitSettings, `jaxfoam fit`, `build_problem`) actually uses them,
so the written advice and the code cannot drift apart.
"""
import argparse
import pytest
import math
import re
from pathlib import Path

import numpy as np

import fitting.settings as calibrate
from fitting import build_problem
from fitting.cli import add_fit_parser
from jaxfoam import Params
from jaxfoam._scene import init_state
from jaxfoam import stable_dt
from fitting import synthesize

from helpers import scene as zoo_scene

MODEL_CHOICE = Path(__file__).resolve().parents[2] / "experiments" / "MODEL_CHOICE.md"


def defaults_block() -> dict:
    """key -> value (str) from the ```defaults fenced block of MODEL_CHOICE.md."""
    text = MODEL_CHOICE.read_text()
    blocks = re.findall(r"```defaults\n(.*?)```", text, flags=re.S)
    assert len(blocks) == 1, "MODEL_CHOICE.md must hold exactly one ```defaults block"
    out = {}
    for line in blocks[0].splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            key, value = (part.strip() for part in line.split("=", 1))
            out[key] = value
    return out


def test_calibrate_constants_equal_the_model_choice_block():
    d = defaults_block()
    assert set(d) == {"cells_2d", "cells_3d", "ppc_2d", "ppc_3d", "cfl", "dtype"}
    assert calibrate.FIT_CELLS == {2: int(d["cells_2d"]), 3: int(d["cells_3d"])}
    assert calibrate.FIT_PPC == {2: int(d["ppc_2d"]), 3: int(d["ppc_3d"])}
    assert calibrate.FIT_CFL == float(d["cfl"])
    assert calibrate.FIT_DTYPE == d["dtype"]


@pytest.mark.slow
def test_fitter_uses_the_constants(tmp_path):
    """FitSettings, the `jaxfoam fit` parser and build_problem take their defaults from the constants."""
    assert calibrate.FitSettings().dtype == calibrate.FIT_DTYPE
    sub = argparse.ArgumentParser().add_subparsers()
    ap = add_fit_parser(sub)
    assert ap.get_default("dtype") == calibrate.FIT_DTYPE

    scene = zoo_scene("slump")
    data = synthesize(scene, {"mu": 150.0, "sigma_y": 25.0, "eta": 5.0, "m": 0.6}, dx=0.02, frames=2,
                      duration=0.01, noise=0.0, seed=0)
    problem = build_problem(data, calibrate.FitSettings(starts=1))
    assert math.isclose(problem.dx, 0.24 / calibrate.FIT_CELLS[2], rel_tol=1e-12)
    # The initial particles are sampled at FIT_PPC per cell (the count differs for any other ppc).
    sampled = init_state(problem.scene, problem.dx, calibrate.FIT_PPC[2], rho=80.0, seed=0)
    assert int(np.asarray(problem.sim.state0.active).sum()) == int(np.asarray(sampled.active).sum())
    # The time step is the FIT_CFL step of the stiffest admissible material (mu at its upper bound).
    p = Params(mu=calibrate.DEFAULT_BOUNDS["mu"][1], kappa=3000.0, sigma_y=1.0, eta=1.0, m=0.5, rho=80.0)
    expected = stable_dt(p, problem.dx, problem.sim.max_speed, calibrate.FIT_CFL)
    assert math.isclose(problem.sim.dt_cfl, expected, rel_tol=1e-9), (problem.sim.dt_cfl, expected)
    assert problem.sim.dtype == np.dtype(calibrate.FIT_DTYPE)
