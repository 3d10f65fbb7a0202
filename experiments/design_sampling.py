"""Which particles should make the predicted recording? `jaxfoam design --sampling same|other` against fits.

For the two recordings `experiments/design_study.py` synthesized and fitted (its results/design_study.json),
the design is run once more at the truth (one point, the fit's default grid) with the predicted recording
rendered from the fit's own particle sampling ("same") and from a second one ("other"), and each
predicted 95% half-width is divided by the one the fit achieved. Writes
experiments/results/design_sampling.md. Usage: python -m experiments design_sampling (after design_study).
"""
from __future__ import annotations

import json
import os
import sys

import jax

jax.config.update("jax_enable_x64", True)

from experiments._common import machine_line, md_table, write_md  # noqa: E402
from fitting.design import SAMPLINGS, Variable, design  # noqa: E402

HERE = os.path.dirname(__file__)
SCENE = os.path.join(HERE, "scenes", "hanging_plate_2d.json")
NAMES = ("mu", "sigma_y", "eta", "m")


def main(argv=None):
    with open(os.path.join(HERE, "results", "design_study.json")) as fh:
        study = json.load(fh)
    rows = []
    for label, fit in study["fits"].items():
        variables = [Variable(k, (v,)) for k, v in fit["values"].items()]
        for sampling in SAMPLINGS:
            hw = design(SCENE, study["material"], variables, points=1, sampling=sampling).best["half_width"]
            ratios = [hw[n] / fit["achieved_half_width"][n] for n in NAMES]
            rows.append([label, sampling] + [f"{r:.2f}" for r in ratios])
            print(label, sampling, [round(r, 3) for r in ratios], flush=True)
    body = ("Predicted half-width at the truth / the half-width the fit of `design_study.py` achieved (its "
            f"statistical interval at its optimum), per parameter; material {study['material']}.\n\n"
            + md_table(["recording", "sampling"] + list(NAMES), rows) + "\n")
    write_md("design_sampling", False, "Predicted against achieved half-widths, by the predicted recording's particles",
             body)
    print(machine_line())
    return 0


if __name__ == "__main__":
    sys.exit(main())
